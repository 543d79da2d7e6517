"""The Chamfer loss of LRF-Net (eqs. `eq_loss`, `eq_cham`) for one pair and batched with vmap."""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from lrf_jax.frames.lrf_net import lrf_net_frames
from lrf_jax.frames.weights import Params
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

REDUCTIONS = ("min", "max", "sum")
_FAR = 1e30


def _directed_means(a: jax.Array, mask_a: AnyArray, b: jax.Array,
                    mask_b: AnyArray) -> tuple[jax.Array, jax.Array]:
  d2 = jnp.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)  # (Ka, Kb)
  pair_ok = mask_a[:, None] & mask_b[None, :]
  d2 = jnp.where(pair_ok, d2, _FAR)
  a_to_b = jnp.min(d2, axis=1)
  b_to_a = jnp.min(d2, axis=0)

  def mean_dist(sq, mask):
    ok = mask & (sq > 0) & (sq < _FAR)
    dist = jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)  # finite gradient at 0
    return jnp.sum(dist) / jnp.maximum(jnp.sum(mask), 1)

  return mean_dist(a_to_b, mask_a), mean_dist(b_to_a, mask_b)


def chamfer(a: jax.Array, mask_a: AnyArray, b: jax.Array, mask_b: AnyArray,
            reduction: str = "min") -> jax.Array:
  """Chamfer distance between two padded point sets (eq. `eq_cham`), unsquared distances.

  d_AB = mean over real a of min over real b of |a - b|, and d_BA likewise. The paper's loss is
  min(d_AB, d_BA) (`reduction="min"`, the default); "max" and "sum" (the usual symmetric Chamfer
  of the folding-net losses it cites) are options. The gradient is finite (zero) at coincident
  points. A set with no real point gives 0.

  Args:
    a: (Ka, 3) points. mask_a: (Ka,) bool.
    b: (Kb, 3) points. mask_b: (Kb,) bool.
    reduction: "min", "max" or "sum".

  Returns:
    () the distance, in the points' units.
  """
  if reduction not in REDUCTIONS:
    raise ValueError(f"reduction: expected one of {REDUCTIONS}, got {reduction!r}")
  ab, ba = _directed_means(a, mask_a, b, mask_b)
  if reduction == "min":
    return jnp.minimum(ab, ba)
  if reduction == "max":
    return jnp.maximum(ab, ba)
  return ab + ba


def batched_chamfer(a: jax.Array, mask_a: AnyArray, b: jax.Array, mask_b: AnyArray,
                    reduction: str = "min") -> jax.Array:
  """`chamfer` vmapped over a leading batch axis: (N, Ka, 3), (N, Ka), (N, Kb, 3), (N, Kb) -> (N,)."""
  # x is the 4 arrays; mypy counts *x as possibly filling `reduction` too
  return jax.vmap(lambda *x: chamfer(*x, reduction))(  # type: ignore[call-arg]
      a, mask_a, b, mask_b)


def to_frame(offsets: AnyArray, frames: jax.Array) -> jax.Array:
  """Express patch offsets (N, K, 3) in frames (N, 3, 3): q' = L q (the paper's L·Q)."""
  return jnp.einsum("nij,nkj->nki", frames, offsets)


def frames_with_view(frames_fn, params: Params, patches: Patches,
                     view: AnyArray | None) -> tuple[jax.Array, jax.Array]:
  """`frames_fn(params, patches)`, or `frames_fn(params, patches, view)` with a (N, 3) `view`:
  (frames (N, 3, 3), valid (N,)). A frames function that takes no view keeps working without."""
  return frames_fn(params, patches) if view is None else frames_fn(params, patches, view)


def siamese_loss(params: Params, model: Patches, scene: Patches, *, reduction: str = "min",
                 x_mode: str = "sum", frames_fn=None, model_view: AnyArray | None = None,
                 scene_view: AnyArray | None = None) -> tuple[jax.Array, dict[str, jax.Array]]:
  """The LRF-Net training loss (eq. `eq_loss`) over a batch of corresponding patch pairs.

  Both streams share `params`. Pairs where either frame is invalid are left out of the mean.

  Args:
    params: WeightNet parameters.
    model: `Patches` of the model keypoints (N pairs).
    scene: `Patches` of the corresponding scene keypoints (N pairs).
    reduction: Chamfer reduction, see `chamfer`.
    x_mode: "sum" or "max" (see `lrf_net_frames`).
    frames_fn (Callable | None): `(params, patches) -> (frames, valid)` replacing
      `lrf_net_frames` (ablation variants); `x_mode` is then ignored. Given a view, it is
      called as `(params, patches, view)`.
    model_view: optional (N, 3) direction the model side's z must not point away from where
      non-zero (`lrf_net.view_sign`; `Batch.model_view`, `TrainConfig.z_view`); None: none.
    scene_view: the same for the scene side (`Batch.scene_view`).

  Returns:
    (loss, aux): the mean Chamfer distance over valid pairs (cloud units); aux holds
    `per_pair` (N,), `valid` (N,) and `valid_fraction` ().
  """
  if frames_fn is None:
    frames_fn = lambda p, patches, view=None: lrf_net_frames(  # noqa: E731
        p, patches, x_mode=x_mode, view=view)
  fm, vm = frames_with_view(frames_fn, params, model, model_view)
  fs, vs = frames_with_view(frames_fn, params, scene, scene_view)
  per_pair = batched_chamfer(to_frame(model.offsets, fm), model.mask,
                             to_frame(scene.offsets, fs), scene.mask, reduction)
  valid = vm & vs
  loss = jnp.sum(jnp.where(valid, per_pair, 0.0)) / jnp.maximum(jnp.sum(valid), 1)
  return loss, {"per_pair": per_pair, "valid": valid,
                "valid_fraction": jnp.mean(valid.astype(jnp.float32))}
