"""Point-signature local reference frames (Chua & Jarvis 1997), discretised for point clouds.

Chua & Jarvis intersect a sphere of radius r centred at p with the surface, fit a plane to the
resulting contour, translate it to p and take its normal as z; x points from p towards the
projection of the contour point with the largest signed distance to that plane. Our discrete
version for a cloud:

* contour: the points in the spherical shell `MARGIN_RATIO` · r <= |pq_i| <= r (a band of the
  support's outer 15 %, the same band as BOARD/FLARE's margin);
* z: the least-squares plane normal of the contour points (smallest eigenvector of their
  covariance about their centroid), flipped to agree with the keypoint's normal (z · n(p) >= 0);
* x: the unit tangent projection of pq_j for the contour point with the largest signed distance
  h_j = pq_j · z to the tangent plane through p (ties: the nearer, then the lower cloud index);
  y = z × x.

Minimum neighbors: 5 contour points. Invalid also for a degenerate contour plane (collinear
contour), a non-finite keypoint normal, a chosen point projecting onto p, or a non-finite input.

References:
  Chua, Jarvis, "Point signatures: a new representation for 3D object recognition", IJCV 25(1),
  1997, section 3.
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

# MARGIN_RATIO: the margin, the band MARGIN_RATIO · r <= |pq_i| <= r of the support (here the
# contour; BOARD/FLARE choose x there, `flare.MARGIN_RATIO`).
MARGIN_RATIO = 0.85
MIN_CONTOUR = 5


def ps_frame(offsets, mask, index, radius, kp_normal):
  """Point-signature frame of one keypoint.

  Args:
    offsets: (K, 3) pq_i (cloud units), finite.
    mask: (K,) bool.
    index: (K,) int cloud indices (tie-breaking only).
    radius: () support radius r.
    kp_normal: (3,) the keypoint's normal (NaN allowed: invalid).

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool).
  """
  dist2 = jnp.sum(offsets * offsets, axis=-1)
  contour = mask & (dist2 >= (MARGIN_RATIO * radius) ** 2)
  cov, _ = geometry.centered_covariance(offsets, contour.astype(offsets.dtype))
  z, z_ok = geometry.smallest_eigvec(cov)
  n = geometry.finite_or_zero(kp_normal)
  n_ok = jnp.all(jnp.isfinite(kp_normal)) & (geometry.safe_norm(n) > 0)
  z = geometry.orient_like(z, n)
  slot, found = geometry.lexicographic_argmax(offsets @ z, contour, dist2, index)
  x, x_ok = geometry.directed_tangent_axis(z, offsets[slot])
  frame, f_ok = geometry.frame_from_zx(z, x)
  valid = z_ok & n_ok & found & x_ok & f_ok & (jnp.sum(contour) >= MIN_CONTOUR)
  return geometry.identity_where_invalid(frame, valid), valid


def ps_frames(patches: Patches, kp_normal: AnyArray) -> tuple[jax.Array, jax.Array]:
  """Point-signature frames for a batch (pure, jittable).

  Args:
    patches: `Patches` (N keypoints); `k=None` (the registry's default) keeps every contour point.
    kp_normal: (N, 3) normals of the keypoints (they fix the sign of z only).

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  return batch_frames(ps_frame, patches, ("offsets", "mask", "indices", "radius"), kp_normal)

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host from the engine's ball lists, in float64, one keypoint per thread
# (`frames.host_geometry`): `compute_frames`' default on the CPU.


@nb.njit(parallel=True, cache=True)
def _ps_host_kernel(points, centers, ptr, ball, kp_ids, normals, r, eps, frames, valid):
  rc2 = (MARGIN_RATIO * r) ** 2
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    c = 0.0
    s = np.zeros(3)
    sq = np.zeros((3, 3))
    for t in range(start, stop):
      ox, oy, oz, d2 = hg.offset(points, ball[t], centers[i])
      if d2 >= rc2:
        c += 1.0
        s[0] += ox
        s[1] += oy
        s[2] += oz
        sq[0, 0] += ox * ox
        sq[0, 1] += ox * oy
        sq[0, 2] += ox * oz
        sq[1, 1] += oy * oy
        sq[1, 2] += oy * oz
        sq[2, 2] += oz * oz
    if c < MIN_CONTOUR:
      continue
    sq[1, 0], sq[2, 0], sq[2, 1] = sq[0, 1], sq[0, 2], sq[1, 2]
    m = s / c
    evals, evecs = np.linalg.eigh(sq / c - np.outer(m, m))
    z, n_ok = hg.z_signed_by(evecs, normals[kp_ids[i]])
    if not (hg.smallest_ok(evals, eps) and n_ok):
      continue
    best_j = hg.highest_point(points, centers[i], ball, start, stop, z, rc2, False)
    hg.write_frame(frames, valid, i, z, points[best_j] - centers[i])


# ------------------------------------------------------------------------------ registry entry

def _ps(patches: Patches, extra: NormalExtra):
  return ps_frames(patches, extra.kp_normal)


SPEC = MethodSpec(
    "ps", _ps, default_k=None, needs_normals=True, prepare=prepare_normals,
    extra=NormalExtra,
    host_frames=BallKernel(_ps_host_kernel, ("keypoints", "normals", "radius"), (hg.EPS,)),
    description="Point signature (Chua & Jarvis 1997): contour-plane z, x to the highest "
                "contour point")
