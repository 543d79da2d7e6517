"""`Cloud`, the common result of the readers, and `read_cloud`, which dispatches on the suffix."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from lrf_jax.io.validation import bad_input, check_points, require_file


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
    A Cloud with float64 points (and normals for 6 columns).

  Raises:
    FileNotFoundError: missing file.
    ValueError: unreadable file, a header shape larger than the file, a dtype that is not real
      floating or integer (complex, bool, strings), wrong shape, empty, or non-finite values.
  """
  p = require_file(path)
  try:  # memory-mapped first: the header's shape is checked against the file before loading
    arr = np.load(p, allow_pickle=False, mmap_mode="r")
  except (ValueError, OSError, EOFError) as e:
    raise bad_input(p, "array", "a numeric .npy array", f"an unreadable file ({e})") from e
  if arr.dtype.kind not in "fiu":
    raise bad_input(p, "dtype", "real floating or integer values", f"dtype {arr.dtype}")
  if arr.ndim != 2 or arr.shape[1] not in (3, 6):
    raise bad_input(p, "array", "shape (n, 3) or (n, 6)", f"shape {arr.shape}")
  arr = np.asarray(arr)
  points = check_points(arr[:, :3], p, "x/y/z columns")
  normals = check_points(arr[:, 3:], p, "normal columns") if arr.shape[1] == 6 else None
  return Cloud(points, None, normals, p)


_TEXT_SUFFIXES = (".xyz", ".txt", ".pts", ".asc")


def read_cloud(path: str | os.PathLike) -> Cloud:
  """Reads any supported point-cloud or mesh file, choosing the reader by suffix.

  Supported: `.ply` (`read_ply`), `.pcd` (`read_pcd`), `.npy` (`read_npy`) and whitespace text
  `.xyz/.txt/.pts/.asc`, optionally gzip-compressed with a further `.gz` (`read_xyz`).

  Args:
    path: the file.

  Returns:
    A Cloud (faces only for PLY meshes; normals where the file stores them).

  Raises:
    FileNotFoundError: missing file.
    ValueError: unsupported suffix, or any error of the chosen reader.
  """
  # Local imports: the readers import this module for `Cloud`.
  from lrf_jax.io.pcd import read_pcd
  from lrf_jax.io.ply import read_ply
  from lrf_jax.io.text import read_xyz

  p = require_file(path)
  suffixes = [s.lower() for s in p.suffixes]
  last = suffixes[-1] if suffixes else ""
  if last == ".gz" and len(suffixes) >= 2:
    last = suffixes[-2]
    if last not in _TEXT_SUFFIXES:
      raise bad_input(p, "suffix", "a text cloud when gzip'ed (" + ", ".join(_TEXT_SUFFIXES)
                      + " + .gz)", f"{suffixes[-2]}.gz")
  if last == ".ply":
    return read_ply(p).to_cloud()
  if last == ".pcd":
    return read_pcd(p)
  if last == ".npy":
    return read_npy(p)
  if last in _TEXT_SUFFIXES:
    return read_xyz(p)
  raise bad_input(p, "suffix", "one of .ply, .pcd, .npy, " + ", ".join(_TEXT_SUFFIXES)
                  + " (text optionally .gz)", repr("".join(p.suffixes) or "(none)"))
