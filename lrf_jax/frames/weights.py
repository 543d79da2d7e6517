"""The LRF-Net weight network for inference: its forward pass, parameter files, shipped weights.

The paper (section 3.1, "a U-Net with MLP layers only") feeds each radius neighbor's two invariant
attributes (distance / r, cos(z, pq)) through per-point MLP layers and predicts one weight per
neighbor. The figure with its layer sizes is missing from our copy, so the sizes are ours:

    encoder   2 -> 16 -> 32 -> 64          (Dense + ReLU, per point)
    decoder  64 -> 32 (concat enc 32) -> 16 (concat enc 16) -> 1

about 6.6k parameters. Why this size: the network maps a 2-D input to a scalar, so it only needs
the capacity to draw a smooth 2-D weight map w(d, cos θ), and every extra width costs K x width
FLOPs per keypoint on the hot path. The
output is linear (signed weights): TOLDI's own weight (r - d)² sign(h) h² is signed, and a positive
activation could not express it. The weights only matter up to a positive scale (x is normalised).
lrf_net_plus reads the same output as a log-weight (`frames.lrf_net.softmax_weights`).

The layers are defined as flax.linen modules in `lrf_jax.learning.networks` (initialised by
`lrf_jax.learning.model.init_params`); this module evaluates them from the parameter dict without
flax (`apply_weights`, in `jax.numpy` or numpy) and reads parameter files with `msgpack` (flax's
format), so inference never imports flax (nor anything of `lrf_jax.learning`); saving imports
flax's serializer.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from lrf_jax._jax import is_jax_numpy, jax, jnp
import msgpack
import numpy as np

from lrf_jax.defaults import WEIGHTS_KINDS
from lrf_jax.extras import missing_extra

Params = Any

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"  # lrf_jax/weights
DEFAULT_WEIGHTS = WEIGHTS_DIR / "lrf_net.msgpack"



def shipped_file(method_weights: str, kind: str) -> Path:
  """Where the shipped weights of `kind` (a `WEIGHTS_KINDS` entry) live for a method whose own
  file is `method_weights`: "objects" is that file, "rooms" and "streets" are
  `<method_weights>_<kind>.msgpack` (shipped for lrf_net_plus only). It may not exist."""
  return WEIGHTS_DIR / (f"{method_weights}.msgpack" if kind == "objects"
                        else f"{method_weights}_{kind}.msgpack")


def is_shipped(path: str | Path) -> bool:
  """Whether `path` is one of the package's own parameter files (read once per process)."""
  return Path(path).resolve().parent == WEIGHTS_DIR


def learned_weights_file(spec: Any, weights: str | Path) -> Path:
  """`weights_file` for the method `spec` (a `MethodSpec`), which must be a learned one.

  Raises:
    ValueError: a hand-crafted method (it reads no weights; the message lists the learned
      ones), and as `weights_file`.
  """
  if not spec.needs_params:
    from lrf_jax.frames.spec import METHODS  # pylint: disable=import-outside-toplevel
    raise ValueError(f"weights: method {spec.name!r} is hand-crafted and reads no weights; "
                     f"learned methods: {sorted(n for n, s in METHODS.items() if s.needs_params)}")
  return weights_file(spec.weights, weights)


def weights_file(method_weights: str, weights: str | Path) -> Path:
  """The parameter file `weights=` selects for a method whose own shipped file is
  `method_weights` (`MethodSpec.weights`, e.g. "lrf_net_plus").

  Args:
    method_weights: the method's shipped file stem.
    weights: "objects" (the method's own file: what the method reads when no weights are
      given), "rooms" or "streets" (`<method_weights>_<kind>.msgpack`, trained on room fragments /
      LiDAR sweeps), or the path of a parameter file (`save_params`' flax msgpack, such as a
      `train.py` workdir's `best_params.msgpack`).

  Returns:
    The file's path (not read here: `load_params` checks its content).

  Raises:
    ValueError: `weights` is neither a kind nor an existing file, or a kind not shipped for
      this method (the message lists the kinds that are).
  """
  if isinstance(weights, str) and weights in WEIGHTS_KINDS:
    path = shipped_file(method_weights, weights)
    if not path.exists():
      shipped = [k for k in WEIGHTS_KINDS if shipped_file(method_weights, k).exists()]
      raise ValueError(f"weights: no {weights!r} weights are shipped for {method_weights} "
                       f"(expected one of {shipped} or a parameter file's path)")
    return path
  if not isinstance(weights, (str, Path)) or not str(weights):
    raise ValueError(f"weights: expected one of {list(WEIGHTS_KINDS)} or a parameter file's "
                     f"path, got {weights!r}")
  path = Path(weights)
  if not path.is_file():
    raise ValueError(f"weights: {str(weights)!r} is not one of {list(WEIGHTS_KINDS)} and no "
                     "such parameter file exists")
  return path


