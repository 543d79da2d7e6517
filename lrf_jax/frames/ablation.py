"""The paper's 8-way ablation (section 3.3, tables analyse_BR/_UWA3M/_UWAOR) as one function.

z-axis: "normal" (the TOLDI normal over r/3, as LRF-Net) or "dr" (regressed by a PointNet from
the raw offsets q_i / r).
x-axis, given z:
  "sum1" LRF-Net: weights from the invariant attributes (|pq|/r, cos(z, pq)), weighted vector sum;
  "sum2" weights from the raw [q_i / r, z] (6 numbers, not rotation invariant), vector sum;
  "dr"   x regressed directly by a PointNet from [q_i / r, z], projected on the tangent plane;
  "max"  the tangent projection of the neighbor with the largest Sum1 weight (no gradient
         through the argmax, so it reuses weights trained for "sum1").
(normal, sum1) is exactly `lrf_net_frames`. Parameters are a dict with the parts a variant uses:
"weights" (WeightNet), "z_reg" / "x_reg" (PointRegressor). The networks are defined and
initialised in flax (`lrf_jax.learning.networks`, `lrf_jax.learning.model.init_variant_params`);
their forward passes here need no flax (`apply_weights`, `apply_regressor`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lrf_jax._jax import jax, jnp

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames.lrf_net import attributes, frame_from_weights, z_axes
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.geometry.ops import sanitize
from lrf_jax.frames.weights import Params, apply_weights
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

Z_MODES = ("normal", "dr")
X_MODES = ("sum1", "sum2", "dr", "max")


def check_modes(z_mode: str, x_mode: str) -> None:
  if z_mode not in Z_MODES:
    raise ValueError(f"z_mode: expected one of {Z_MODES}, got {z_mode!r}")
  if x_mode not in X_MODES:
    raise ValueError(f"x_mode: expected one of {X_MODES}, got {x_mode!r}")


def apply_regressor(params: Params, feats: AnyArray, mask: AnyArray) -> jax.Array:
  """The forward pass of `learning.networks.PointRegressor` without flax: (..., K, F) features and
  (..., K) mask -> (..., 3). The same operations as flax's `Dense` (`lax.dot_general` over the
  last axis, then the bias); `tests/test_weights_shipped.py` holds the two equal."""

  def dense(layer, h):
    dtype = jnp.result_type(h, layer["kernel"], layer["bias"])  # flax's promote_dtype
    h, kernel, bias = (jnp.asarray(a, dtype) for a in (h, layer["kernel"], layer["bias"]))
    y = jax.lax.dot_general(h, kernel, (((h.ndim - 1,), (0,)), ((), ())))
    return y + jnp.reshape(bias, (1,) * (y.ndim - 1) + (-1,))

  h = jax.nn.relu(dense(params["p0"], feats))
  h = jax.nn.relu(dense(params["p1"], h))
  h = jnp.max(jnp.where(mask[..., None], h, -1e9), axis=-2)
  h = jnp.where(jnp.any(mask, axis=-1, keepdims=True), h, 0.0)
  h = jax.nn.relu(dense(params["g0"], h))
  return dense(params["g1"], h)


def variant_frames(params: dict[str, Params], patches: Patches, *, z_mode: str = "normal",
                   x_mode: str = "sum1") -> tuple[jax.Array, jax.Array]:
  """Frames of an ablation variant for a batch of patches: (N, 3, 3) rows x, y, z; (N,) valid."""
  check_modes(z_mode, x_mode)
  patches, finite = sanitize(patches)
  rel = patches.offsets / patches.radius[:, None, None]
  if z_mode == "normal":
    z, z_ok = z_axes(patches)
  else:
    z, z_ok = geometry.safe_normalize(apply_regressor(params["z_reg"], rel, patches.mask))
  z_ok = z_ok & finite
  if x_mode == "dr":
    feats = jnp.concatenate([rel, jnp.broadcast_to(z[:, None, :], rel.shape)], axis=-1)
    x_raw = apply_regressor(params["x_reg"], feats, patches.mask)
    frames, ok = jax.vmap(geometry.frame_from_zx)(z, x_raw)
    valid = z_ok & ok
    return geometry.identity_where_invalid(frames, valid), valid
  if x_mode == "sum2":
    feats = jnp.concatenate([rel, jnp.broadcast_to(z[:, None, :], rel.shape)], axis=-1)
    w = apply_weights(params["weights"], feats)
  else:
    w = apply_weights(params["weights"],
                      jax.vmap(attributes)(patches.offsets, z, patches.radius))
  if x_mode == "max":
    idx = jnp.argmax(jnp.where(patches.mask, w, -jnp.inf), axis=-1)
    w = jax.nn.one_hot(idx, w.shape[-1], dtype=w.dtype)
  return jax.vmap(frame_from_weights)(patches.offsets, patches.mask, z, z_ok, w)


# ------------------------------------------------------------------------------ registry entry


def _variant(patches: Patches, extra: None, *, params, z_mode: str = "normal",
             x_mode: str = "sum1"):
  del extra
  if not any(k in params for k in ("weights", "x_reg", "z_reg")):
    params = {"weights": params}  # plain LRF-Net parameters
  return variant_frames(params, patches, z_mode=z_mode, x_mode=x_mode)


SPEC = MethodSpec(
    "lrf_net_variant", _variant, default_k=256, needs_params=True,
    description="LRF-Net ablation variants (options z_mode: normal/dr, x_mode: sum1/sum2/dr/max)")
