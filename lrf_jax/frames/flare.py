"""FLARE local reference frames (Petrelli & Di Stefano 2012; the paper's "SD"), as PCL 1.13.

PCL's `FLARELocalReferenceFrameEstimation` with `setRadiusSearch(r_z)`, `setTangentRadius(r)`,
margin threshold 0.85 and 6 / 6 minimum neighbours (the defaults). For a keypoint p:

* z: with at least 6 points within r_z = `Z_RATIO` · r, their least-squares plane normal
  (`Patches.z_cov`) flipped to agree with the mean of their finite normals
  (`flipNormalTowardsNormalsMean`); otherwise the keypoint's own normal;
* x: among the points in the ring 0.85 r < |pq_i| <= r, the one with the largest signed distance
  pq_i · z from the tangent plane (the largest "local depth"); x is the unit projection of its
  offset on the tangent plane, y = z × x.

Minimum neighbours: 6 within r (PCL's `min_neighbors_for_tangent_axis`) and at least one in the
ring; where PCL then returns a *random* x-axis, we return the identity with `valid = False`.
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

import jax
import jax.numpy as jnp

from lrf_jax import geometry
from lrf_jax.frames.board import normals_mean
from lrf_jax.frames.normal_based import NormalExtra, prepare_normals
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.geometry import sanitize
from lrf_jax.neighborhoods import Patches

Z_RATIO = 1.0 / 3.0
MARGIN = 0.85
MIN_Z_NEIGHBOURS = 6
MIN_TANGENT_NEIGHBOURS = 6


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
  dist2 = jnp.sum(offsets * offsets, axis=-1)
  fit, fit_ok = geometry.smallest_eigvec(z_cov)
  in_z = mask & (dist2 <= (Z_RATIO * radius) ** 2)
  ref, ref_ok = normals_mean(normals, in_z)
  fit = geometry.orient_like(fit, ref)
  own, own_ok = geometry.safe_normalize(geometry.finite_or_zero(kp_normal))
  own_ok = own_ok & jnp.all(jnp.isfinite(kp_normal))
  use_fit = z_count >= MIN_Z_NEIGHBOURS
  z = jnp.where(use_fit, fit, own)
  z_ok = jnp.where(use_fit, fit_ok & ref_ok, own_ok)

  margin = mask & (dist2 > (MARGIN * radius) ** 2)
  slot, found = geometry.lexicographic_argmax(offsets @ z, margin, dist2, index)
  x, x_ok = geometry.directed_tangent_axis(z, offsets[slot])
  frame, f_ok = geometry.frame_from_zx(z, x)
  valid = z_ok & (count >= MIN_TANGENT_NEIGHBOURS) & found & x_ok & f_ok
  return geometry.identity_where_invalid(frame, valid), valid


def flare_frames(patches: Patches, normals: jax.Array,
                 kp_normal: jax.Array) -> tuple[jax.Array, jax.Array]:
  """FLARE frames for a batch (pure, jittable).

  Args:
    patches: `Patches` built with `z_ratio=Z_RATIO`; `k=None` (every neighbour) reproduces PCL.
    normals: (N, K, 3) normals of the patch slots.
    kp_normal: (N, 3) normals of the keypoints.

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  patches, finite = sanitize(patches)
  frames, valid = jax.vmap(flare_frame)(
      patches.offsets, patches.mask, patches.indices, patches.radius, patches.count,
      patches.z_cov, patches.z_count, normals, kp_normal)
  valid = valid & finite
  return geometry.identity_where_invalid(frames, valid), valid

# ------------------------------------------------------------------------------ registry entry

def _flare(patches: Patches, extra: NormalExtra):
  return flare_frames(patches, extra.normals, extra.kp_normal)


SPEC = MethodSpec(
    "flare", _flare, default_k=None, needs_normals=True, z_ratio=Z_RATIO, prepare=prepare_normals, extra=NormalExtra,
    shells=(Z_RATIO, MARGIN),
    description="FLARE / SD (Petrelli & Di Stefano 2012): plane-fit z over r/3, x to the "
                "highest margin point (PCL)")
