"""TOLDI (Yang, Zhang, Cao 2017): three-view local depth images on an external LRF.

The local surface (every point within r) is expressed in the LRF and projected on three planes;
each plane's square [-r, r]^2 is split into L x L pixels (L = 20) and each pixel keeps the
*minimum* normalised depth of the points falling into it ("to resist self-occlusion", the
original C++):

=======  =========================  =================  ===========================
 view     image column (from)        image row (from)   depth of a point
=======  =========================  =================  ===========================
 1        x                          y (top = +r)       (r - z) / 2r, clipped [0, 1]
 2        y                          z (top = +r)       (r - x) / 2r
 3        z                          x (top = +r)       (r - y) / 2r
=======  =========================  =================  ===========================

Pixel (row, col) of a view is stored at view * L^2 + row * L + col (row 0 = the top of the image,
i.e. the largest second coordinate, as the original's `y_bin = bin - y_bin + 1`). Empty pixels hold
`EMPTY_PIXEL` = 100 (the original's `TOLDI_NULL_PIXEL`): 3 x 20 x 20 = 1200 values, compared with
the L2 distance, not normalised.

Bins follow the original's arithmetic: column = trunc((u + r) / (2r / L)) clamped to [0, L - 1]
(truncation towards zero, like its int conversion). Invalid (zeros, `valid = False`): an invalid
frame, or at most 10 points in the ball (the original describes a keypoint only when the radius
search returns more than 10 points).

References:
  Yang, Zhang, Cao, "TOLDI: An effective and robust approach for 3D local shape description",
  Pattern Recognition 65, 2017, section 3.2; the authors' C++ (`local_TOLDI`).
"""

from __future__ import annotations

from typing import Any

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.descriptors.common import local_coordinates, sanitize_inputs
from lrf_jax.frames import host_geometry as hg
from lrf_jax.search.engine import run_blocks
from lrf_jax.search.neighborhoods import Patches

GRID = 20
EMPTY_PIXEL = 100.0
MIN_POINTS = 11
# (column coordinate, row coordinate, depth coordinate) per view.
VIEWS = ((0, 1, 2), (1, 2, 0), (2, 0, 1))


def depth_image(local: jax.Array, mask: jax.Array, radius: jax.Array, view: tuple[int, int, int],
                grid: int, empty: float) -> jax.Array:
  """One local depth image: min over each pixel of (r - depth coordinate) / 2r.

  Args:
    local: (K, 3) coordinates in the LRF.
    mask: (K,) bool.
    radius: () r.
    view: (column, row, depth) coordinate indices.
    grid: L.
    empty: value of pixels without points.

  Returns:
    (L * L,) pixels, row-major, row 0 at the top (+r).
  """
  cu, cv, cd = view
  step = 2 * radius / grid
  col = jnp.clip(jnp.trunc((local[:, cu] + radius) / step).astype(jnp.int32), 0, grid - 1)
  row = jnp.clip(jnp.trunc((local[:, cv] + radius) / step).astype(jnp.int32), 0, grid - 1)
  row = grid - 1 - row
  depth = jnp.clip((radius - local[:, cd]) / (2 * radius), 0.0, 1.0)
  inf = jnp.asarray(jnp.inf, local.dtype)
  img = jnp.full(grid * grid, inf).at[row * grid + col].min(jnp.where(mask, depth, inf))
  return jnp.where(jnp.isinf(img), jnp.asarray(empty, local.dtype), img)


def toldi_descriptors(patches: Patches, frames: jax.Array, valid: jax.Array, *,
                      grid: int = GRID,
                      empty: float = EMPTY_PIXEL) -> tuple[jax.Array, jax.Array]:
  """TOLDI descriptors of a batch (pure, jittable).

  Args:
    patches: `Patches` with every neighbor within r (`k=None`).
    frames: (N, 3, 3) LRFs, rows x, y, z, from any method.
    valid: (N,) bool validity of the frames.
    grid: pixels per image side L (20 in the paper).
    empty: value of empty pixels (the original: 100).

  Returns:
    (descriptors (N, 3 * L * L) float32, zeros where invalid; valid (N,) bool).
  """
  offsets, mask, frames, ok = sanitize_inputs(patches, frames, valid)
  local = local_coordinates(offsets, frames)
  radius = jnp.where(ok, jnp.asarray(patches.radius, local.dtype), 1.0)

  def one(loc, m, r):
    return jnp.concatenate([depth_image(loc, m, r, v, grid, empty) for v in VIEWS])

  desc = jax.vmap(one)(local, mask, radius)
  ok = ok & (jnp.sum(mask, axis=-1) >= MIN_POINTS)
  return jnp.where(ok[:, None], desc, 0.0), ok


