"""Process-wide cache of parsed files: each file is parsed once per process.

Cached arrays are made read-only, so a caller cannot corrupt the cache by writing into a
result (copy first: `np.array(mesh.points)`). The cache key includes the file's size and
modification time, so an edited file is read again. `clear_cache()` empties it.

`load_mesh` reads a file as stored, with its `mesh_resolution`. `load_scan` reads a scan of a
user's scan set (`lrf_jax.datasets.scan_sets`) at its working resolution
(`lrf_jax.geometry.resolution.working_resolution`), thinned where it is far denser than that (a
raw LiDAR sweep's near field); what that costs (a nearest-neighbor pass, the thinning) is also
kept on disk, under `default_cache_dir()`, so a second process reads an `.npz`.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lrf_jax.io import atomic, read_cloud
from lrf_jax.geometry.resolution import (MrDefinition, Resolution, mesh_resolution,
                                         working_resolution)
from lrf_jax.geometry.sampling import thin_cloud, thinning_voxel_size

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
  """Forgets every cached file (`load_mesh`'s and `load_scan`'s; the disk cache stays)."""
  _load.cache_clear()
  _load_scan.cache_clear()


def default_cache_dir() -> Path:
  """$LRF_CACHE, else $XDG_CACHE_HOME/lrf_jax, else ~/.cache/lrf_jax."""
  if os.environ.get("LRF_CACHE"):
    return Path(os.environ["LRF_CACHE"]).expanduser()
  base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
  return Path(base).expanduser() / "lrf_jax"


# Bumped whenever what `load_scan` computes changes: older .npz files are then not read.
_SCAN_CACHE_VERSION = 1


@dataclasses.dataclass(frozen=True, eq=False)
class Scan:
  """A scan at its working resolution: read, measured and (where far denser) thinned.

  Attributes:
    points: (m, 3) float64, read-only: the file's points, or their voxel centroids where the
      scan was thinned (units as stored).
    faces: (f, 3) int64 read-only, or None (a cloud, or a thinned mesh).
    resolution: its `working_resolution` (measured on the points as stored): `mr` is the mean
      nearest-neighbor distance of an even cloud, the mean edge length of a mesh, the
      area-weighted median spacing of an uneven one (a raw LiDAR sweep).
    voxel: the thinning voxel edge (`sampling.thinning_voxel_size` at `resolution.mr`; 0: the
      points as stored).
    raw_count: the number of points in the file.
    path: the file.
  """

  points: np.ndarray
  faces: np.ndarray | None
  resolution: Resolution
  voxel: float
  raw_count: int
  path: Path


def _prepare_scan(path: str) -> dict[str, np.ndarray]:
  """`Scan`'s figures for the file at `path` (what the disk cache stores) and its arrays: the
  thinned points, or the file's points and faces under the keys "_points" / "_faces" (not
  stored: reading the file again is cheap, measuring it is not)."""
  cloud = read_cloud(path)
  res = working_resolution(cloud.points, cloud.faces, name=path)
  voxel = thinning_voxel_size(cloud.points, res, res.mr, faces=cloud.faces)
  out = {"resolution": np.array([res.mr, res.mean_spacing, res.area_spacing]),
         "definition": np.array(res.definition), "voxel": np.array(float(voxel)),
         "raw_count": np.array(len(cloud.points))}
  if voxel > 0:
    out["points"] = thin_cloud(np.asarray(cloud.points, np.float64), voxel)[0]
  else:
    out["_points"] = np.asarray(cloud.points, np.float64)
    if cloud.faces is not None:
      out["_faces"] = np.asarray(cloud.faces, np.int64)
  return out


_SCAN_KEYS = {"resolution", "definition", "voxel", "raw_count"}


def _read_scan_cache(cache_file: Path) -> dict[str, np.ndarray] | None:
  """The arrays of a disk-cache file, or None where it is missing or damaged (then computed
  again and replaced)."""
  if not cache_file.is_file():
    return None
  try:
    with np.load(cache_file) as f:
      arrays = {k: f[k] for k in f.files}
  except (OSError, ValueError, zipfile.BadZipFile):
    return None
  thinned = float(arrays.get("voxel", 0.0)) > 0
  if not _SCAN_KEYS <= set(arrays) or thinned != ("points" in arrays):
    return None
  return arrays


@functools.lru_cache(maxsize=64)  # thinned sweeps: about 0.25 MB each; clouds as load_mesh's
def _load_scan(path: str, mtime_ns: int, size: int, cache_dir: str | None) -> Scan:
  cache_file = None
  arrays = None
  if cache_dir is not None:
    key = json.dumps([_SCAN_CACHE_VERSION, path, mtime_ns, size])
    cache_file = Path(cache_dir) / "scans" / f"{hashlib.sha1(key.encode()).hexdigest()[:20]}.npz"
    arrays = _read_scan_cache(cache_file)
  if arrays is None:
    arrays = _prepare_scan(path)
    if cache_file is not None:
      cache_file.parent.mkdir(parents=True, exist_ok=True)
      with atomic.atomic_write(cache_file) as f:  # a concurrent reader never sees half a file
        np.savez(f, **{k: v for k, v in arrays.items()  # type: ignore[arg-type]
                       if not k.startswith("_")})
  if "points" in arrays:
    points, faces = arrays["points"], None
  elif "_points" in arrays:
    points, faces = arrays["_points"], arrays.get("_faces")
  else:  # a cached scan kept as stored: its file, read again
    cloud = read_cloud(path)
    points, faces = cloud.points, cloud.faces
  mr, mean, area = (float(v) for v in arrays["resolution"])
  res = Resolution(mr, mean, area, str(arrays["definition"]))
  return Scan(_frozen(np.array(points, np.float64)),
              _frozen(np.asarray(faces, np.int64)) if faces is not None else None, res,
              float(arrays["voxel"]), int(arrays["raw_count"]), Path(path))


def load_scan(path: str | os.PathLike, *, cache_dir: str | os.PathLike | None = None,
              use_cache: bool = True) -> Scan:
  """Reads a scan (any `read_cloud` format) at its working resolution, once per process.

  The scan's resolution is `working_resolution`; a cloud far denser than it (a raw LiDAR
  sweep, whose mean spacing is its near field's) is thinned by voxel averaging to it, by the
  rule `compute_frames` and `register` thin at their door (`sampling.thinning_voxel_size`);
  clean scans, fragments and meshes are kept as stored. The result is kept in memory (keyed
  by the file's path, size and modification time) and, with `use_cache`, on disk as an .npz
  under `cache_dir` (default `default_cache_dir()`), so another process only reads that.

  Args:
    path: the file.
    cache_dir: the disk cache's folder (its `scans/` sub-folder is used).
    use_cache: read and write the disk cache.

  Returns:
    The cached `Scan` (read-only arrays).

  Raises:
    FileNotFoundError: no such file.
    ValueError: a file `read_cloud` refuses, or a cloud without spacing (each message names
      the file).
  """
  p = Path(path).resolve()
  st = p.stat()
  folder = None
  if use_cache:
    folder = str(Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir())
  return _load_scan(str(p), st.st_mtime_ns, st.st_size, folder)
