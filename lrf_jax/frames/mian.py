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

import functools
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
  return batch_frames(functools.partial(mian_frame, center=center), patches, ("offsets", "mask"),
                      kp_normal)

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host from the engine's ball lists, in float64, one keypoint per thread
# (`frames.host_geometry`): `compute_frames`' default on the CPU.


@nb.njit(parallel=True, cache=True)
def _mian_host_kernel(points, centers, ptr, ball, kp_ids, normals, eps, frames, valid):
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    if stop - start < MIN_NEIGHBORS:
      continue
    mean = np.zeros(3)
    cov = np.zeros((3, 3))
    hg.inner_stats(points, centers[i], ball, start, stop, np.inf, mean, cov)
    evals, evecs = np.linalg.eigh(cov)  # ascending
    z, n_ok = hg.z_signed_by(evecs, normals[kp_ids[i]])
    if not (hg.full_spectrum_ok(evals, eps) and n_ok):
      continue
    hg.write_frame(frames, valid, i, z, evecs[:, 2].copy())


# ------------------------------------------------------------------------------ registry entry

def _mian(patches: Patches, extra: NormalExtra, *, center: str = "centroid"):
  return mian_frames(patches, extra.kp_normal, center=center)


SPEC = MethodSpec(
    "mian", _mian, default_k=None, needs_normals=True, prepare=prepare_normals,
    extra=NormalExtra,
    host_frames=BallKernel(_mian_host_kernel, ("keypoints", "normals"), (hg.EPS,)),
    description="Mian et al. 2010: covariance eigenvectors, z signed by the normal (x/y sign "
                "ambiguous)")
