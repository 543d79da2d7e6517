"""Every function lrf_jax jits multiplies float32 matrices at full precision, whatever
`jax.default_matmul_precision` the caller set (`lrf_jax._jax.exact_matmuls`). On a GPU, JAX's
default lets products run in TF32, which moved frames by up to 0.03 against the float64 host
kernels; on a CPU every precision gives the same numbers, so this is checked on the traced
programs: each `dot_general` carries precision HIGHEST even under an outer "bfloat16"."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lrf_jax
from lrf_jax import _jax, datasets
from lrf_jax.frames import patch_frames
from lrf_jax import descriptors as descriptors_mod
from lrf_jax.search import device as device_search

HIGHEST = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)


def _precisions(jaxpr) -> list:
  """The precision of every dot_general in `jaxpr` and the programs nested in it."""
  found = []
  for eqn in jaxpr.eqns:
    if eqn.primitive.name == "dot_general":
      found.append(eqn.params["precision"])
    for value in eqn.params.values():
      for sub in value if isinstance(value, (tuple, list)) else (value,):
        inner = getattr(sub, "jaxpr", sub)
        if hasattr(inner, "eqns"):
          found += _precisions(inner)
  return found


def _traced_under_bfloat16(fn, args, kwargs=None) -> list:
  with jax.default_matmul_precision("bfloat16"):
    return _precisions(jax.make_jaxpr(lambda *a: fn(*a, **(kwargs or {})))(*args).jaxpr)


@pytest.fixture(scope="module")
def blob():
  pts, faces = datasets.make_demo_mesh("blob", 0)
  mr, _ = datasets.mesh_resolution(pts, faces)
  return pts, faces, np.arange(0, len(pts), 97), 15 * mr


def _recording(monkeypatch, module, name):
  """Replaces `module.name` (a factory of jitted functions) by one that records each call."""
  calls, real = [], getattr(module, name)

  def factory(*a, **kw):
    fn = real(*a, **kw)

    def record(*args):
      calls.append((fn, args))
      return fn(*args)
    return record
  monkeypatch.setattr(module, name, factory)
  return calls


@pytest.mark.parametrize("method", sorted(lrf_jax.METHODS))
def test_every_method_traces_full_precision_products(method, blob, monkeypatch):
  pts, faces, kp, r = blob
  calls = _recording(monkeypatch, patch_frames, "jitted_method")
  kw = {"faces": faces} if lrf_jax.METHODS[method].needs_mesh else {}
  lrf_jax.compute_frames(pts, kp, r, method, kernel="jit", search="host", **kw)
  assert calls, method
  fn, args = calls[0]
  precisions = _traced_under_bfloat16(fn, args)
  assert all(p == HIGHEST for p in precisions), (method, set(precisions))


def test_descriptors_device_search_and_decorated_functions(blob, monkeypatch):
  pts, _, kp, r = blob
  calls = _recording(monkeypatch, descriptors_mod, "jitted_descriptor")
  searches = []
  real_search = device_search._search  # noqa: SLF001

  def search(*a, **kw):
    searches.append((a, kw))
    return real_search(*a, **kw)
  monkeypatch.setattr(device_search, "_search", search)
  frames, valid = lrf_jax.compute_frames(pts, kp, r, "lrf_net", search="device", kernel="jit")
  assert searches
  for name in ("toldi", "shot"):
    descriptors_mod.compute_descriptors(pts, kp, r, frames, valid, name)
  checked = [_traced_under_bfloat16(fn, args) for fn, args in calls]
  a, kw = searches[0]
  checked.append(_traced_under_bfloat16(real_search, a, kw))

  @_jax.jit
  def product(x):
    return x @ x.T
  checked.append(_traced_under_bfloat16(product, (jnp.ones((4, 3)),)))
  assert len(checked) >= 4 and all(checked[-1])  # the matrix product is there
  assert all(p == HIGHEST for ps in checked for p in ps), checked
