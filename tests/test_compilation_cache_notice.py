"""The compile notice ("lrf_jax: compiling kernels ...") comes only when something is compiled:
a warm cache prints nothing even when the compile workers start (their marker of the package's
sources is missing after any edit of a source, or before a program's first run, while every
kernel is cached); an empty cache prints it once; a process that waits for a worker compiling a
kernel it needs prints it."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from lrf_jax import compilation_cache
from lrf_jax.cli import parallel_compile as pc

REPO = Path(__file__).resolve().parents[1]
NOTICE = "lrf_jax: compiling kernels"
TWO_CORES = pytest.mark.skipif(pc.cores() < 2, reason="needs two cores")


def _env(tmp_path: Path, **extra: str) -> dict[str, str]:
  env = {k: v for k, v in os.environ.items()
         if k not in ("NUMBA_CACHE_DIR", "LRF_JAX_CACHE_DIR", "XDG_CACHE_HOME", pc.ENV_VAR,
                      "LRF_JAX_DEBUG_COMPILE")}
  env.update(XDG_CACHE_HOME=str(tmp_path / "cache"), TMPDIR=str(tmp_path / "tmp"),
             PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
  (tmp_path / "tmp").mkdir(parents=True, exist_ok=True)
  env.update(extra)
  return env


def _warm_markers(tmp_path: Path) -> list[Path]:
  warm = tmp_path / "cache" / "lrf_jax" / "numba" / "lrf_jax" / "warm"
  return sorted(warm.iterdir()) if warm.is_dir() else []


def test_waiting_for_a_worker_that_compiles_a_kernel_announces_it(tmp_path, monkeypatch):
  """The main process needs a kernel a worker has claimed: it waits, and says why."""
  from lrf_jax import kernel_cache
  stream = io.StringIO()
  monkeypatch.setattr(compilation_cache, "_state", dict(compilation_cache._state,
                                                        announced=False, stream=stream))
  compilation_cache.announce_compiles()  # installs the wait hook when numba is imported
  assert "numba" in sys.modules
  monkeypatch.setattr(kernel_cache, "_ON_WAIT", [compilation_cache._announce])
  claims = tmp_path / "claims"
  claims.mkdir()
  index = str(tmp_path / "k-1.py311.nbi")
  monkeypatch.setattr(kernel_cache, "_SHARING", dict(kernel_cache._SHARING, held=set()))
  kernel_cache.share(str(claims), alive=lambda pid: True)
  claim = kernel_cache._claim_path(index)
  Path(claim).write_text("1")  # pid 1's claim: a worker compiling it
  done = threading.Timer(0.3, lambda: Path(claim + ".done").touch())
  done.start()
  try:
    assert kernel_cache._wait_for_claimant(index)  # waited for the worker, then loads
  finally:
    done.cancel()
    kernel_cache.share(None)
  assert stream.getvalue().count(NOTICE) == 1
  stream.truncate(0)
  compilation_cache._state["announced"] = False
  kernel_cache.share(str(claims), alive=lambda pid: True)
  try:
    assert kernel_cache._wait_for_claimant(index)  # finished already: no wait, no notice
  finally:
    kernel_cache.share(None)
  assert NOTICE not in stream.getvalue()


_WITH_WORKERS = """
import sys
import numpy as np
from lrf_jax.cli import parallel_compile as pc
started = pc.start("frames")
print("workers", started, file=sys.stderr, flush=True)
import lrf_jax.search.grid as grid
for shape in ((2, 3), (5, 3)):
  assert grid._bounds(np.zeros(shape)) is not None
pc.stop()
"""


@TWO_CORES
def test_workers_on_a_warm_cache_say_nothing(tmp_path):
  """An empty numba cache prints the notice once (the kernel is compiled, here or by a
  worker); a second process, whose workers start again (this code's marker is missing: the
  first stopped its workers before they finished), loads the kernel and prints nothing."""
  env = _env(tmp_path, **{pc.ENV_VAR: "1"})
  code = textwrap.dedent(_WITH_WORKERS)
  runs = []
  for _ in range(2):
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    runs.append(out.stderr)
  assert all("workers True" in err for err in runs), runs  # the workers started both times
  assert not _warm_markers(tmp_path)
  assert runs[0].count(NOTICE) == 1, runs[0]
  assert NOTICE not in runs[1], runs[1]


def _frames(tmp_path: Path, cloud: str, env: dict[str, str]) -> str:
  out = subprocess.run([sys.executable, "-m", "lrf_jax.cli.frames", cloud, "--out",
                        str(tmp_path / "f.npz")], env=env, capture_output=True, text=True,
                       timeout=900)
  assert out.returncode == 0, out.stderr
  return out.stderr


@TWO_CORES
@pytest.mark.slow
def test_lrf_frames_says_it_compiles_only_when_it_does(tmp_path):
  """lrf-frames on an empty cache: the notice once; again, after its marker of the sources is
  gone (as after any edit of a source: the workers start again on a cache that holds every
  kernel): none; and again: none."""
  from lrf_jax.cli import record_manifest
  cloud, _ = record_manifest.demo_files(tmp_path)
  env = _env(tmp_path / "run", **{pc.ENV_VAR: "1"})
  started = time.perf_counter()
  cold = _frames(tmp_path, cloud, env)
  assert cold.count(NOTICE) == 1, cold
  for marker in _warm_markers(tmp_path / "run"):  # none when the workers did not finish
    marker.unlink()  # a stale marker: the workers start, every kernel it needs is cached
  stale = _frames(tmp_path, cloud, env)
  assert NOTICE not in stale, stale
  warm = _frames(tmp_path, cloud, env)
  assert NOTICE not in warm, warm
  assert time.perf_counter() - started < 900
