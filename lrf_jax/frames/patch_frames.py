"""A registered method's jitted frame function on prepared patches (`frames_from_patches`), its
options, and the caches behind it: one jitted function per option set (`jitted_method`) and
the weight tables of the learned methods' `lut` option (`cached_weight_table`)."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Mapping
from typing import Any

from lrf_jax._jax import jax, jit
import numpy as np

from lrf_jax.frames.spec import DEFAULT_METHOD, MethodSpec, method_spec
from lrf_jax.frames.weights import default_params
from lrf_jax.search.neighborhoods import Patches


@functools.lru_cache(maxsize=64)
def jitted_method(spec: MethodSpec, static_items: tuple) -> Any:
  """The jitted frame function of method `spec` with the static options `static_items` (sorted
  (name, value) pairs), built once per option set (64 kept; `caches.clear_caches` empties it):
  called as fn(patches, extra, params) -> (frames (N, 3, 3), valid (N,))."""
  static = dict(static_items)
  if spec.needs_params:
    return jit(lambda patches, extra, params: spec.fn(patches, extra, params=params, **static))
  return jit(lambda patches, extra, params: spec.fn(patches, extra, **static))


def frames_from_patches(patches: Patches, method: str = DEFAULT_METHOD, *, params: Any = None,
                        extra: Any = None, **options: Any) -> tuple[jax.Array, jax.Array]:
  """Run a registered method's jitted frame function on prepared patches.

  Args:
    patches: `Patches` from `build_patches`.
    method: a key of `lrf_jax.METHODS` (default "lrf_net_plus", the most repeatable shipped
      method; "lrf_net" is the paper's model).
    params: learned parameters for learned methods (None: the shipped default).
    extra: what the method's `prepare` hook returned, if it has one.
    **options: static method options (e.g. `x_mode="max"` for lrf_net, `signed=False` for toldi).

  Returns:
    (frames (N, 3, 3), valid (N,)).
  """
  spec = method_spec(method)
  check_options(method, options, spec)
  return patch_frames_checked(spec, patches, params, extra, options)


def patch_frames_checked(spec: MethodSpec, patches: Patches, params: Any, extra: Any,
                         options: dict) -> tuple[jax.Array, jax.Array]:
  """`frames_from_patches` without its checks: `spec` is a registered method and `options` are
  options it takes (inputs already checked by `frames_from_patches` or `compute_frames`)."""
  options = dict(spec.default_options) | options
  if spec.needs_params and params is None:
    params = default_params(spec.weights)
  if spec.needs_params and int(options.get("lut", 0) or 0) > 1:
    params = cached_weight_table(params, int(options["lut"]))
  fn = jitted_method(spec, tuple(sorted(options.items())))
  n_dev = jax.local_device_count()
  if n_dev > 1 and patches.offsets.shape[0] % n_dev == 0:
    # Keypoints are independent: shard them over the local devices' "data" axis, replicate
    # the parameters; XLA partitions the jitted function accordingly.
    mesh = jax.make_mesh((n_dev,), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
    shard = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    patches = jax.device_put(patches, shard)
    extra = None if extra is None else jax.device_put(extra, shard)
    return fn(patches, extra, params)
  return fn(jax.device_put(patches), extra, params)


# `cached_weight_table`'s tables: (params_key, size, host, table), newest last, the 4 newest
# kept; `caches.clear_caches` empties it.
WEIGHT_TABLES: list[tuple[bytes, int, bool, Any]] = []


@jit(static_argnums=1)
def _jit_weight_table(params: Any, size: int) -> Any:
  from lrf_jax.frames.lrf_net import weight_table
  return weight_table(params, size)


def cached_weight_table(params: Any, size: int, host: bool = False) -> Any:
  """The `WeightTable` of `params` for `lut=size`, built once per parameter content
  (`_params_key`: a leaf replaced or written in place gives a new table): jitted, or with
  `host` in numpy (`weight_table_numpy`, for the host frame kernels). Traced parameters (under a
  caller's jit) are not cached."""
  from lrf_jax.frames.lrf_net import WeightTable, weight_table_numpy
  if isinstance(params, WeightTable):
    return params
  key = _params_key(params)
  for k, n, h, table in WEIGHT_TABLES:
    if key is not None and k == key and n == size and h == host:
      return table
  table = weight_table_numpy(params, size) if host else _jit_weight_table(params, size)
  if host:  # shared by every later call: read-only, so no caller can write into the cache
    assert isinstance(table.values, np.ndarray)  # weight_table_numpy's
    table.values.flags.writeable = False
  if key is not None:
    WEIGHT_TABLES.append((key, size, host, table))
    del WEIGHT_TABLES[:-4]
  return table


def _params_key(params: Any) -> bytes | None:
  """SHA-256 of a parameter tree's structure and every leaf's dtype, shape and bytes (the nets
  are small: LRF-Net's are 24 kB); None when a leaf is a JAX tracer. Needs no JAX import."""
  import hashlib
  import sys
  tracer = getattr(getattr(sys.modules.get("jax"), "core", None), "Tracer", ())
  h = hashlib.sha256()

  def visit(node: Any) -> bool:
    if isinstance(node, Mapping):
      for k in sorted(node, key=repr):
        h.update(f"{k!r}:".encode())
        if not visit(node[k]):
          return False
      return True
    if isinstance(node, (list, tuple)):
      h.update(f"{type(node).__name__}{len(node)}[".encode())
      return all(visit(v) for v in node)
    if tracer and isinstance(node, tracer):
      return False
    a = np.asarray(node)
    h.update(f"{a.dtype.str}{a.shape}|".encode())
    h.update(np.ascontiguousarray(a).tobytes())
    return True

  return h.digest() if visit(params) else None


def method_options(method: str) -> list[str]:
  """The option names `method` accepts (keyword arguments of its frame function)."""
  return _option_names(method_spec(method))


def _option_names(spec: MethodSpec) -> list[str]:
  params = inspect.signature(spec.fn).parameters.values()
  return sorted(p.name for p in params if p.kind is p.KEYWORD_ONLY and p.name != "params")


def check_options(method: str, options: dict, spec: MethodSpec) -> None:
  """Raise unless `spec` (the method registered as `method`) takes every option in `options`."""
  valid = _option_names(spec)
  unknown = sorted(set(options) - set(valid))
  if unknown:
    raise ValueError(f"options: unknown option(s) {unknown} for method {method!r}; its options "
                     f"are {valid or 'none'}")
