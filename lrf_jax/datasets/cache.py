"""Process-wide cache of parsed files: each file is parsed once per process.

Cached arrays are made read-only, so a caller cannot corrupt the cache by writing into a
result (copy first: `np.array(mesh.points)`). The cache key includes the file's size and
modification time, so an edited file is read again. `clear_cache()` empties it.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lrf_jax.io import read_cloud
from lrf_jax.geometry.resolution import MrDefinition, mesh_resolution

if TYPE_CHECKING:
  from typing import TypeVar

  _Array = TypeVar("_Array", bound=np.ndarray | None)  # an array stays one, None stays None


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
  """A parsed, cached mesh or cloud with its mesh resolution.

  Attributes:
    points: (n, 3) float64, read-only (units as stored).
    faces: (f, 3) int64 read-only, or None for a cloud.
    mr: mesh resolution in the points' units.
    mr_definition: "mean_edge_length" (mesh) or "mean_nn_distance" (cloud).
    path: the file.
  """

  points: np.ndarray
  faces: np.ndarray | None
  mr: float
  mr_definition: MrDefinition
  path: Path


def _frozen(a: _Array) -> _Array:
  if a is not None:
    a.flags.writeable = False
  return a


@functools.lru_cache(maxsize=64)  # about 5 MB a BR scene: bounded by a few hundred MB
def _load(path: str, mtime_ns: int, size: int) -> Mesh:
  del mtime_ns, size  # only part of the cache key
  cloud = read_cloud(path)
  mr, definition = mesh_resolution(cloud.points, cloud.faces)
  return Mesh(_frozen(cloud.points), _frozen(cloud.faces), mr, definition, Path(path))


def load_mesh(path: str | os.PathLike) -> Mesh:
  """Reads a mesh or cloud (any `read_cloud` format) once per process and caches it.

  Args:
    path: the file.

  Returns:
    The cached Mesh (read-only arrays; mr computed from the file's own geometry).
  """
  p = Path(path).resolve()
  st = p.stat()
  return _load(str(p), st.st_mtime_ns, st.st_size)


def cache_info() -> functools._CacheInfo:
  """Hits, misses and size of the file cache (each miss is one parse)."""
  return _load.cache_info()


def clear_cache() -> None:
  """Forgets every cached file."""
  _load.cache_clear()