def weights_params(method_weights: str, weights: str | Path = "objects", *,
                   host: bool = False) -> Params:
  """The parameters `weights=` selects (`weights_file`): a shipped file read once per process
  (`default_params`), another file on every call (`load_params`); numpy arrays for the host
  kernels (`host`), else arrays on JAX's default device. Raises as `weights_file` and
  `load_params` do."""
  path = weights_file(method_weights, weights)
  if is_shipped(path):
    return default_params_numpy(path.stem) if host else default_params(path.stem)
  return load_params_numpy(path) if host else load_params(path)


def weights_options(path: str | Path) -> dict[str, Any]:
  """The method options a parameter file was trained under and is read with: the "options"
  object of the JSON file beside it (`<stem>.json`; `{}` when there is none or it holds none).
  A shipped "streets" file, trained with z signed over each support, says `{"vote": false}`:
  without a viewpoint its frames take the ball sign, not the convexity vote.

  Raises:
    ValueError: the JSON file exists but is not an object, or its "options" is not one.
  """
  import json  # pylint: disable=import-outside-toplevel
  meta = Path(path).with_suffix(".json")
  if not meta.is_file():
    return {}
  try:
    d = json.loads(meta.read_text())
  except ValueError as e:
    raise ValueError(f"{meta}: expected JSON ({e})") from e
  options = d.get("options", {}) if isinstance(d, dict) else None
  if not isinstance(options, dict):
    raise ValueError(f"{meta}: options: expected an object of method options, got {options!r}")
  return dict(options)


def apply_weights(params: Params, attrs: Any, xp: Any = jnp, dtype: Any = None) -> Any:
  """Weights (..., K) for attributes (..., K, A): the forward pass of `learning.networks.WeightNet`
  (the definition, in flax) without flax; `tests/test_weights_shipped.py` holds the two equal.

  Encoder Dense+ReLU layers enc0..enc{m-1}, decoder Dense+ReLU layers dec0..dec{m-2} each
  concatenated with the encoder output of the same width, and a linear Dense "out" to one
  value; the widths are read from `params`. Every caller evaluates the network through this
  function: the jitted frames and training (jax.numpy), the host kernels' weight table
  (`lrf_net.weight_table(..., xp=np)`, numpy float32: no JAX program to trace and load in a
  fresh process) and the tests' float64 reference (`tests/reference_numpy.py`).

  Args:
    params: WeightNet parameters, {"enc<i>", "dec<i>", "out"} each {"kernel", "bias"}.
    attrs: (..., K, A) per-neighbor attributes (`lrf_net.attributes`: |pq|/r and cos(z, pq),
      dimensionless).
    xp: the array module, jax.numpy (traceable and differentiable) or numpy.
    dtype: the float type the parameters and attributes are cast to first (None: as given);
      numpy callers give np.float32 or np.float64.

  Returns:
    (..., K) weights (dimensionless, any sign), an `xp` array.
  """
  relu = jax.nn.relu if is_jax_numpy(xp) else (lambda h: np.maximum(h, 0.0))

  def dense(layer, h):
    return h @ xp.asarray(layer["kernel"], dtype) + xp.asarray(layer["bias"], dtype)

  n_enc = _num_enc(params)
  h = xp.asarray(attrs, dtype)
  skips = []
  for i in range(n_enc):
    h = relu(dense(params[f"enc{i}"], h))
    skips.append(h)
  skips.pop()  # the bottleneck is not concatenated with itself
  for i in range(n_enc - 1):
    h = relu(dense(params[f"dec{i}"], h))
    h = xp.concatenate([h, skips.pop()], axis=-1)
  return dense(params["out"], h)[..., 0]


def apply_weights_numpy(params: Params, attrs: np.ndarray) -> np.ndarray:
  """`apply_weights` in numpy float32 (`xp=np, dtype=np.float32`) for host callers (no JAX
  program to trace, lower and load): attrs (..., K, A) -> weights (..., K) float32. numpy's BLAS
  runs on one thread here (`search.grid.serial_blas`): threaded BLAS beside numba's threads was
  up to 25x slower on 2 cores."""
  from lrf_jax.search.grid import serial_blas  # pylint: disable=import-outside-toplevel
  with serial_blas():
    return apply_weights(params, attrs, np, np.float32)


def _num_enc(params: Params) -> int:
  return sum(1 for name in params if name.startswith("enc"))


def save_params(params: Params, path: str | Path) -> None:
  """Write parameters as flax msgpack (a few KB)."""
  try:
    from flax import serialization  # only to write
  except ImportError as e:
    raise missing_extra(e.name, "train", "save_params (writing flax msgpack)") from e
  Path(path).parent.mkdir(parents=True, exist_ok=True)
  from lrf_jax.io import atomic  # pylint: disable=import-outside-toplevel
  atomic.write_bytes(path, serialization.msgpack_serialize(jax.device_get(params)))


