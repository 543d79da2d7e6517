"""Repeatability of LRFs: MeanCos (paper eqs. `eq_meancos`, `eq_LRFtrans`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def meancos(frames_a, frames_b, rotation, valid_a=None, valid_b=None):
  """Per-keypoint MeanCos between model frames and ground-truth-corresponding scene frames.

  The scene frame is mapped back by the ground-truth rotation R (model -> scene) before the axes
  are compared: with rows as axes, a perfectly repeatable scene frame is L_s = L_m Rᵀ, so
  cos x = x_m · (Rᵀ x_s) and likewise for z. MeanCos = (cos x + cos z) / 2; keypoints where either
  frame is invalid count as 0.

  Args:
    frames_a: (N, 3, 3) model frames (rows x, y, z).
    frames_b: (N, 3, 3) scene frames.
    rotation: (3, 3) ground-truth rotation model -> scene (or a (4, 4) transform; its rotation
      block is used).
    valid_a: optional (N,) bool.
    valid_b: optional (N,) bool.

  Returns:
    (N,) MeanCos in [-1, 1].
  """
  rot = jnp.asarray(rotation)
  if rot.shape == (4, 4):
    rot = rot[:3, :3]
  if rot.shape != (3, 3):
    raise ValueError(f"rotation: expected a (3, 3) rotation or (4, 4) transform, got {rot.shape}")
  fa, fb = jnp.asarray(frames_a), jnp.asarray(frames_b)
  if fa.shape != fb.shape or fa.shape[-2:] != (3, 3):
    raise ValueError(f"frames: expected two (N, 3, 3) arrays of the same shape, got {fa.shape} "
                     f"and {fb.shape}")
  back = jnp.einsum("nij,jk->nik", fb, rot)  # rows R^T x_s: (x_s^T R)
  cos_x = jnp.sum(fa[:, 0] * back[:, 0], axis=-1)
  cos_z = jnp.sum(fa[:, 2] * back[:, 2], axis=-1)
  mc = 0.5 * (cos_x + cos_z)
  ok = jnp.ones(mc.shape, bool)
  if valid_a is not None:
    ok = ok & jnp.asarray(valid_a)
  if valid_b is not None:
    ok = ok & jnp.asarray(valid_b)
  return jnp.where(ok, mc, 0.0)


def repeatability_summary(mc, valid=None, threshold: float = 0.97) -> dict[str, float]:
  """Mean MeanCos, the fraction above `threshold` and the number of valid frames."""
  mc = np.asarray(mc)
  out = {"meancos": float(mc.mean()) if mc.size else float("nan"),
         f"frac_above_{threshold}": float((mc > threshold).mean()) if mc.size else float("nan"),
         "n_keypoints": int(mc.size)}
  if valid is not None:
    out["n_valid"] = int(np.asarray(valid).sum())
  return out
