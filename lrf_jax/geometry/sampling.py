"""Downsampling a cloud: `voxel_downsample(points, size)`, one point per occupied voxel.

The counterpart of Open3D's `voxel_down_sample` and PCL's `VoxelGrid` filter, in numpy: the
voxel grid is anchored at the cloud's minimum corner, every occupied voxel gives the centroid
(mean) of its points, and the output lists the voxels in lexicographic order of their integer
(ix, iy, iz) cell coordinates, so the result depends only on the set of points and `size`
(not on the order of the input rows).

`thinning_voxel_size` and `thin_cloud` are the thinning at the door of `register` and
`compute_frames(voxel_size=)`: which voxel (the rule of their `voxel_size=`) and the thinned
cloud with each input point's voxel.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # imported where used: `voxel_downsample` alone loads no numba engine
  from lrf_jax.geometry.resolution import Resolution

__all__ = ["thin_cloud", "thinning_voxel_size", "voxel_centroids", "voxel_downsample",
           "voxel_groups"]

# Cells per axis beyond which the integer cell coordinates would lose precision.
_MAX_CELLS = 2**40


def voxel_downsample(points: Any, size: float, *, return_index: bool = False
                     ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
  """The centroid of the points of each occupied voxel of edge `size`.

  Deterministic: voxel (i, j, k) holds the points p with
  `floor((p - points.min(0)) / size) == (i, j, k)`; the output row of a voxel is the mean of its
  points (float64, summed in input order), and the rows are sorted by (i, j, k)
  lexicographically. A voxel holding one point returns that point exactly. Reordering the input
  rows changes the result only by float rounding of the means (about 1e-16 relative). The
  voxels are found by sorting one integer key per point (O(n log n)), not by comparing rows.

  Args:
    points: the cloud: an (n, 3) array of finite floats (any units), an `lrf_jax.io.Cloud`, a
      path `lrf_jax.io.read_cloud` opens, or an object with `.points` (as `compute_frames`
      takes; `lrf_jax.geometry.cloud.CheckedCloud`). Faces and normals are ignored.
    size: the voxel edge, in the cloud's units (> 0). `lrf_jax.mesh_resolution(points)` gives
      the cloud's point spacing: `size = 2 * mr` keeps about one point in 4 to 8 on a surface.
    return_index: also return, per output row, the index of the first input point (in input
      order) of its voxel: a representative input point.

  Returns:
    (m, 3) float64 centroids, m = the number of occupied voxels (1 <= m <= n); with
    `return_index`, also (m,) int64 input indices.

  Raises:
    ValueError: `points` is not a non-empty (n, 3) cloud of finite floats, `size` is not a
      positive finite number, or `size` is so small that the cloud spans more than 2**40
      voxels along an axis.

  Example:
    >>> small = lrf_jax.voxel_downsample(points, 2 * lrf_jax.mesh_resolution(points))
  """
  from lrf_jax.geometry.cloud import as_cloud
  pts = np.asarray(as_cloud(points, "points").points, np.float64)
  try:
    size = float(size)
  except (TypeError, ValueError):
    raise ValueError(f"voxel_downsample: size: expected a positive number, got {size!r}") from None
  if not (np.isfinite(size) and size > 0):
    raise ValueError(f"voxel_downsample: size: expected a positive finite number, got {size!r}")
  out, first, _ = voxel_centroids(pts, size)
  return (out, first) if return_index else out


def voxel_centroids(points: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """`voxel_downsample` of a checked cloud, with the voxel of every input point.

  Args:
    points: (n, 3) finite float64 cloud, n >= 1 (not checked here).
    size: the voxel edge, a positive finite float.

  Returns:
    (centroids (m, 3) float64 as `voxel_downsample` returns them, first (m,) int64: each voxel's
    first input point, inverse (n,) int64: each input point's row of `centroids`).

  Raises:
    ValueError: `size` so small that the cloud spans more than 2**40 voxels along an axis.
  """
  pts = points
  cells = pts - _column_extremes(pts, np.min)  # floor((pts - pts.min(0)) / size), in place
  cells /= size
  np.floor(cells, out=cells)
  if cells.max(initial=0) >= _MAX_CELLS:
    raise ValueError(f"voxel_downsample: size {size:g} is too small for a cloud of extent "
                     f"{np.ptp(pts, axis=0).max():g} (more than 2**40 voxels along an axis)")
  inverse, first = voxel_groups(cells.astype(np.int64))
  counts = np.bincount(inverse)
  out = np.stack([np.bincount(inverse, weights=pts[:, a], minlength=len(counts))
                  for a in range(3)], axis=1) / counts[:, None]
  single = counts == 1  # one point: return it exactly (no division rounding)
  out[single] = pts[first[single]]
  return out, first, inverse


def thin_cloud(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """A checked cloud thinned by voxel averaging at `voxel` (`voxel_centroids`), as `register`
  and `compute_frames` thin at the door; errors name their `voxel_size` option.

  Args:
    points: (n, 3) finite float64 cloud (not checked here).
    voxel: the voxel edge (> 0, finite).

  Returns:
    `voxel_centroids`' (centroids, first, inverse).

  Raises:
    ValueError: a voxel too small for the cloud's extent, or one that leaves fewer than 10
      points.
  """
  try:
    thin, first, inverse = voxel_centroids(points, float(voxel))
  except ValueError as e:  # named by the option that chose the voxel
    raise ValueError(f"voxel_size: {str(e).removeprefix('voxel_downsample: ')}") from None
  if len(thin) < 10:
    raise ValueError(f"voxel_size: voxels of {voxel:.6g} leave {len(thin)} points of the "
                     f"{len(points)} of a cloud (at least 10 needed); give a smaller "
                     "voxel_size, or 0 to keep every point")
  return thin, first, inverse


def _column_extremes(a: np.ndarray, reduce: Any) -> np.ndarray:
  """`reduce(a, axis=0)` of a non-empty (n, 3) array, one column at a time (numpy's axis-0
  reductions of a C-ordered (n, 3) array are about 50x slower than three strided ones)."""
  return np.array([reduce(a[:, j]) for j in range(a.shape[1])], a.dtype)


def voxel_groups(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """The occupied cells of integer cell coordinates, in lexicographic order of (i, j, k).

  Args:
    cells: (n, 3) int64 non-negative cell coordinates, each below 2**40.

  Returns:
    (inverse (n,): each point's cell number, first (m,): the first point (in input order) of each
    cell), int64.
  """
  span = _column_extremes(cells, np.max) + 1 if len(cells) else np.ones(3, np.int64)
  volume = float(span[0]) * float(span[1]) * float(span[2])
  if volume < 2.0**62:  # one exact integer key
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    n = len(key)
    if volume * max(n, 1) < 2.0**62:
      # the stable order by key, as the sorted values of key * n + index (one int64 sort of
      # values: several times faster than a stable argsort)
      both = np.sort(key * n + np.arange(n, dtype=np.int64))
      sk = both // n
      order = both - sk * n
    else:
      order = np.argsort(key, kind="stable")
      sk = key[order]
    new = np.empty(len(sk), bool)
    new[:1] = True
    np.not_equal(sk[1:], sk[:-1], out=new[1:])
    inverse = np.empty(len(sk), np.int64)
    inverse[order] = np.cumsum(new) - 1
    return inverse, order[new]
  _, first, inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
  return inverse.ravel().astype(np.int64), first.astype(np.int64)


def thinning_voxel_size(points: np.ndarray, res: Resolution, mr: float, *,
                        faces: np.ndarray | None = None, voxel_size: float | None = None) -> float:
  """The voxel edge a cloud is thinned at before `register` or `compute_frames` work on it (0:
  it is not), by the rule of their `voxel_size=`:

  * a positive `voxel_size`: that edge (meshes included; thinning drops their faces);
  * 0: none;
  * None: a cloud without faces whose mean spacing is under `mr` / `PAIR_RATIO`, or under
    `CAPPED_THIN_RATIO` mr where `registration_resolution` capped its resolution
    (`resolution.thinning_voxel`: a raw sweep's near field, a full-density fragment) is thinned
    by the voxel whose centroids come out spaced `mr` apart (a voxel of mr leaves them closer,
    about 0.7 mr: the voxel is scaled by mr over the spacing that gives, measured, for a capped
    cloud on `resolution.sampled_spacings` of the centroids); meshes and
    clean clouds are not (a single clean cloud's working resolution is its mean spacing: never
    thinned).

  Args:
    points: (n, 3) finite float64 cloud.
    res: its `resolution.working_resolution` (`compute_frames`) or
      `resolution.registration_resolution` (`register`).
    mr: the working resolution the cloud is measured in (its own `res.mr`, or a pair's
      `resolution.pair_resolution`).
    faces: its triangles, or None.
    voxel_size: `validate_voxel_size`'s None, 0 or a positive edge (cloud units).

  Returns:
    The voxel edge (cloud units), or 0.0.
  """
  from lrf_jax.geometry.resolution import mesh_resolution, sampled_spacings, thinning_voxel
  if voxel_size is not None:
    return float(voxel_size)
  voxel = None if faces is not None else thinning_voxel(res, float(mr))
  if not voxel:
    return 0.0
  centroids = voxel_centroids(np.asarray(points, np.float64), voxel)[0]
  if res.capped and len(centroids) >= 2:  # as its resolution: on a sample of an oversampled cloud
    spacing = float(sampled_spacings(centroids).mean())
  else:
    spacing = mesh_resolution(centroids)[0]
  return voxel * float(mr) / spacing if spacing > 0 else voxel
