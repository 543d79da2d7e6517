"""The LRF-Net weight network (flax.linen); the only module of lrf_jax that imports flax.

The paper (section 3.1, "a U-Net with MLP layers only") feeds each radius neighbour's two invariant
attributes (distance / r, cos(z, pq)) through per-point MLP layers and predicts one weight per
neighbour. The figure with its layer sizes is missing from our copy, so the sizes are ours:

    encoder   2 -> 16 -> 32 -> 64          (Dense + ReLU, per point)
    decoder  64 -> 32 (concat enc 32) -> 16 (concat enc 16) -> 1

about 6.6k parameters. Why this size: the network maps a 2-D input to a scalar, so it only needs
the capacity to draw a smooth 2-D weight map w(d, cos θ), and every extra width costs K x width
FLOPs per keypoint on the hot path. The
output is linear (signed weights): TOLDI's own weight (r - d)² sign(h) h² is signed, and a positive
activation could not express it. The weights only matter up to a positive scale (x is normalised).
lrf_net_plus reads the same output as a log-weight (`frames.lrf_net.softmax_weights`).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import serialization

Params = Any

WEIGHTS_DIR = Path(__file__).parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "lrf_net.msgpack"


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


def init_params(seed: int = 0, num_attributes: int = 2,
                widths: Sequence[int] = (16, 32, 64)) -> Params:
  """Seeded initial parameters of `WeightNet`.

  Args:
    seed: PRNG seed (`jax.random.key(seed)`).
    num_attributes: A, the number of per-point attributes (2 in the paper).
    widths: encoder widths.

  Returns:
    A flax params pytree.
  """
  model = WeightNet(widths=tuple(widths))
  return model.init(jax.random.key(seed), jnp.zeros((1, num_attributes), jnp.float32))["params"]


def apply_weights(params: Params, attrs: jax.Array) -> jax.Array:
  """Weights (..., K) for attributes (..., K, A), with the network shape read from `params`."""
  widths = tuple(params[f"enc{i}"]["kernel"].shape[1] for i in range(_num_enc(params)))
  return WeightNet(widths=widths).apply({"params": params}, attrs)


def _num_enc(params: Params) -> int:
  return sum(1 for name in params if name.startswith("enc"))


def save_params(params: Params, path: str | Path) -> None:
  """Write parameters as flax msgpack (a few KB)."""
  Path(path).parent.mkdir(parents=True, exist_ok=True)
  Path(path).write_bytes(serialization.msgpack_serialize(jax.device_get(params)))


def load_params(path: str | Path) -> Params:
  """Read parameters written by `save_params`.

  Raises:
    FileNotFoundError: when `path` does not exist.
    ValueError: when the file is not a parameter file of this network.
  """
  path = Path(path)
  if not path.exists():
    raise FileNotFoundError(f"{path}: no such parameter file")
  try:
    params = serialization.msgpack_restore(path.read_bytes())
  except Exception as e:  # msgpack raises several types on garbage
    raise ValueError(f"{path}: not a flax msgpack parameter file ({e})") from e
  weightnet = isinstance(params, dict) and "out" in params and _num_enc(params) > 0
  variant = (isinstance(params, dict) and params
             and set(params) <= {"weights", "x_reg", "z_reg"})  # ablation variants
  if not (weightnet or variant):
    raise ValueError(f"{path}: expected WeightNet parameters (enc*/dec*/out) or ablation "
                     f"parameters (weights/x_reg/z_reg), got keys "
                     f"{sorted(params) if isinstance(params, dict) else type(params)}")
  return jax.tree.map(jnp.asarray, params)


@functools.lru_cache(maxsize=8)
def _default_params_cached(name: str) -> Params:
  path = WEIGHTS_DIR / f"{name}.msgpack"
  # Concrete arrays even when the first call happens inside a jit trace: the cache would
  # otherwise keep (and later leak) that trace's tracers.
  with jax.ensure_compile_time_eval():
    if path.exists():
      return load_params(path)
    return init_params(0)


def default_params(name: str = "lrf_net") -> Params:
  """The shipped weights `lrf_jax/weights/<name>.msgpack` ("lrf_net": the paper's model trained
  with the default config; "lrf_net_plus": see that method), or, where none are shipped, the
  seeded initialisation `init_params(0)`."""
  return _default_params_cached(name)


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


def apply_regressor(params: Params, feats: jax.Array, mask: jax.Array) -> jax.Array:
  """(..., K, F), (..., K) -> (..., 3)."""
  return PointRegressor().apply({"params": params}, feats, mask)
