"""Mian et al. (2010) local reference frames: the principal axes of the support.

For a keypoint p with neighbors q_i within r:

* C = the covariance of the q_i about their centroid (`center="centroid"`, Mian et al.'s mean
  vector m) or about p (`center="keypoint"`);
* x, y, z = the eigenvectors of the largest, middle and smallest eigenvalue; z is flipped to agree
  with the keypoint's normal n(p) (z · n >= 0); y = z × x.

**Sign ambiguity, by construction**: nothing in the method fixes the sign of x (hence of y). The
sign returned here is whatever the eigen-solver gives, which is a function of C but *not*
equivariant: under a rotation of the cloud, x may come back as -x (on the BR bunny at 15 mr,
about half of the x-axes flip under a random rotation). Mian's frames are therefore
equivariant only up to the sign of x and y (z is fixed by the normal); tests check them so, and
MeanCos penalises the flips, which is precisely the weakness the LRF-Net paper points out.

Minimum neighbors: 5 points within r. Invalid also when two eigenvalues coincide (relative gap
<= `geometry.DEGENERATE_EPS`: collinear or isotropic supports), the keypoint normal is not finite,
or an input is not finite. Normals come from the `prepare` hook (`frames.normal_based.prepare_normals`).

References:
  Mian, Bennamoun, Owens, "On the repeatability and quality of keypoints for local feature-based
  3D object retrieval from cluttered scenes", IJCV 89(2), 2010, section 3.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.normal_based import NormalExtra, prepare_normals, usable_normals
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.geometry.ops import sanitize
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

MIN_NEIGHBORS = 5


def mian_frame(offsets, mask, kp_normal, center: str = "centroid"):
  """Mian frame of one keypoint.

  Args:
    offsets: (K, 3) pq_i (cloud units), finite.
    mask: (K,) bool.
    kp_normal: (3,) the keypoint's normal (NaN allowed: invalid).
    center: "centroid" (Mian et al.) or "keypoint".

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool); x and y have an arbitrary common sign.
  """
  w = mask.astype(offsets.dtype)
  if center == "centroid":
    cov, _ = geometry.centered_covariance(offsets, w)
  elif center == "keypoint":
    cov = geometry.weighted_covariance(offsets, w)
  else:
    raise ValueError(f"center: expected 'centroid' or 'keypoint', got {center!r}")
  _, evecs, ok = geometry.eigen_frame(cov)
  n = geometry.finite_or_zero(kp_normal)
  n_ok = jnp.all(jnp.isfinite(kp_normal)) & (geometry.safe_norm(n) > 0)
  z = geometry.orient_like(evecs[2], n)
  frame, f_ok = geometry.frame_from_zx(z, evecs[0])
  valid = ok & n_ok & f_ok & (jnp.sum(mask) >= MIN_NEIGHBORS)
  return geometry.identity_where_invalid(frame, valid), valid


def mian_frames(patches: Patches, kp_normal: AnyArray, *,
                center: str = "centroid") -> tuple[jax.Array, jax.Array]:
  """Mian frames for a batch (pure, jittable).

  Args:
    patches: `Patches` (N keypoints); `k=None` uses every neighbor (the registry's default).
    kp_normal: (N, 3) normals of the keypoints (they fix the sign of z only).
    center: "centroid" (default, Mian et al.) or "keypoint".

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  patches, finite = sanitize(patches)
  frames, valid = jax.vmap(lambda o, m, n: mian_frame(o, m, n, center))(
      patches.offsets, patches.mask, kp_normal)
  valid = valid & finite
  return geometry.identity_where_invalid(frames, valid), valid

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host from the engine's ball lists, in float64, one keypoint per thread
# (`frames.host_geometry`): `compute_frames`' default on the CPU.


@nb.njit(parallel=True, cache=True)
def _mian_host_kernel(points, centers, kp_ids, ptr, ball, normals, eps, frames, valid):
  for i in nb.prange(centers.shape[0]):
    hg.set_identity(frames, valid, i)
    start, stop = ptr[i], ptr[i + 1]
    if stop - start < MIN_NEIGHBORS:
      continue
    mean = np.zeros(3)
    cov = np.zeros((3, 3))
    hg.inner_stats(points, centers[i], ball, start, stop, np.inf, mean, cov)
    evals, evecs = np.linalg.eigh(cov)  # ascending
    n, n_ok = hg.unit_or_zero(normals[kp_ids[i]])
    if not (hg.full_spectrum_ok(evals, eps) and n_ok):
      continue
    z = evecs[:, 0].copy()
    if z[0] * n[0] + z[1] * n[1] + z[2] * n[2] < 0.0:
      z = -z
    hg.write_frame(frames, valid, i, z, evecs[:, 2].copy())


def mian_frames_host(points: np.ndarray, keypoints: np.ndarray, radius: float, index: Any, *,
                     faces: Any = None, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Mian frames (`mian_frame`, center "centroid") of `keypoints` on the host, float64.

  Args:
    points: (n, 3) float64 cloud.
    keypoints: (N,) indices.
    radius: support radius r.
    index: the cloud's `neighborhoods.SearchIndex`.
    faces: unused.
    normals: (n, 3) per-point normals (NaN where undefined).

  Returns:
    (frames (N, 3, 3) float32 rows x, y, z, the identity where invalid; valid (N,) bool).
  """
  del faces
  pts, centers, ptr, ball = hg.ball_lists(points, keypoints, radius, index)
  return hg.run_kernel(_mian_host_kernel, len(centers), pts, centers,
                       np.asarray(keypoints, np.int64), ptr, ball,
                       usable_normals(normals), hg.EPS)

# ------------------------------------------------------------------------------ registry entry

def _mian(patches: Patches, extra: NormalExtra, *, center: str = "centroid"):
  return mian_frames(patches, extra.kp_normal, center=center)


SPEC = MethodSpec(
    "mian", _mian, default_k=None, needs_normals=True, prepare=prepare_normals,
    host_frames=mian_frames_host, extra=NormalExtra,
    description="Mian et al. 2010: covariance eigenvectors, z signed by the normal (x/y sign "
                "ambiguous)")
