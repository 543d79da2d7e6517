"""lrf_jax: learned (LRF-Net) and hand-crafted local reference frames in JAX.

    import lrf_jax
    frames, valid = lrf_jax.compute_frames(points, keypoints, radius, method="lrf_net")

Conventions: frames are (..., 3, 3) with rows x, y, z (they map world vectors into the LRF),
right-handed, det +1; invalid frames are the identity with `valid == False`.

`import lrf_jax` is light (no JAX, flax, orbax, matplotlib or numba): every public name and
subpackage below is loaded on first use (module `__getattr__`), so a program pays only for the
parts it calls. Before numba is first imported, its on-disk cache is pointed at a per-user
directory (`lrf_jax.compilation_cache.numba_cache_dir()`, beside JAX's) unless `NUMBA_CACHE_DIR`
is set, so that compiled kernels are kept even for a read-only install.
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, Any

from lrf_jax import compilation_cache as _compilation_cache

_compilation_cache.configure_numba_cache()

# public name -> the module (under lrf_jax) that defines it; loaded on first access.
_EXPORTS: dict[str, str] = {
    "compute_frames": "frames.compute",
    "frames_from_patches": "frames.patch_frames",
    "mesh_resolution": "frames.compute",
    "clear_caches": "caches",
    "set_num_threads": "search.engine",
    "METHODS": "frames",
    "MethodSpec": "frames",
    "add_method": "frames",
    "lrf_net_frames": "frames.lrf_net",
    "iss_keypoints": "geometry.keypoints",
    "batched_chamfer": "learning.losses",
    "chamfer": "learning.losses",
    "siamese_loss": "learning.losses",
    "meancos": "frames.metrics",
    "repeatability_summary": "frames.metrics",
    "default_params": "frames.weights",
    "init_params": "learning.model",
    "load_params": "frames.weights",
    "save_params": "frames.weights",
    "Patches": "search.neighborhoods",
    "build_patches": "search.neighborhoods",
    "register": "registration",
    "register_all": "multiway",
    "voxel_downsample": "geometry.sampling",
    "view": "viz",
}

# subpackages and modules reachable as attributes after a bare `import lrf_jax`.
_SUBMODULES = frozenset({"cli", "datasets", "descriptors", "evaluation", "frames", "geometry",
                         "io", "learning", "multiway", "registration", "search"})

__all__ = sorted([*_EXPORTS, "search"])


def _load(module: str) -> Any:
  """The lrf_jax module `module` (a key of `_EXPORTS` or `_SUBMODULES`), imported now.

  Every import is written out (no computed module names), so the package's import graph stays
  visible to static checks. `import lrf_jax.x as m`, not `from lrf_jax import x`: the latter
  would look the name up on this package first and so call `__getattr__` again."""
  m: ModuleType  # declared once: every case binds it to a different module
  match module:
    case "frames.compute":
      import lrf_jax.frames.compute as m
    case "frames.patch_frames":
      import lrf_jax.frames.patch_frames as m
    case "caches":
      import lrf_jax.caches as m
    case "search.engine":
      import lrf_jax.search.engine as m
    case "frames":
      import lrf_jax.frames as m
    case "frames.lrf_net":
      import lrf_jax.frames.lrf_net as m
    case "geometry.keypoints":
      import lrf_jax.geometry.keypoints as m
    case "learning.losses":
      import lrf_jax.learning.losses as m
    case "frames.metrics":
      import lrf_jax.frames.metrics as m
    case "frames.weights":
      import lrf_jax.frames.weights as m
    case "learning.model":
      import lrf_jax.learning.model as m
    case "search.neighborhoods":
      import lrf_jax.search.neighborhoods as m
    case "registration":
      import lrf_jax.registration as m
    case "multiway":
      import lrf_jax.multiway as m
    case "geometry.sampling":
      import lrf_jax.geometry.sampling as m
    case "viz":
      import lrf_jax.viz as m
    case "datasets":
      import lrf_jax.datasets as m
    case "descriptors":
      import lrf_jax.descriptors as m
    case "evaluation":
      import lrf_jax.evaluation as m
    case "io":
      import lrf_jax.io as m
    case "search":
      import lrf_jax.search as m
    case "geometry":
      import lrf_jax.geometry as m
    case "learning":
      import lrf_jax.learning as m
    case "cli":
      import lrf_jax.cli as m
    case _:
      raise KeyError(module)
  return m


def __getattr__(name: str) -> Any:
  """A public name or subpackage of lrf_jax, imported on first access (then cached here);
  `__version__` too (read from the package metadata on first access: importlib.metadata is
  not free to import)."""
  if name == "__version__":
    from lrf_jax.records import version
    value: Any = version()
  elif name in _EXPORTS:
    value = getattr(_load(_EXPORTS[name]), name)
  elif name in _SUBMODULES:
    value = _load(name)
  else:
    raise AttributeError(f"module 'lrf_jax' has no attribute {name!r}")
  globals()[name] = value
  return value


def __dir__() -> list[str]:
  """The module's names, the lazily loaded ones included."""
  return sorted({*globals(), *_EXPORTS, *_SUBMODULES, "__version__"})


if TYPE_CHECKING:  # for type checkers and IDEs; at run time these come from __getattr__
  __version__: str
  from lrf_jax import (cli, datasets, descriptors, evaluation, frames, geometry, io,  # noqa: F401
                       learning, multiway, registration, search)
  from lrf_jax.frames.compute import compute_frames, mesh_resolution  # noqa: F401
  from lrf_jax.frames.patch_frames import frames_from_patches  # noqa: F401
  from lrf_jax.caches import clear_caches  # noqa: F401
  from lrf_jax.search.engine import set_num_threads  # noqa: F401
  from lrf_jax.frames import METHODS, MethodSpec, add_method  # noqa: F401
  from lrf_jax.frames.lrf_net import lrf_net_frames  # noqa: F401
  from lrf_jax.geometry.keypoints import iss_keypoints  # noqa: F401
  from lrf_jax.learning.losses import batched_chamfer, chamfer, siamese_loss  # noqa: F401
  from lrf_jax.frames.metrics import meancos, repeatability_summary  # noqa: F401
  from lrf_jax.frames.weights import default_params, load_params, save_params  # noqa: F401
  from lrf_jax.learning.model import init_params  # noqa: F401
  from lrf_jax.search.neighborhoods import Patches, build_patches  # noqa: F401
  from lrf_jax.multiway import register_all  # noqa: F401
  from lrf_jax.registration import register  # noqa: F401
  from lrf_jax.geometry.sampling import voxel_downsample  # noqa: F401
  from lrf_jax.viz import view  # noqa: F401
