"""What the normal-based LRFs (mian, board, flare, ps) share: their host `prepare` hook and the
batched evaluation of their one-keypoint frame functions.

The hook is numpy, outside jit: it gathers the per-point normals (the caller's, else estimated by
`lrf_jax.geometry.normals.estimate_normals`) into the patch slots, for the jitted frame functions.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple
from collections.abc import Callable

import numpy as np

from lrf_jax._jax import jax
from lrf_jax.frames.spec import KEYPOINT, SLOT
from lrf_jax.geometry import ops as geometry
from lrf_jax.geometry.normals import default_normals

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray, Patches


class NormalExtra(NamedTuple):
  """`extra` of the normal-based LRFs: normals of the patch slots and of the keypoint."""

  normals: AnyArray    # (N, K, 3) float32, 0 in padding, NaN where undefined
  kp_normal: AnyArray  # (N, 3) float32
  # A class attribute, not a field: mypy takes it for a field (hence the ignores here and on
  # the constructor calls).
  AXES = {"normals": SLOT, "kp_normal": KEYPOINT}  # type: ignore[misc]


def usable_normals(normals: np.ndarray, dtype: type = np.float64) -> np.ndarray:
  """Normals with the rows that carry no direction marked missing: a row that is all zero (the
  usual placeholder of files without normals) or not finite becomes NaN, which every
  normal-based method skips (a frame whose normals are all missing is invalid).

  Args:
    normals: (n, 3) per-point normals.
    dtype: the returned dtype.

  Returns:
    (n, 3) C-contiguous array of `dtype` (the input itself when nothing is missing and it already
    has that layout).
  """
  nrm: np.ndarray = np.ascontiguousarray(normals, dtype)
  missing = ~(np.isfinite(nrm).all(axis=1) & (nrm != 0).any(axis=1))
  if missing.any():
    nrm = nrm.copy()
    nrm[missing] = np.nan
  return nrm


def prepare_normals(points: np.ndarray, keypoints: np.ndarray, patches, *,
                    faces: np.ndarray | None = None, normals: np.ndarray | None = None,
                    radius: float) -> NormalExtra:
  """`MethodSpec.prepare` hook of the normal-based LRFs: their `NormalExtra`.

  Args:
    points: (n, 3) cloud.
    keypoints: (N,) indices.
    patches: their `Patches` (K slots).
    faces: optional (f, 3) triangles (used to orient estimated normals).
    normals: optional (n, 3) normals; None = `estimate_normals`.
    radius: the support radius r.

  Returns:
    `NormalExtra`: (N, K, 3) float32 normals of the patch slots (0 in padding, NaN where
    undefined: not finite or all zero, `usable_normals`) and the (N, 3) float32 normal of each
    keypoint.
  """
  nrm = usable_normals(default_normals(points, radius, faces, normals), np.float32)
  idx = np.asarray(patches.indices)
  gathered = nrm[np.maximum(idx, 0)]
  gathered[idx < 0] = 0.0
  return NormalExtra(gathered, nrm[np.asarray(keypoints)])  # type: ignore[call-arg]  # AXES


def batch_frames(frame: Callable[..., Any], patches: Patches, fields: tuple[str, ...],
                 *rows: AnyArray) -> tuple[jax.Array, jax.Array]:
  """A one-keypoint frame function over a batch (pure, jittable).

  Args:
    frame: `frame(*fields of one keypoint, *rows of one keypoint) -> (frame (3, 3), valid ())`.
    patches: `Patches` (N keypoints); their non-finite inputs are zeroed (`geometry.sanitize`)
      before `frame` reads them.
    fields: the names of the `Patches` fields `frame` reads first, in its order (e.g.
      ("offsets", "mask")).
    *rows: per-keypoint arrays (N, ...) `frame` reads after them (e.g. the keypoints' normals).

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool): the identity and False also where a
    keypoint's inputs were not finite.
  """
  patches, finite = geometry.sanitize(patches)
  frames, valid = jax.vmap(frame)(*(getattr(patches, name) for name in fields), *rows)
  valid = valid & finite
  return geometry.identity_where_invalid(frames, valid), valid
