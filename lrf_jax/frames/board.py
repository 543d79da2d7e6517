"""BOARD local reference frames (Petrelli & Di Stefano 2011), as PCL 1.13 computes them.

PCL's `BOARDLocalReferenceFrameEstimation` with `setRadiusSearch(r_z)`, `setTangentRadius(r)`,
`setFindHoles(false)` (the default) and margin threshold 0.85 (the default). For a keypoint p:

* z: the least-squares plane normal of all points within r_z = `Z_RATIO` · r (the smallest
  eigenvector of their covariance about their centroid, `Patches.z_cov`), flipped to agree with the
  mean of those points' normals (`normalDisambiguation`);
* x: among the points in the margin 0.85 r < |pq_i| <= r, the one whose normal is the most
  inclined to z (smallest n_i · z); if the margin is empty, among all the other points; x is the
  unit projection of its offset on the tangent plane, y = z × x.

Minimum neighbors: 6 within r_z (PCL's rule). Invalid also when the plane fit is degenerate
(collinear points), no candidate has a usable normal (finite and not all zero: zero rows, the
placeholder of files without normals, count as missing, `normal_based.usable_normals`), the
chosen point projects onto p, or an input is not finite. Normals come from the `prepare` hook
(`frames.normal_based.prepare_normals`): the caller's, else `normals.estimate_normals`.

Deviations from PCL: the hole-finding variant (`find_holes`, which starts from a random axis) is
not implemented; non-finite normals are skipped in the mean (PCL would propagate NaN); ties of
n_i · z go to the nearer point (PCL: the first in its distance-sorted search) and then to the lower
cloud index; the keypoint itself is never chosen in the fallback (PCL would return a zero x).
r_z = r / 3 is our choice (PCL takes any radius; the LRF-Net paper: "a small subset").

References:
  Petrelli, Di Stefano, "On the repeatability of the local reference frame for partial shape
  matching", ICCV 2011. PCL 1.13 `features/impl/board.hpp`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.host_path import BallKernel
from lrf_jax.frames.normal_based import NormalExtra, batch_frames, prepare_normals
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# Z_RATIO: the z support, the ball of radius Z_RATIO · r (r/3) whose points' plane gives z
# (`MethodSpec.z_ratio`, `Patches.z_*`). MARGIN_RATIO: the margin, the band
# MARGIN_RATIO · r < |pq_i| <= r (PCL's margin threshold) where the x axis is chosen.
Z_RATIO = 1.0 / 3.0
MARGIN_RATIO = 0.85
MIN_Z_NEIGHBORS = 6


def normals_mean(normals: jax.Array, use: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Sum of the finite normals of the `use` slots and whether it is non-zero.

  Args:
    normals: (K, 3) normals (may hold NaN).
    use: (K,) bool.

  Returns:
    (s (3,), ok ()); only the direction of s matters (PCL normalises it).
  """
  good = use & geometry.all_finite_rows(normals)
  s = jnp.sum(jnp.where(good[:, None], geometry.finite_or_zero(normals), 0.0), axis=0)
  return s, geometry.safe_norm(s) > 0


def normal_oriented_plane_z(offsets, mask, radius, z_cov, normals):
  """The z of BOARD and FLARE (PCL's): the plane normal of the points within Z_RATIO · r (the
  smallest eigenvector of their covariance), flipped to agree with the sum of their finite
  normals (`normals_mean`).

  Args:
    offsets: (K, 3) pq_i (cloud units), finite.
    mask: (K,) bool.
    radius: () support radius r.
    z_cov: (3, 3) covariance of the points within Z_RATIO · r about their centroid.
    normals: (K, 3) the slots' normals (NaN allowed).

  Returns:
    (z (3,); z_ok () the plane fit is not degenerate; ref_ok () a finite normal oriented z;
    dist2 (K,) the squared lengths |pq_i|²).
  """
  dist2 = jnp.sum(offsets * offsets, axis=-1)
  z, z_ok = geometry.smallest_eigvec(z_cov)
  in_z = mask & (dist2 <= (Z_RATIO * radius) ** 2)
  ref, ref_ok = normals_mean(normals, in_z)
  return geometry.orient_like(z, ref), z_ok, ref_ok, dist2


