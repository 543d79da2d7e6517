"""The chunk loop shared by the batched host -> jit paths: pad, run, slice, concatenate."""

from __future__ import annotations

from typing import Any
from collections.abc import Callable

from lrf_jax._jax import jnp
import numpy as np


def map_chunks(fn: Callable[[np.ndarray, int], tuple[Any, ...]], n: int, chunk: int, *,
               pad: bool = True, progress: bool = False, desc: str = "") -> tuple[Any, ...]:
  """Run `fn` over consecutive chunks of `range(n)` and concatenate its outputs.

  Args:
    fn: `fn(idx, n_real) -> tuple of arrays`, each with leading axis `len(idx)`: `idx` holds the
      chunk's positions, padded (with `pad`) to `chunk` entries by repeating its first one so
      that every call has the compiled shape; `n_real` of them are real.
    n: number of items (> 0).
    chunk: items per call (> 0).
    pad: pad the last chunk to `chunk` entries.
    progress: show a progress bar over the chunks.
    desc: the bar's label.

  Returns:
    fn's outputs over all chunks, the padding sliced off, each concatenated along axis 0.
  """
  starts = range(0, n, chunk)
  if progress:
    from tqdm.auto import tqdm
    starts = tqdm(starts, desc=desc, unit="chunk", dynamic_ncols=True)
  parts = []
  for start in starts:
    idx = np.arange(start, min(start + chunk, n))
    n_real = idx.size
    if pad and n_real < chunk:
      idx = np.concatenate([idx, np.full(chunk - n_real, idx[0])])
    outs = fn(idx, n_real)
    parts.append(tuple(out if len(out) == n_real else out[:n_real] for out in outs))
  if len(parts) == 1:  # one call: nothing to slice or concatenate (no eager op to compile)
    return parts[0]
  return tuple(jnp.concatenate(outs) for outs in zip(*parts))
