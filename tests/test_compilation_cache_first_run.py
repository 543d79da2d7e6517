"""The first run: a light `import lrf_jax` (lazy exports), numba's cache in the per-user cache
root, one stderr note when a kernel is actually compiled, and an ETA timed after the first
record."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import lrf_jax
from lrf_jax import compilation_cache
from tests.lrf_testing import repo_env

HEAVY = ("jax", "numba", "flax", "orbax", "matplotlib", "optax", "scipy")


def _python(code: str, env: dict[str, str], cwd: Path | None = None,
            timeout: float = 120) -> subprocess.CompletedProcess:
  full = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
  full.update(env)
  return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                        text=True, env=full, cwd=cwd, timeout=timeout)


def test_import_is_light_and_exports_are_lazy(tmp_path):
  out = _python(f"""
      import sys, time
      t = time.perf_counter()
      import lrf_jax
      seconds = time.perf_counter() - t
      heavy = [m for m in {HEAVY!r} if m in sys.modules]
      assert not heavy, heavy
      assert "lrf_jax.datasets" not in sys.modules
      assert lrf_jax.datasets.__name__ == "lrf_jax.datasets"   # reachable after a bare import
      assert "jax" not in sys.modules                          # the datasets do not need JAX
      print(seconds)
      """, {"XDG_CACHE_HOME": str(tmp_path)})
  assert out.returncode == 0, out.stderr
  assert float(out.stdout) < 1.0


def test_every_export_resolves():
  for name in lrf_jax.__all__:
    assert getattr(lrf_jax, name) is not None, name
  assert set(lrf_jax.__all__) <= set(dir(lrf_jax))
  assert lrf_jax.compute_frames.__module__ == "lrf_jax.frames.compute"
  assert callable(lrf_jax.voxel_downsample)
  with pytest.raises(AttributeError):
    lrf_jax.no_such_name  # noqa: B018


def test_numba_cache_under_the_cache_root(tmp_path):
  code = "import os, lrf_jax; print(os.environ.get('NUMBA_CACHE_DIR'))"
  out = _python(code, {"XDG_CACHE_HOME": str(tmp_path)})
  assert out.stdout.strip() == str(tmp_path / "lrf_jax" / "numba"), out.stderr
  assert (tmp_path / "lrf_jax" / "numba").is_dir()
  assert compilation_cache.cache_dir().parent == compilation_cache.cache_root()
  mine = tmp_path / "mine"
  out = _python(code, {"XDG_CACHE_HOME": str(tmp_path), "NUMBA_CACHE_DIR": str(mine)})
  assert out.stdout.strip() == str(mine)  # the user's setting stays
  blocked = tmp_path / "a_file"
  blocked.write_text("")
  out = _python(code, {"XDG_CACHE_HOME": str(blocked), "TMPDIR": str(tmp_path)})
  # cannot be created: a private folder in the temporary directory, never the package's folder
  assert out.returncode == 0, out.stderr
  assert out.stdout.strip() == str(tmp_path / f"lrf_jax-{os.getuid()}" / "numba"), out.stderr


def test_compile_notice_once_and_only_on_a_cache_miss(tmp_path):
  code = """
      import sys, numpy as np, numba, lrf_jax.search.grid as grid
      assert numba.config.CACHE_DIR.endswith("/lrf_jax/numba"), numba.config.CACHE_DIR
      print("imported", file=sys.stderr, flush=True)
      for shape in ((2, 3), (3, 3), (2, 3)):  # one compile (one signature), three calls
        assert grid._bounds(np.zeros(shape)) is not None
      assert grid._bounds(np.zeros((2, 3), np.float32)) is not None  # a second signature
      """
  env = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
  first = _python(code, env, cwd=tmp_path)
  assert first.returncode == 0, first.stderr
  note = "lrf_jax: compiling kernels"
  assert first.stderr.count(note) == 1, first.stderr
  assert first.stderr.index("imported") < first.stderr.index(note)  # nothing compiled at import
  second = _python(code, env, cwd=tmp_path)  # the kernels come from numba's cache
  assert second.returncode == 0, second.stderr
  assert note not in second.stderr, second.stderr


def test_jax_compile_notice(monkeypatch):
  stream = io.StringIO()
  monkeypatch.setattr(compilation_cache, "_state", dict(compilation_cache._state,
                                                        announced=False, stream=stream))
  compilation_cache._on_jax_duration("/jax/core/compile/backend_compile_duration", 0.01)
  compilation_cache._on_jax_event("/jax/compilation_cache/cache_hits")
  assert stream.getvalue() == ""  # a cache load or a short compile says nothing
  compilation_cache._on_jax_event("/jax/compilation_cache/cache_misses")
  compilation_cache._on_jax_duration("/jax/core/compile/backend_compile_duration", 5.0)
  assert stream.getvalue().count("lrf_jax: compiling kernels") == 1


def test_eta_is_timed_after_the_first_record():
  from tqdm import tqdm

  from lrf_jax.evaluation.runner import restart_clock
  bar = tqdm(total=100, file=io.StringIO(), mininterval=0)
  time.sleep(0.3)  # the first record: compiling
  bar.update(1)
  restart_clock(bar)
  assert bar.n == 1 and bar.format_dict["elapsed"] < 0.1
  time.sleep(0.02)
  bar.update(1)
  fmt = bar.format_dict
  assert fmt["n"] == 2
  rate = fmt["rate"] or (fmt["n"] - fmt["initial"]) / fmt["elapsed"]
  assert rate > 10  # one record per ~0.02 s, not 2 per 0.32 s
  remaining = (fmt["total"] - fmt["n"]) / rate
  assert remaining < 98 * 0.3 / 3
  bar.close()


def test_multiway_progress_times_each_stage_after_its_first_item(monkeypatch):
  """register_all's bars: one per stage (describing scans, registering pairs: a pair takes
  longer than a scan), each timed from its first task's end (a first run compiles the stage's
  kernels in it), and no bar for a stage with nothing to do."""
  from tqdm import tqdm

  from lrf_jax.multiway import tasks
  from lrf_jax.registration.options import RegisterOptions
  bars: list = []

  def bar(total, progress, desc):
    made = tqdm(total=total, desc=desc, file=io.StringIO(), mininterval=0,
                disable=not progress or total == 0)
    bars.append(made)
    return made
  seen: list = []

  def task(slow, value):
    def run(payload):
      if bars[-1].n:  # the rate the bar shows once a task of this stage has finished
        seen.append((bars[-1].desc, bars[-1].n, bars[-1].format_dict["elapsed"]))
      time.sleep(slow if bars[-1].n == 0 else 0.01)  # the first: compiling
      return value(payload)
    return run
  monkeypatch.setattr(tasks, "_bar", bar)
  monkeypatch.setattr(tasks, "describe_task", task(0.4, lambda p: {"features": p["name"]}))
  monkeypatch.setattr(tasks, "pair_task",
                      task(0.4, lambda p: tasks.error_record(p["i"], p["j"], "fake", "fake")))
  n = 5
  pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
  opts = RegisterOptions()
  records = tasks.PairRecords(None, ["ab" * 32] * n, opts, 1.0, 1.0, None)
  out, work = tasks.run_pairs([None] * n, [f"s{k}" for k in range(n)], pairs, options=opts,
                              mr=1.0, viewpoints=[None] * n, distance=1.0, params=None,
                              engine=None, records=records, progress=True)
  assert len(out) == len(pairs) and work["pairs_registered"] == len(pairs)
  assert [(b.desc, b.total, b.n) for b in bars] == [("describing scans", n, n),
                                                    ("registering pairs", len(pairs), len(pairs))]
  assert {d for d, _, _ in seen} == {"describing scans", "registering pairs"}
  for desc, done, elapsed in seen:
    assert elapsed < 0.4, (desc, done, elapsed)  # the first (slow) task is not in the clock
  eta = bars[1].format_dict
  rate = (eta["n"] - eta["initial"]) / eta["elapsed"]
  assert eta["initial"] == 1 and rate > 1 / 0.1  # pairs after the first: ~0.01 s each
  assert bars[0].format_dict["initial"] == 1


@pytest.mark.slow
def test_one_specialisation_per_kernel(tmp_path):
  """A register (from files and from arrays) and compute_frames compile each numba kernel for
  one argument type only: a read-only array (a file's cached cloud, a broadcast) is a type of
  its own to numba, and a second specialisation is a second compile on a first run."""
  code = textwrap.dedent(f"""
      import sys
      import numpy as np
      import lrf_jax
      from lrf_jax.io import write_ply
      from numba.core.registry import CPUDispatcher
      rng = np.random.default_rng(0)
      uv = rng.uniform(-1, 1, (4000, 2))
      pts = np.column_stack([uv, 0.3 * np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])])
      a, b = {str(tmp_path / 'a.ply')!r}, {str(tmp_path / 'b.ply')!r}
      write_ply(a, pts)
      write_ply(b, pts[::-1] + [0.05, 0.0, 0.0])
      lrf_jax.register(a, b, n_keypoints=400, n_correspondences=300)
      ro = pts.copy()
      ro.flags.writeable = False
      lrf_jax.register(ro, ro + 0.01, n_keypoints=400, n_correspondences=300)
      lrf_jax.compute_frames(a, np.arange(100), radius_mr=15)
      lrf_jax.compute_frames(ro, np.arange(100), radius_mr=15)
      many = [f"{{name}}.{{attr}}: {{len(obj.signatures)}}"
              for name, mod in list(sys.modules.items()) if name.startswith("lrf_jax")
              for attr, obj in list(vars(mod).items())
              if isinstance(obj, CPUDispatcher) and obj.__module__ == name
              and len(obj.signatures) > 1]
      print("MANY", many)
      """)
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=1200)
  assert out.returncode == 0, out.stderr[-3000:]
  assert "MANY []" in out.stdout, out.stdout[-2000:]


def test_register_on_the_cpu_imports_no_jax():
  """The host path (numba kernels, numpy) runs without JAX: a fresh `lrf-register` does not pay
  its import (about a second). The user's cache root, so that the kernels the suite compiled
  are loaded, not compiled again."""
  out = _python("""
      import sys
      import numpy as np
      import lrf_jax
      from lrf_jax import compilation_cache, datasets
      compilation_cache.enable()  # as the command-line programs do
      pair = datasets.make_demo_pair(0, seed=0, partial=False)
      res = lrf_jax.register(pair.model_points, pair.model_points @ np.diag([1.0, -1.0, -1.0]),
                             n_keypoints=400, n_correspondences=200, seed=0)
      assert "jax" not in sys.modules, "JAX was imported"
      print(res.success, np.round(res.transform[:3, :3]).astype(int).ravel().tolist())
      """, {k: v for k, v in os.environ.items() if k in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")},
      timeout=900)
  assert out.returncode == 0, out.stderr
  assert out.stdout.split()[0] == "True", out.stdout  # a half turn about x, found
  assert out.stdout.split(maxsplit=1)[1].strip() == "[1, 0, 0, 0, -1, 0, 0, 0, -1]", out.stdout


def test_jax_settings_wait_for_jax(tmp_path):
  """`compilation_cache.enable()` before JAX is imported keeps the cache directory and applies
  it when the package first uses JAX."""
  out = _python("""
      import sys
      from lrf_jax import compilation_cache
      path = compilation_cache.enable()
      assert "jax" not in sys.modules
      from lrf_jax._jax import jnp
      assert float(jnp.ones(3).sum()) == 3.0
      import jax
      assert jax.config.jax_compilation_cache_dir == str(path), jax.config.jax_compilation_cache_dir
      print("ok")
      """, {"XDG_CACHE_HOME": str(tmp_path)})
  assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_lazy_jax_helpers():
  import jax
  import jax.numpy as real_jnp
  from lrf_jax import _jax
  assert _jax.jnp.float32 is real_jnp.float32  # every attribute is the real module's
  assert _jax.is_jax_numpy(_jax.jnp) and _jax.is_jax_numpy(real_jnp)
  assert not _jax.is_jax_numpy(np)
  assert _jax.backend_is_cpu() == (jax.default_backend() == "cpu")

  def double(x, n):
    return x * n

  lazy = _jax.jit(static_argnums=1)(double)
  np.testing.assert_array_equal(lazy(real_jnp.arange(3), 2), jax.jit(double, static_argnums=1)(
      real_jnp.arange(3), 2))
  assert lazy.__name__ == "double"


def test_compute_frames_returns_jax_arrays_from_the_host_kernels_too():
  import jax
  from lrf_jax import datasets
  pair = datasets.make_demo_pair(0, seed=0, partial=False)
  kp = np.arange(0, len(pair.model_points), 40)
  for kernel in ("host", "jit"):
    frames, valid = lrf_jax.compute_frames(pair.model_points, kp, radius_mr=15, method="toldi",
                                           kernel=kernel)
    assert isinstance(frames, jax.Array) and isinstance(valid, jax.Array), kernel


def test_compile_notice_once_per_process_from_many_threads(monkeypatch):
  """Kernels compiled at once from several threads (and a JAX compile) say it once."""
  import threading
  stream = io.StringIO()
  monkeypatch.setattr(compilation_cache, "_state", dict(compilation_cache._state,
                                                        announced=False, stream=stream))
  start = threading.Barrier(8)

  def compile_kernel():
    start.wait()
    for _ in range(50):
      compilation_cache._announce()
  threads = [threading.Thread(target=compile_kernel) for _ in range(8)]
  for t in threads:
    t.start()
  for t in threads:
    t.join()
  compilation_cache._on_jax_event("/jax/compilation_cache/cache_misses")
  assert stream.getvalue().count("lrf_jax: compiling kernels") == 1


# ------------------------------------------------------ numba's CPU target and the kernel cache


_MATCH = """
import numpy as np
from lrf_jax.descriptors import select_correspondences
rng = np.random.default_rng(0)
q = np.where(rng.random((40, 30)) < 0.5, 100.0, rng.random((40, 30))).astype(np.float32)
select_correspondences(q, q[::-1], n=10)
"""


def _compiles(cache: Path, cpu: str | None) -> bool:
  env = {k: v for k, v in repo_env().items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES")}
  env["NUMBA_CACHE_DIR"] = str(cache)
  if cpu is not None:
    env["NUMBA_CPU_NAME"] = cpu
  out = subprocess.run([sys.executable, "-c", _MATCH], env=env, capture_output=True, text=True,
                       timeout=600)
  assert out.returncode == 0, out.stderr
  return "compiling kernels" in out.stderr


def test_kernels_compiled_for_one_cpu_target_are_never_loaded_for_another(tmp_path):
  """A user's NUMBA_CPU_NAME (here "generic", as for a cache shipped to other machines) is
  respected: lrf_jax's locator keys a kernel by its sources, and numba's index keys each entry
  by the target (triple, CPU name, features), so one cache holds both builds side by side and
  each run loads only its own."""
  cache = tmp_path / "cache"
  assert _compiles(cache, "generic")
  assert _compiles(cache, None)  # native: not the generic build
  assert not _compiles(cache, "generic")
  assert not _compiles(cache, None)
