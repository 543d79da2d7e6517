"""JAX for the package's modules, imported when a module first uses it.

The host paths (numba kernels and numpy: `register` and `compute_frames`' host kernels on a CPU)
need no JAX, and importing it costs about a second of every fresh process. The package's modules
therefore take `jax` and `jax.numpy` from here, as `from lrf_jax._jax import jax, jnp`: module
objects whose first attribute read imports the real module (and then hands over every
attribute of it). Type checkers see the real modules.

Also here:
  * `jit`: `jax.jit` for a module-level decorator, applied at the function's first call, of
    the function wrapped by `exact_matmuls` (float32 products at full precision on any device);
  * `is_jax_numpy(xp)`: whether an array-module argument is jax.numpy (the proxy or the module);
  * `backend_is_cpu()`: `jax.default_backend() == "cpu"`, without importing JAX where no
    accelerator plugin is installed (JAX's default backend is then the CPU).

When JAX is first imported through these, `compilation_cache.jax_imported()` applies the
package's JAX settings (the persistent cache, the compile notice).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
import types
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

_state = {"hooked": False}


def _import(name: str) -> types.ModuleType:
  # pylint: disable=import-outside-toplevel
  import jax as top
  import jax.numpy as numpy_module
  module = numpy_module if name == "jax.numpy" else top
  if not _state["hooked"]:
    _state["hooked"] = True
    from lrf_jax import compilation_cache  # pylint: disable=import-outside-toplevel
    compilation_cache.jax_imported()
  return module


class _LazyModule(types.ModuleType):
  """A module that imports `self.__name__` at its first attribute read and forwards every read
  to it (nothing is copied: a test that patches the real module patches what this returns)."""

  def __getattr__(self, attr: str) -> Any:
    return getattr(_import(self.__name__), attr)

  def __repr__(self) -> str:
    return f"<lrf_jax lazy module {self.__name__!r}>"


if TYPE_CHECKING:
  import jax as jax
  import jax.numpy as jnp
else:
  jax = _LazyModule("jax")
  jnp = _LazyModule("jax.numpy")


# The precision of float32 matrix products in every function lrf_jax traces: "highest" is true
# float32. JAX's default lets a GPU use TF32 (10-bit mantissas) for them, which moved frames by up
# to 0.03 and descriptors by 5 % against the float64 host kernels on an H200, and broke the
# equivariance the methods guarantee; the products here are 3x3 covariances, small MLPs and
# descriptor distances, memory-bound, so full precision costs little.
MATMUL_PRECISION = "highest"


def exact_matmuls(fun: Callable) -> Callable:
  """`fun` traced with float32 matrix products at full precision (`MATMUL_PRECISION`), whatever
  `jax.default_matmul_precision` the caller set: the setting is read when a product is traced,
  so it holds inside the caller's own `jax.jit` too. `jit` wraps every function lrf_jax jits."""

  @functools.wraps(fun)
  def call(*args: Any, **kw: Any) -> Any:
    with jax.default_matmul_precision(MATMUL_PRECISION):
      return fun(*args, **kw)

  return call


def jit(fun: Callable | None = None, **kwargs: Any) -> Any:
  """`jax.jit(exact_matmuls(fun), **kwargs)`, built at the first call (a module-level decorator
  that does not import JAX when the module is imported). `@jit` or `@jit(static_argnames=...)`."""
  if fun is None:
    return functools.partial(jit, **kwargs)
  jitted: list[Any] = []

  @functools.wraps(fun)
  def call(*args: Any, **kw: Any) -> Any:
    if not jitted:
      jitted.append(jax.jit(exact_matmuls(fun), **kwargs))
    return jitted[0](*args, **kw)

  return call


def is_jax_numpy(xp: Any) -> bool:
  """Whether the array module `xp` is jax.numpy (this module's `jnp` or the real one)."""
  return getattr(xp, "__name__", None) == "jax.numpy"


# JAX's accelerator plugins (CUDA, ROCm, TPU): where none is installed and JAX_PLATFORMS does not
# name another platform, JAX's default backend is the CPU.
_PLUGINS = ("jax_plugins", "jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin",
            "jax_rocm7_plugin", "libtpu")


@functools.cache
def _accelerator_plugin_installed() -> bool:
  return any(importlib.util.find_spec(p) is not None for p in _PLUGINS)


def backend_is_cpu() -> bool:
  """`jax.default_backend() == "cpu"`, answered without importing JAX when it is not imported
  yet, no accelerator plugin is installed and `JAX_PLATFORMS` is unset or "cpu"."""
  if "jax" not in sys.modules:
    platforms = os.environ.get("JAX_PLATFORMS", "").strip().lower()
    if platforms in ("", "cpu") and not _accelerator_plugin_installed():
      return True
  return _import("jax").default_backend() == "cpu"
