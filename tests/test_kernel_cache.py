"""numba's cache keys for lrf_jax's kernels (`lrf_jax.kernel_cache`): every cached kernel
keyed by the sources it is compiled from, shared by installs at different paths, and recompiled
when a helper it inlines from another file changes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numba

import lrf_jax
import lrf_jax.descriptors.matching as matching
import lrf_jax.frames.toldi as toldi
import lrf_jax.geometry.keypoints  # noqa: F401  (modules with cached kernels, for the census)
import lrf_jax.geometry.mesh  # noqa: F401
import lrf_jax.geometry.normals  # noqa: F401
import lrf_jax.registration  # noqa: F401
from lrf_jax import kernel_cache

PACKAGE = Path(lrf_jax.__file__).parent


def test_every_cached_kernel_is_keyed_by_its_sources():
  census, other = 0, []
  for name, module in list(sys.modules.items()):
    if not name.startswith("lrf_jax"):
      continue
    for attr, value in vars(module).items():
      cache = getattr(value, "_cache", None)
      if isinstance(value, numba.core.registry.CPUDispatcher) and hasattr(cache, "_impl"):
        census += 1
        if not isinstance(cache._impl._locator, kernel_cache.PackageLocator):
          other.append(f"{name}.{attr}")
  assert census >= 20 and not other, (census, other)


def test_dependencies_follow_calls_into_other_files():
  rel = lambda f: {os.path.relpath(p, PACKAGE) for p in kernel_cache.dependency_files(f.py_func)}
  assert {"frames/toldi.py", "frames/host_geometry.py"} <= rel(toldi._toldi_host_kernel)
  assert {"descriptors/matching.py", "search/bits.py", "search/nearest.py"} <= rel(
      matching._occupancy_knn_kernel)
  assert not any(p.startswith("..") for p in rel(toldi._toldi_host_kernel))


_RUN = """
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
import lrf_jax
assert lrf_jax.__file__.startswith(sys.argv[1]), lrf_jax.__file__
from lrf_jax.descriptors import select_correspondences
rng = np.random.default_rng(0)
q = np.where(rng.random((40, 30)) < 0.5, 100.0, rng.random((40, 30))).astype(np.float32)
select_correspondences(q, q[::-1], n=10)
"""


def _run(root: Path, cache: Path) -> str:
  env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
  env["NUMBA_CACHE_DIR"] = str(cache)
  out = subprocess.run([sys.executable, "-c", textwrap.dedent(_RUN), str(root)], env=env,
                       capture_output=True, text=True, timeout=300, cwd=root)
  assert out.returncode == 0, out.stderr
  return out.stderr


def test_installs_share_kernels_and_an_edited_helper_recompiles(tmp_path):
  """Two copies of the package at different paths, one cache: the second copy loads what the
  first compiled; after an edit of search/bits.py (which the occupancy kernel inlines from
  another file) it compiles again."""
  copies = []
  for name in ("a", "b"):
    shutil.copytree(PACKAGE, tmp_path / name / "lrf_jax",
                    ignore=shutil.ignore_patterns("__pycache__", "weights"))
    copies.append(tmp_path / name)
  cache = tmp_path / "cache"
  assert "compiling" in _run(copies[0], cache)
  assert "compiling" not in _run(copies[1], cache)
  with open(copies[1] / "lrf_jax" / "search" / "bits.py", "a") as f:
    f.write("\n# an edit\n")
  assert "compiling" in _run(copies[1], cache)
