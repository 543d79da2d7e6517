"""A cold first run compiles its kernels in worker processes (`lrf_jax.cli.parallel_compile`):
the manifest is current, the workers end with the command (normal exit, Ctrl-C, a killed
parent), the results are the warm run's bit for bit, the opt-out works, and concurrent saves
into one cache keep every entry."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lrf_jax.cli import parallel_compile as pc
from lrf_jax.cli import record_manifest

REPO = Path(__file__).resolve().parents[1]
TWO_CORES = pytest.mark.skipif(pc.cores() < 2, reason="needs two cores")


def _env(tmp_path: Path, **extra: str) -> dict[str, str]:
  env = {k: v for k, v in os.environ.items()
         if k not in ("NUMBA_CACHE_DIR", "LRF_JAX_CACHE_DIR", "XDG_CACHE_HOME", pc.ENV_VAR)}
  env.update(XDG_CACHE_HOME=str(tmp_path / "cache"), TMPDIR=str(tmp_path / "tmp"),
             PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
  (tmp_path / "tmp").mkdir(parents=True, exist_ok=True)
  env.update(extra)
  return env


def _workers(marker: str) -> list[int]:
  """Live compile workers whose command line holds `marker` (their claims folder's parent)."""
  found = []
  for proc in Path("/proc").iterdir():
    if not proc.name.isdigit():
      continue
    try:
      cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
      state = (proc / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
      continue
    if "parallel_compile --worker" in cmd and marker in cmd and state != "Z":
      found.append(int(proc.name))
  return found


def _demo_pair(tmp_path: Path) -> tuple[str, str]:
  return record_manifest.demo_files(tmp_path)  # the manifest's own inputs


def _register(tmp_path: Path, a: str, b: str, env: dict[str, str]) -> subprocess.Popen:
  return subprocess.Popen([sys.executable, "-m", "lrf_jax.cli.register", a, b], env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_manifest_names_kernels_and_types_that_exist():
  mods = pc.kernel_modules()
  for program, entries in pc.manifest().items():
    assert program in pc.PROGRAMS and entries
    for module, name, sig in entries:
      disp = getattr(mods[module], name)  # a module the worker imports, a cached kernel
      assert disp._cache._cache_file._index_path  # noqa: SLF001
      types = [pc.parse_type(t) for t in sig]
      assert [repr(t) for t in types] == sig


@pytest.mark.slow
def test_manifest_is_current():
  """Fails when a program's default call needs other kernels or types than the manifest says:
  rerun `python -m lrf_jax.cli.record_manifest`."""
  assert record_manifest.record() == pc.manifest(), "stale: python -m lrf_jax.cli.record_manifest"


def test_opt_out_one_core_and_warm_start_nothing(tmp_path, monkeypatch):
  monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "nb"))
  monkeypatch.setenv(pc.ENV_VAR, "0")
  assert not pc.start("register") and not pc._STATE["procs"]  # noqa: SLF001
  monkeypatch.setenv(pc.ENV_VAR, "1")
  monkeypatch.setattr(pc, "cores", lambda: 1)
  assert not pc.start("register")
  monkeypatch.undo()
  monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "nb"))
  monkeypatch.setenv(pc.ENV_VAR, "1")
  marker = pc.warm_marker("register")
  marker.parent.mkdir(parents=True)
  marker.touch()
  assert not pc.start("register")  # compiled for this code already
  assert not pc.start("no such program")


@TWO_CORES
def test_stop_ends_the_workers_at_once(tmp_path, monkeypatch):
  monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "nb"))
  monkeypatch.setenv(pc.ENV_VAR, "1")
  monkeypatch.setattr(pc.tempfile, "tempdir", str(tmp_path))
  assert pc.start("register")
  procs, claims = list(pc._STATE["procs"]), pc._STATE["claims"]  # noqa: SLF001
  assert len(procs) == pc.cores() - 1
  deadline = time.monotonic() + 60  # a loaded machine may take a while to exec the workers
  while not _workers(str(tmp_path)) and time.monotonic() < deadline:
    time.sleep(0.1)
  assert _workers(str(tmp_path))
  time.sleep(1.0)
  pc.stop()
  assert all(p.poll() is not None for p in procs)
  assert not _workers(str(tmp_path)) and not os.path.exists(claims)
  assert not pc.warm_marker("register").exists()  # unfinished: the next run compiles on
  pc.stop()  # idempotent


