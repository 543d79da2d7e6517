"""FLARE local reference frames (Petrelli & Di Stefano 2012; the paper's "SD"), as PCL 1.13.

PCL's `FLARELocalReferenceFrameEstimation` with `setRadiusSearch(r_z)`, `setTangentRadius(r)`,
margin threshold 0.85 and 6 / 6 minimum neighbors (the defaults). For a keypoint p:

* z: with at least 6 points within r_z = `Z_RATIO` · r, their least-squares plane normal
  (`Patches.z_cov`) flipped to agree with the mean of their finite normals
  (`flipNormalTowardsNormalsMean`); otherwise the keypoint's own normal;
* x: among the points in the margin 0.85 r < |pq_i| <= r, the one with the largest signed distance
  pq_i · z from the tangent plane (the largest "local depth"); x is the unit projection of its
  offset on the tangent plane, y = z × x.

Minimum neighbors: 6 within r (PCL's `min_neighbors_for_tangent_axis`) and at least one in the
margin; where PCL then returns a *random* x-axis, we return the identity with `valid = False`.
Invalid also for a degenerate plane fit (collinear points; PCL returns an arbitrary normal), no
finite normal to orient z, or a non-finite input. Normals come from the `prepare` hook.

Deviations from PCL: ties of pq_i · z go to the nearer point, then the lower cloud index (PCL:
the first in its distance-sorted search); PCL scores z · q_i in absolute coordinates, we use
z · (q_i - p) (the same order up to float32 rounding). r_z = r / 3 is our choice (PCL's own test
uses 5 mr for z and 20 mr for x).

References:
  Petrelli, Di Stefano, "A repeatable and efficient canonical reference for surface matching",
  3DIMPVT 2012. PCL 1.13 `features/impl/flare.hpp`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.host_path import BallKernel
from lrf_jax.frames.board import Z_RATIO, normal_oriented_plane_z
from lrf_jax.frames.normal_based import NormalExtra, batch_frames, prepare_normals
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# Z_RATIO (BOARD's, whose z this is): the z support, the ball of radius Z_RATIO · r (r/3) whose
# points' plane gives z (`MethodSpec.z_ratio`, `Patches.z_*`). MARGIN_RATIO: the margin, the band
# MARGIN_RATIO · r < |pq_i| <= r (PCL's margin threshold) where the x axis is chosen.
MARGIN_RATIO = 0.85
MIN_Z_NEIGHBORS = 6
MIN_TANGENT_NEIGHBORS = 6
# FLARE reads the z support and the margin only (`MethodSpec.shells`).
SHELLS = (Z_RATIO, MARGIN_RATIO)


def flare_frame(offsets, mask, index, radius, count, z_cov, z_count, normals, kp_normal):
  """FLARE frame of one keypoint.

  Args:
    offsets: (K, 3) pq_i (cloud units), finite.
    mask: (K,) bool.
    index: (K,) int cloud indices (tie-breaking only).
    radius: () support radius r (PCL's tangent radius).
    count: () number of points within r (before any subsample).
    z_cov: (3, 3) covariance of the points within Z_RATIO · r about their centroid.
    z_count: () number of those points.
    normals: (K, 3) the slots' normals (NaN allowed).
    kp_normal: (3,) the keypoint's normal (NaN allowed).

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool).
  """
  fit, fit_ok, ref_ok, dist2 = normal_oriented_plane_z(offsets, mask, radius, z_cov, normals)
  own, own_ok = geometry.safe_normalize(geometry.finite_or_zero(kp_normal))
  own_ok = own_ok & jnp.all(jnp.isfinite(kp_normal))
  use_fit = z_count >= MIN_Z_NEIGHBORS
  z = jnp.where(use_fit, fit, own)
  z_ok = jnp.where(use_fit, fit_ok & ref_ok, own_ok)

  margin = mask & (dist2 > (MARGIN_RATIO * radius) ** 2)
  slot, found = geometry.lexicographic_argmax(offsets @ z, margin, dist2, index)
  x, x_ok = geometry.directed_tangent_axis(z, offsets[slot])
  frame, f_ok = geometry.frame_from_zx(z, x)
  valid = z_ok & (count >= MIN_TANGENT_NEIGHBORS) & found & x_ok & f_ok
  return geometry.identity_where_invalid(frame, valid), valid


def flare_frames(patches: Patches, normals: AnyArray,
                 kp_normal: AnyArray) -> tuple[jax.Array, jax.Array]:
  """FLARE frames for a batch (pure, jittable).

  Args:
    patches: `Patches` built with `z_ratio=Z_RATIO`; `k=None` (every neighbor) reproduces PCL.
    normals: (N, K, 3) normals of the patch slots.
    kp_normal: (N, 3) normals of the keypoints.

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  return batch_frames(flare_frame, patches,
                      ("offsets", "mask", "indices", "radius", "count", "z_cov", "z_count"),
                      normals, kp_normal)

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host from the engine's ball lists, in float64, one keypoint per thread
# (`frames.host_geometry`): `compute_frames`' default on the CPU.


@nb.njit(parallel=True, cache=True)
def _flare_host_kernel(points, centers, ptr, ball, kp_ids, counts, normals, r, rz2, eps, frames,
                       valid):
  margin2 = (MARGIN_RATIO * r) ** 2
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    if counts[i] < MIN_TANGENT_NEIGHBORS:
      continue
    mean = np.zeros(3)
    cov = np.zeros((3, 3))
    count = hg.inner_stats(points, centers[i], ball, start, stop, rz2, mean, cov)
    if count >= MIN_Z_NEIGHBORS:
      evals, evecs = np.linalg.eigh(cov)
      z = evecs[:, 0].copy()
      ref = np.zeros(3)
      for t in range(start, stop):
        j = ball[t]
        if hg.offset(points, j, centers[i])[3] <= rz2 and hg.finite_row(normals, j):
          ref[0] += normals[j, 0]
          ref[1] += normals[j, 1]
          ref[2] += normals[j, 2]
      if not (hg.smallest_ok(evals, eps) and (ref != 0.0).any()):
        continue
      if z[0] * ref[0] + z[1] * ref[1] + z[2] * ref[2] < 0.0:
        z = -z
    else:
      z, own_ok = hg.unit_or_zero(normals[kp_ids[i]])
      if not own_ok:
        continue
    best_j = hg.highest_point(points, centers[i], ball, start, stop, z, margin2, True)
    if best_j >= 0:
      hg.write_frame(frames, valid, i, z, points[best_j] - centers[i])


# ------------------------------------------------------------------------------ registry entry

def _flare(patches: Patches, extra: NormalExtra):
  return flare_frames(patches, extra.normals, extra.kp_normal)


SPEC = MethodSpec(
    "flare", _flare, default_k=None, needs_normals=True, z_ratio=Z_RATIO, prepare=prepare_normals, extra=NormalExtra,
    shells=SHELLS,
    host_frames=BallKernel(_flare_host_kernel, ("keypoints", "counts", "normals", "radius", "rz2"),
                           (hg.EPS,), Z_RATIO, SHELLS),
    description="FLARE / SD (Petrelli & Di Stefano 2012): plane-fit z over r/3, x to the "
                "highest margin point (PCL)")
