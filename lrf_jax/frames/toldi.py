"""TOLDI local reference frames (Yang, Zhang, Cao 2017), the hand-crafted LRF that LRF-Net builds on.

z: the normal of the neighbours within r/3 (`geometry.toldi_normal`, sign so that Σ (p - q_i)·z >= 0).
x: normalised Σ w_i v_i over all radius neighbours with v_i the tangent projection of pq_i and

* `signed=True` (default, the original C++ implementation): w_i = (r - d_i)² · sign(h_i) · h_i²,
* `signed=False` (the paper's eqs. `eq_w1`, `eq_w2`): w_i = (r - d_i)² · h_i²,

where d_i = |pq_i| and h_i = pq_i · z. Minimum neighbours as for LRF-Net (3 within r/3, a
non-vanishing weighted sum). TOLDI uses every radius neighbour: call it with `k=None`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lrf_jax import geometry
from lrf_jax.frames.lrf_net import frames_with_weight_fn
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.neighborhoods import Patches


def toldi_weights(offsets: jax.Array, z: jax.Array, radius: jax.Array,
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
    patches: `Patches` (N keypoints); use `k=None` for the original (all neighbours).
    signed: the original signed height weight (True) or the paper's unsigned eq. `eq_w2` (False).

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  frames, valid, _ = frames_with_weight_fn(
      patches, lambda o, z, r: toldi_weights(o, z, r, signed))
  return frames, valid

# ------------------------------------------------------------------------------ registry entry

def _toldi(patches: Patches, extra: None, *, signed: bool = True):
  del extra
  return toldi_frames(patches, signed=signed)


SPEC = MethodSpec(
    "toldi", _toldi, default_k=None,
    description="TOLDI (Yang et al. 2017): z over r/3, x weights (r-d)^2 sign(h) h^2 (original C++)")
