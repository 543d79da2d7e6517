"""TOLDI local reference frames (Yang, Zhang, Cao 2017), the hand-crafted LRF that LRF-Net builds on.

z: the normal of the neighbors within r/3 (`geometry.toldi_normal`, sign so that Σ (p - q_i)·z >= 0).
x: normalised Σ w_i v_i over all radius neighbors with v_i the tangent projection of pq_i and

* `signed=True` (default, the original C++ implementation): w_i = (r - d_i)² · sign(h_i) · h_i²,
* `signed=False` (the paper's eqs. `eq_w1`, `eq_w2`): w_i = (r - d_i)² · h_i²,

where d_i = |pq_i| and h_i = pq_i · z. Minimum neighbors as for LRF-Net (3 within r/3, a
non-vanishing weighted sum). TOLDI uses every radius neighbor: call it with `k=None`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.host_path import BallKernel
from lrf_jax.frames.lrf_net import MIN_Z_NEIGHBORS, X_EPS, frames_with_weight_fn
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# The z support: the ball of radius Z_RATIO · r whose points' plane gives z.
Z_RATIO = 1.0 / 3.0


def toldi_weights(offsets: AnyArray, z: jax.Array, radius: AnyArray,
                  signed: bool = True) -> jax.Array:
  """TOLDI's x weights for a batch: offsets (N, K, 3), z (N, 3), radius (N,) -> (N, K).

  Computed on the offsets in units of r, (1 - d/r)^2 (h/r)^2: the original (r - d)^2 h^2 over
  r^4, the same x-axis, but scale free: in float32 the unscaled fourth powers underflow for
  clouds in small units (r ~ 1e-4) and overflow for large ones (r ~ 1e6).
  """
  r = radius[:, None]
  d = geometry.safe_norm(offsets) / r
  h = jnp.einsum("nkc,nc->nk", offsets, z) / r
  w = (1.0 - d) ** 2 * h * h
  return w * jnp.sign(h) if signed else w


def toldi_frames(patches: Patches, *, signed: bool = True) -> tuple[jax.Array, jax.Array]:
  """TOLDI frames for a batch of patches.

  Args:
    patches: `Patches` (N keypoints); use `k=None` for the original (all neighbors).
    signed: the original signed height weight (True) or the paper's unsigned eq. `eq_w2` (False).

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  frames, valid, _ = frames_with_weight_fn(
      patches, lambda o, z, r: toldi_weights(o, z, r, signed))
  return frames, valid

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host from the engine's ball lists, in float64, one keypoint per thread
# (`frames.host_geometry`): `compute_frames`' default on the CPU.


@nb.njit(inline="always")
def _toldi_weight(data, t, ox, oy, oz, z):
  """`toldi_weights` of one neighbor (`hg.x_axis_sum_of`'s `weight`): (1 - d/r)^2 (h/r)^2 with
  d = |o|, h = o · z (cloud units), times sign(h) when signed; data = (r, signed). Returns
  (the weight, h)."""
  r, signed = data
  d = np.sqrt(ox * ox + oy * oy + oz * oz) / r
  dot = ox * z[0] + oy * z[1] + oz * z[2]
  h = dot / r
  w = (1.0 - d) ** 2 * h * h
  if signed:
    w = w if h > 0.0 else (-w if h < 0.0 else 0.0)
  return w, dot


_x_axis_sum = hg.x_axis_sum_of(_toldi_weight)


@nb.njit(parallel=True, cache=True)
def _toldi_host_kernel(points, centers, ptr, ball, r, rz2, signed, eps, x_eps, frames, valid):
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    ok, z, mean = hg.plane_z(points, centers[i], ball, start, stop, rz2, eps, MIN_Z_NEIGHBORS)
    if not ok:
      continue
    if mean[0] * z[0] + mean[1] * z[1] + mean[2] * z[2] > 0.0:
      z = -z
    ok, s = _x_axis_sum(points, centers[i], ball, start, stop, z, (r, signed), x_eps)
    if ok:
      hg.write_frame(frames, valid, i, z, s)


# ------------------------------------------------------------------------------ registry entry

def _toldi(patches: Patches, extra: None, *, signed: bool = True):
  del extra
  return toldi_frames(patches, signed=signed)


# The host kernel's constants: signed=True (the host path runs without options: the default
# weight), then its tolerances.
SPEC = MethodSpec(
    "toldi", _toldi, default_k=None, z_ratio=Z_RATIO,
    host_frames=BallKernel(_toldi_host_kernel, ("radius", "rz2"), (True, hg.EPS, X_EPS), Z_RATIO),
    description="TOLDI (Yang et al. 2017): z over r/3, x weights (r-d)^2 sign(h) h^2 (original C++)")
