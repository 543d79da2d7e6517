"""The flax.linen modules: LRF-Net's weight network and the ablation's direct regressor.

Flax is imported here and nowhere on the inference path: `WeightNet` defines the weight
network, and `lrf_jax.frames.weights.apply_weights` evaluates the same layers from the parameter dict without
flax, in `jax.numpy` or numpy (tests/test_weights_shipped.py holds it equal to
`WeightNet.apply`), so computing frames or registering scans never pays flax's import. These
modules define the parameter layout and initialise it (`model.init_params` and `model.init_variant_params` call them).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast
from collections.abc import Sequence

import jax
import jax.numpy as jnp

from lrf_jax.extras import missing_extra

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

try:
  import flax.linen as nn
except ImportError as e:  # the [train] extra
  raise missing_extra(e.name, "train", "LRF-Net's flax modules (training, the 'dr' ablation)") from e

Params = Any


class WeightNet(nn.Module):
  """Per-point U-Net of MLP layers: attributes (..., K, A) -> weights (..., K).

  Attributes:
    widths: encoder widths; the decoder mirrors them with skip connections.
  """

  widths: Sequence[int] = (16, 32, 64)

  @nn.compact
  def __call__(self, attrs: jax.Array) -> jax.Array:
    h = attrs
    skips = []
    for i, w in enumerate(self.widths):
      h = nn.relu(nn.Dense(w, name=f"enc{i}")(h))
      skips.append(h)
    skips.pop()  # the bottleneck is not concatenated with itself
    for i, w in enumerate(reversed(self.widths[:-1])):
      h = nn.relu(nn.Dense(w, name=f"dec{i}")(h))
      h = jnp.concatenate([h, skips.pop()], axis=-1)
    return nn.Dense(1, name="out")(h)[..., 0]


def init_weight_net(seed: int, num_attributes: int, widths: Sequence[int]) -> Params:
  """Seeded `WeightNet` parameters for `num_attributes` inputs per point."""
  model = WeightNet(widths=tuple(widths))
  return model.init(jax.random.key(seed), jnp.zeros((1, num_attributes), jnp.float32))["params"]


class PointRegressor(nn.Module):
  """PointNet-style direct regressor of one 3-vector from a padded point set (ablation "DR").

  Per-point MLP (in -> 32 -> 64, ReLU), masked max pooling, MLP 64 -> 32 -> 3. The paper's DR
  figure is lost; this is the smallest common design that can regress a direction.
  """

  @nn.compact
  def __call__(self, feats: jax.Array, mask: jax.Array) -> jax.Array:
    h = nn.relu(nn.Dense(32, name="p0")(feats))
    h = nn.relu(nn.Dense(64, name="p1")(h))
    h = jnp.max(jnp.where(mask[..., None], h, -1e9), axis=-2)
    h = jnp.where(jnp.any(mask, axis=-1, keepdims=True), h, 0.0)
    h = nn.relu(nn.Dense(32, name="g0")(h))
    return nn.Dense(3, name="g1")(h)


def init_regressor(seed: int, num_features: int) -> Params:
  """Seeded parameters of `PointRegressor` for inputs with `num_features` per point."""
  return PointRegressor().init(jax.random.key(seed), jnp.zeros((1, 4, num_features)),
                               jnp.ones((1, 4), bool))["params"]


def apply_regressor(params: Params, feats: AnyArray, mask: AnyArray) -> jax.Array:
  """(..., K, F), (..., K) -> (..., 3)."""
  # without `mutable`, apply returns the module's output alone (not an (output, state) pair)
  return cast(jax.Array, PointRegressor().apply({"params": params}, feats, mask))
