"""Every module-level cache of lrf_jax, its bound, and `clear_caches()` to empty them all.

| cache | holds | bound |
|---|---|---|
| `normals.cache_last` | the last estimated normals, areas, grids, curvature (one per kind) | one entry per kind (about 8) |
| `patch_frames.WEIGHT_TABLES` | lrf_net / lrf_net_plus weight tables (257 x 257) | 4 |
| `patch_frames.jitted_method`, `descriptors.jitted_descriptor` | jitted frame / descriptor functions per option set | 64 / 32 |
| `weights.default_params_cached`, `weights.default_params_numpy_cached` | the shipped weights (on the device; numpy) | 8 / 8 |
| `datasets.cache.load_mesh` (emptied by its `clear_cache`) | meshes and clouds read by the dataset loaders | 64 |
| `datasets.cache.load_scan` (emptied by its `clear_cache`) | scans of scan sets at their working resolution (thinned sweeps); also on disk under $LRF_CACHE/scans | 64 |
| `datasets.synthetic.icosphere` | the demo set's base spheres | 8 |

Compiled code (numba's on-disk cache, JAX's jit caches and its optional persistent cache) is not
cleared here.
"""

from __future__ import annotations

from lrf_jax import descriptors
from lrf_jax.frames import patch_frames, weights
from lrf_jax.geometry import normals


def clear_caches() -> None:
  """Empty every cache listed in this module's docstring."""
  from lrf_jax.datasets import cache as dataset_cache  # not imported by lrf_jax itself
  from lrf_jax.datasets import synthetic
  normals.CLOUD_CACHE.clear()
  patch_frames.WEIGHT_TABLES.clear()
  patch_frames.jitted_method.cache_clear()
  descriptors.jitted_descriptor.cache_clear()
  weights.default_params_cached.cache_clear()
  weights.default_params_numpy_cached.cache_clear()
  dataset_cache.clear_cache()
  synthetic.icosphere.cache_clear()
