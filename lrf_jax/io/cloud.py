"""`Cloud`, the common result of the readers, and `read_npy` (KITTI's `.bin` sweeps: `sweeps`)."""

from __future__ import annotations

import dataclasses
import os
import tokenize
from typing import Any
from pathlib import Path

import numpy as np

from lrf_jax.io.validation import bad_input, check_normals, check_points, require_file


@dataclasses.dataclass(frozen=True, eq=False)
class Cloud:
  """A point cloud or triangle mesh read from a file (units as stored in the file).

  Attributes:
    points: (n, 3) float64 coordinates.
    faces: (f, 3) int64 vertex indices of triangles, or None for a cloud.
    normals: (n, 3) float64 per-point normals as stored (not renormalised), or None.
    path: the file it was read from, or None.
  """

  points: np.ndarray
  faces: np.ndarray | None = None
  normals: np.ndarray | None = None
  path: Path | None = None

  def __len__(self) -> int:
    return int(self.points.shape[0])


def read_npy(path: str | os.PathLike) -> Cloud:
  """Reads a `.npy` array of shape (n, 3) (x y z) or (n, 6) (x y z nx ny nz).

  Args:
    path: the `.npy` file (no pickles are loaded).

  Returns:
    A Cloud with float64 points (and normals for 6 columns; a row with a NaN/inf normal is
    kept with a NaN normal row).

  Raises:
    FileNotFoundError: missing file.
    ValueError: unreadable file (e.g. no read permission), a header shape that does not match
      the data stored (larger or smaller), a dtype that is not real floating or integer
      (complex, bool, strings), wrong shape, empty, or non-finite coordinates.
  """
  p = require_file(path)
  try:  # memory-mapped first: the header's shape is checked against the file before loading
    arr = np.load(p, allow_pickle=False, mmap_mode="r")
  except (ValueError, OSError, EOFError, OverflowError, SyntaxError, tokenize.TokenError) as e:
    # numpy: SyntaxError/TokenError for a garbled header dict, OverflowError for a negative shape
    raise bad_input(p, "array", "a numeric .npy array",
                    f"an unreadable file ({type(e).__name__}: {e})") from e
  if not isinstance(arr, np.ndarray):  # np.load opens a zip (an .npz) whatever the suffix
    names = ", ".join(getattr(arr, "files", [])[:8]) or "none"
    getattr(arr, "close", lambda: None)()
    raise bad_input(p, "array", "a numeric .npy array",
                    f"an .npz archive (arrays: {names}); save one (n, 3) array with "
                    "numpy.save, or extract it")
  mapped: Any = arr  # a np.memmap (mmap_mode): its header's length is `offset`
  stored = p.stat().st_size - mapped.offset
  if stored != arr.nbytes:  # np.load ignores data after the header's shape
    raise bad_input(p, "shape", f"{arr.nbytes} bytes of data for shape {arr.shape} and dtype "
                    f"{arr.dtype} (header)", f"{stored} bytes stored")
  if arr.dtype.kind not in "fiu":
    raise bad_input(p, "dtype", "real floating or integer values", f"dtype {arr.dtype}")
  if arr.ndim != 2 or arr.shape[1] not in (3, 6):
    raise bad_input(p, "array", "shape (n, 3) or (n, 6)", f"shape {arr.shape}")
  arr = np.asarray(arr)
  points = check_points(arr[:, :3], p, "x/y/z columns")
  normals = check_normals(arr[:, 3:], p, "normal columns") if arr.shape[1] == 6 else None
  return Cloud(points, None, normals, p)