@TWO_CORES
@pytest.mark.slow
def test_first_run_is_the_warm_run_and_leaves_no_process(tmp_path):
  """A cold lrf-register with workers, then a warm one: the same output, bit for bit; no worker
  outlives the command; the compile announced once, by the cold run. (That the opt-out starts
  no worker is `test_opt_out_one_core_and_warm_start_nothing`'s: a cold run without
  workers costs another minute.)"""
  a, b = _demo_pair(tmp_path)
  outs = []
  for _ in range(2):  # cold, then warm
    proc = _register(tmp_path, a, b, _env(tmp_path / "run"))
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 0, stderr
    assert not _workers(str(tmp_path / "run"))
    outs.append((stdout, stderr.count("lrf_jax: compiling kernels")))
    warm = tmp_path / "run" / "cache" / "lrf_jax" / "numba" / "lrf_jax" / "warm"
    assert warm.is_dir() and any(warm.iterdir())  # the workers ran and finished their share
  assert outs[0][0] == outs[1][0]  # bit for bit
  assert [n for _, n in outs] == [1, 0]  # announced once per process, only when compiling


@TWO_CORES
@pytest.mark.parametrize("how", ["ctrl-c", "killed"])
def test_workers_end_when_the_command_is_interrupted_or_killed(tmp_path, how):
  a, b = _demo_pair(tmp_path)
  proc = _register(tmp_path, a, b, _env(tmp_path))
  deadline = time.monotonic() + 120
  while not _workers(str(tmp_path)) and time.monotonic() < deadline:
    time.sleep(0.1)
  assert _workers(str(tmp_path)), "no worker started"
  time.sleep(1.0)
  proc.send_signal(signal.SIGINT if how == "ctrl-c" else signal.SIGKILL)
  _, err = proc.communicate(timeout=60)
  assert proc.returncode == (130 if how == "ctrl-c" else -signal.SIGKILL), err
  deadline = time.monotonic() + 10
  while _workers(str(tmp_path)) and time.monotonic() < deadline:
    time.sleep(0.1)
  assert not _workers(str(tmp_path))


def test_concurrent_saves_keep_every_entry(tmp_path, monkeypatch):
  """Two processes saving two signatures of one kernel at once both chose the same data file
  (numba's save reads the index, picks a free name, writes the index, then the data); the lock
  of `kernel_cache` makes each save whole."""
  from numba.core import caching, config

  from lrf_jax import kernel_cache
  kernel_cache.install()
  monkeypatch.setattr(config, "CACHE_DIR", str(tmp_path))
  folder = tmp_path / "lrf_jax" / "search"
  folder.mkdir(parents=True)
  load_index = caching.IndexDataCacheFile._load_index
  barrier = threading.Barrier(2, timeout=2)

  def slow_load_index(self):
    out = load_index(self)
    try:
      barrier.wait()  # without the lock both read the empty index before either writes
    except threading.BrokenBarrierError:
      pass
    return out

  monkeypatch.setattr(caching.IndexDataCacheFile, "_load_index", slow_load_index)
  files = [caching.IndexDataCacheFile(cache_path=str(folder), filename_base="k-1.py311",
                                      source_stamp="stamp") for _ in range(2)]
  threads = [threading.Thread(target=f.save, args=(f"key{i}", np.full(3, i)))
             for i, f in enumerate(files)]
  for t in threads:
    t.start()
  for t in threads:
    t.join()
  monkeypatch.setattr(caching.IndexDataCacheFile, "_load_index", load_index)
  for i in range(2):
    got = files[0].load(f"key{i}")
    assert got is not None and np.array_equal(got, np.full(3, i)), (i, got)


def test_lrf_compile_marks_each_program_warm(tmp_path, monkeypatch):
  """lrf-compile's "program:<name>" groups compile (or load) the manifest's kernels by
  signature and mark the program warm: a first run after lrf-compile starts no worker."""
  from lrf_jax.cli import compile as compile_cli
  assert {f"program:{p}" for p in pc.PROGRAMS} <= set(compile_cli.groups())
  markers = {p: tmp_path / "warm" / p for p in pc.PROGRAMS}
  monkeypatch.setattr(pc, "warm_marker", markers.__getitem__)
  monkeypatch.setenv(pc.ENV_VAR, "1")
  monkeypatch.setattr(pc, "cores", lambda: 2)
  pc.compile_program("register")
  assert markers["register"].is_file() and not markers["frames"].exists()
  assert pc.start("register") is False  # warm: no worker
