"""Downsampling a cloud: `voxel_downsample(points, size)`, one point per occupied voxel.

The counterpart of Open3D's `voxel_down_sample` and PCL's `VoxelGrid` filter, in numpy: the
voxel grid is anchored at the cloud's minimum corner, every occupied voxel gives the centroid
(mean) of its points, and the output lists the voxels in lexicographic order of their integer
(ix, iy, iz) cell coordinates, so the result depends only on the set of points and `size`
(not on the order of the input rows).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["voxel_downsample"]

# Cells per axis beyond which the integer cell coordinates would lose precision.
_MAX_CELLS = 2**40


def voxel_downsample(points: Any, size: float) -> np.ndarray:
  """The centroid of the points of each occupied voxel of edge `size`.

  Deterministic: voxel (i, j, k) holds the points p with
  `floor((p - points.min(0)) / size) == (i, j, k)`; the output row of a voxel is the mean of its
  points (float64), and the rows are sorted by (i, j, k) lexicographically. A voxel holding one
  point returns that point exactly. Reordering the input rows changes the result only by
  float rounding of the means (about 1e-16 relative).

  Args:
    points: the cloud: an (n, 3) array of finite floats (any units), an `lrf_jax.io.Cloud`, a
      path `lrf_jax.io.read_cloud` opens, or an object with `.points` (as `compute_frames`
      takes; `lrf_jax.geometry.cloud.CheckedCloud`). Faces and normals are ignored.
    size: the voxel edge, in the cloud's units (> 0). `lrf_jax.mesh_resolution(points)` gives
      the cloud's point spacing: `size = 2 * mr` keeps about one point in 4 to 8 on a surface.

  Returns:
    (m, 3) float64 centroids, m = the number of occupied voxels (1 <= m <= n).

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
  cells = np.floor((pts - pts.min(0)) / size)
  if cells.max(initial=0) >= _MAX_CELLS:
    raise ValueError(f"voxel_downsample: size {size:g} is too small for a cloud of extent "
                     f"{np.ptp(pts, axis=0).max():g} (more than 2**40 voxels along an axis)")
  _, inverse, counts = np.unique(cells.astype(np.int64), axis=0, return_inverse=True,
                                 return_counts=True)
  inverse = inverse.ravel()
  sums = np.zeros((len(counts), 3))
  np.add.at(sums, inverse, pts)
  out = sums / counts[:, None]
  single = counts == 1  # one point: return it exactly (no division rounding)
  if single.any():
    first = np.empty(len(counts), np.int64)
    first[inverse[::-1]] = np.arange(len(pts))[::-1]
    out[single] = pts[first[single]]
  return out
