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

import jax
import jax.numpy as jnp

from lrf_jax.descriptors.common import local_coordinates, sanitize_inputs
from lrf_jax.neighborhoods import Patches

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
    patches: `Patches` with every neighbour within r (`k=None`).
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