# ------------------------------------------------------------------------------ host fast path
# The same images on the host from the engine's ball lists, float64 coordinates, one keypoint
# per thread, no padded patch: `compute_descriptors`' default on the CPU.


@nb.njit(cache=True, nogil=True)
def _toldi_host_kernel(points, centers, ptr, ball, frames, ok, r, grid, empty, out, out_ok, lo,
                       hi):
  """Keypoints lo..hi-1 of `toldi_descriptors_host` (on the engine's threads)."""
  area = grid * grid
  step = 2.0 * r / grid
  img = np.empty(3 * area)
  loc = np.empty(3)
  for i in range(lo, hi):
    out[i, :] = 0.0
    out_ok[i] = False
    start, stop = ptr[i], ptr[i + 1]
    if not ok[i] or stop - start < MIN_POINTS:
      continue
    img[:] = np.inf
    for t in range(start, stop):
      j = ball[t]
      ox = points[j, 0] - centers[i, 0]
      oy = points[j, 1] - centers[i, 1]
      oz = points[j, 2] - centers[i, 2]
      for a in range(3):
        loc[a] = frames[i, a, 0] * ox + frames[i, a, 1] * oy + frames[i, a, 2] * oz
      for v in range(3):
        cu, cv, cd = v, (v + 1) % 3, (v + 2) % 3  # VIEWS
        col = min(max(int(np.trunc((loc[cu] + r) / step)), 0), grid - 1)
        row = grid - 1 - min(max(int(np.trunc((loc[cv] + r) / step)), 0), grid - 1)
        depth = min(max((r - loc[cd]) / (2.0 * r), 0.0), 1.0)
        k = v * area + row * grid + col
        if depth < img[k]:
          img[k] = depth
    for k in range(3 * area):
      out[i, k] = empty if np.isinf(img[k]) else img[k]
    out_ok[i] = True


def toldi_descriptors_host(points: np.ndarray, keypoints: np.ndarray, radius: float,
                           frames: np.ndarray, valid: np.ndarray, index: Any, *,
                           grid: int = GRID, empty: float = EMPTY_PIXEL
                           ) -> tuple[np.ndarray, np.ndarray]:
  """TOLDI descriptors (`toldi_descriptors`) of `keypoints` on the host, from every point within
  `radius` (float64 coordinates in the LRF).

  Args:
    points: (n, 3) float64 cloud.
    keypoints: (N,) indices.
    radius: support radius r.
    frames: (N, 3, 3) LRFs, rows x, y, z.
    valid: (N,) bool validity of the frames.
    index: the cloud's `neighborhoods.SearchIndex`.
    grid: pixels per image side L.
    empty: value of empty pixels.

  Returns:
    (descriptors (N, 3 * L * L) float32, zeros where invalid; valid (N,) bool).
  """
  pts, centers, ptr, ball = hg.ball_lists(points, keypoints, radius, index)
  f = np.asarray(frames, np.float64)
  ok = np.asarray(valid, bool) & np.isfinite(f).all(axis=(1, 2))
  f = np.where(ok[:, None, None], np.nan_to_num(f), np.eye(3))
  # float32 rows written by the kernel (each depth rounded once, as a float64 image cast would)
  out = np.empty((len(centers), 3 * grid * grid), np.float32)
  out_ok = np.empty(len(centers), np.bool_)
  args = (pts, centers, ptr, ball, np.ascontiguousarray(f), ok, float(radius), int(grid),
          float(empty), out, out_ok)
  run_blocks(lambda lo, hi: _toldi_host_kernel(*args, lo, hi), len(centers))
  return out, out_ok