def load_params(path: str | Path) -> Params:
  """Read parameters written by `save_params`, as arrays on JAX's default device.

  Raises:
    FileNotFoundError: when `path` does not exist.
    ValueError: when the file is not a parameter file of this network.
  """
  return jax.device_put(load_params_numpy(path))


def load_params_numpy(path: str | Path) -> Params:
  """`load_params` as numpy arrays (no JAX: what the host kernels read). Raises as it does."""
  path = Path(path)
  if not path.exists():
    raise FileNotFoundError(f"{path}: no such parameter file")
  try:
    params = msgpack.unpackb(path.read_bytes(), ext_hook=_unpack_array, raw=False)
  except Exception as e:  # msgpack raises several types on garbage
    raise ValueError(f"{path}: not a flax msgpack parameter file ({e})") from e
  weightnet = isinstance(params, dict) and "out" in params and _num_enc(params) > 0
  variant = (isinstance(params, dict) and params
             and set(params) <= {"weights", "x_reg", "z_reg"})  # ablation variants
  if not (weightnet or variant):
    raise ValueError(f"{path}: expected WeightNet parameters (enc*/dec*/out) or ablation "
                     f"parameters (weights/x_reg/z_reg), got keys "
                     f"{sorted(params) if isinstance(params, dict) else type(params)}")
  return params


@functools.lru_cache(maxsize=8)
def default_params_numpy_cached(name: str) -> Params:
  """The shipped weights `name` as read-only numpy arrays, read once per process (8 kept;
  `caches.clear_caches` empties it). Shared by every caller: hand out new dicts around them
  (`default_params_numpy`), never these. Raises as `default_params` does."""
  path = WEIGHTS_DIR / f"{name}.msgpack"
  if not path.exists():
    shipped = sorted(p.stem for p in WEIGHTS_DIR.glob("*.msgpack"))
    raise ValueError(f"default_params: no shipped weights named {name!r} (expected one of "
                     f"{', '.join(shipped) or 'none: the package was installed without its weights'}"
                     f", from {WEIGHTS_DIR}); init_params(seed) gives an untrained network")
  params = load_params_numpy(path)
  for leaf in _leaves(params):  # shared by every caller: read-only
    if isinstance(leaf, np.ndarray):
      leaf.flags.writeable = False
  return params


def _leaves(tree: Any) -> list[Any]:
  if isinstance(tree, dict):
    return [x for v in tree.values() for x in _leaves(v)]
  return [tree]


def _fresh_containers(tree: Any) -> Any:
  """`tree` with new dicts (the same, immutable or read-only, leaves): a caller who replaces a
  leaf of what `default_params` handed out changes no later call's parameters."""
  if isinstance(tree, dict):
    return {k: _fresh_containers(v) for k, v in tree.items()}
  return tree


@functools.lru_cache(maxsize=8)
def default_params_cached(name: str) -> Params:
  """The shipped weights `name` on the default device, put there once per process (8 kept;
  `caches.clear_caches` empties it). Shared by every caller: hand out new dicts around them
  (`default_params`), never these. Raises as `default_params` does."""
  params = default_params_numpy_cached(name)
  # Concrete arrays even when the first call happens inside a jit trace: the cache would
  # otherwise keep (and later leak) that trace's tracers.
  with jax.ensure_compile_time_eval():
    return jax.device_put(params)


def default_params_numpy(name: str = "lrf_net") -> Params:
  """`default_params(name)` as numpy arrays, read once per process (no JAX: the host kernels'
  form; read-only arrays in new dicts). Raises as `default_params` does."""
  return _fresh_containers(default_params_numpy_cached(name))


def default_params(name: str = "lrf_net") -> Params:
  """The shipped weights `lrf_jax/weights/<name>.msgpack` ("lrf_net": the paper's model trained
  with the default config; "lrf_net_plus" and "lrf_net_plus_points": see that method).

  Raises:
    ValueError: no weights of that name are shipped (the message lists those that are; an
      untrained network is `lrf_jax.init_params(seed)`, never given in their place).

  Each call returns new dicts around the (immutable) cached arrays: replacing a leaf of the
  result changes no later call.
  """
  return _fresh_containers(default_params_cached(name))


def _unpack_array(code: int, data: bytes) -> Any:
  """flax.serialization's msgpack extension types: 1 an ndarray, 3 a numpy scalar."""
  if code not in (1, 3):
    raise ValueError(f"msgpack extension type {code} (expected 1, an array, or 3, a scalar)")
  shape, dtype, buffer = msgpack.unpackb(data, raw=True)
  arr = np.frombuffer(buffer, dtype=np.dtype(dtype.decode())).reshape(shape)
  return arr if code == 1 else arr[()]