def board_frame(offsets, mask, index, radius, z_cov, z_count, normals):
  """BOARD frame of one keypoint.

  Args:
    offsets: (K, 3) pq_i (cloud units), finite.
    mask: (K,) bool.
    index: (K,) int cloud indices (tie-breaking only).
    radius: () support radius r (= PCL's tangent radius).
    z_cov: (3, 3) covariance of the points within Z_RATIO · r about their centroid.
    z_count: () number of those points.
    normals: (K, 3) the slots' normals (NaN allowed).

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool).
  """
  z, z_ok, _, dist2 = normal_oriented_plane_z(offsets, mask, radius, z_cov, normals)
  n_ok = geometry.all_finite_rows(normals)
  cos = geometry.finite_or_zero(normals) @ z
  margin = mask & (dist2 > (MARGIN_RATIO * radius) ** 2)
  cand = jnp.where(jnp.any(margin), margin, mask & (dist2 > 0)) & n_ok
  slot, found = geometry.lexicographic_argmax(-cos, cand, dist2, index)
  x, x_ok = geometry.directed_tangent_axis(z, offsets[slot])
  frame, f_ok = geometry.frame_from_zx(z, x)
  valid = z_ok & (z_count >= MIN_Z_NEIGHBORS) & found & x_ok & f_ok
  return geometry.identity_where_invalid(frame, valid), valid


def board_frames(patches: Patches, normals: AnyArray) -> tuple[jax.Array, jax.Array]:
  """BOARD frames for a batch (pure, jittable).

  Args:
    patches: `Patches` built with `z_ratio=Z_RATIO`; `k=None` (every neighbor) reproduces PCL.
    normals: (N, K, 3) normals of the patch slots.

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  return batch_frames(board_frame, patches,
                      ("offsets", "mask", "indices", "radius", "z_cov", "z_count"), normals)

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host from the engine's ball lists, in float64, one keypoint per thread
# (`frames.host_geometry`): `compute_frames`' default on the CPU.


@nb.njit(parallel=True, cache=True)
def _board_host_kernel(points, centers, ptr, ball, normals, r, rz2, eps, frames, valid):
  margin2 = (MARGIN_RATIO * r) ** 2
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    ok, z, _ = hg.plane_z(points, centers[i], ball, start, stop, rz2, eps, MIN_Z_NEIGHBORS)
    if not ok:
      continue
    ref = np.zeros(3)
    any_margin = False
    for t in range(start, stop):
      j = ball[t]
      d2 = hg.offset(points, j, centers[i])[3]
      any_margin = any_margin or d2 > margin2
      if d2 <= rz2 and hg.finite_row(normals, j):
        ref[0] += normals[j, 0]
        ref[1] += normals[j, 1]
        ref[2] += normals[j, 2]
    if z[0] * ref[0] + z[1] * ref[1] + z[2] * ref[2] < 0.0:
      z = -z
    best, best_d2, best_j = -np.inf, np.inf, -1
    for t in range(start, stop):
      j = ball[t]
      d2 = hg.offset(points, j, centers[i])[3]
      if (d2 > margin2 if any_margin else d2 > 0.0) and hg.finite_row(normals, j):
        score = -(normals[j, 0] * z[0] + normals[j, 1] * z[1] + normals[j, 2] * z[2])
        if best_j < 0 or hg.better(score, d2, j, best, best_d2, best_j):
          best, best_d2, best_j = score, d2, j
    if best_j >= 0:
      hg.write_frame(frames, valid, i, z, points[best_j] - centers[i])


# ------------------------------------------------------------------------------ registry entry

def _board(patches: Patches, extra: NormalExtra):
  return board_frames(patches, extra.normals)


SPEC = MethodSpec(
    "board", _board, default_k=None, needs_normals=True, z_ratio=Z_RATIO, prepare=prepare_normals, extra=NormalExtra,
    host_frames=BallKernel(_board_host_kernel, ("normals", "radius", "rz2"), (hg.EPS,), Z_RATIO),
    description="BOARD (Petrelli & Di Stefano 2011): plane-fit z over r/3, x to the most "
                "inclined margin normal (PCL)")
