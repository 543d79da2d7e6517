"""Compile workers die with the process that started them, a SIGKILL included: `lrf-compile`'s
pool of workers (`parallel_compile.spawn_context`) and, through the portable watch of the
parent's pid alone (no `prctl`), any worker that calls `parallel_compile.die_with_parent`."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
GONE_WITHIN_S = 15.0

pytestmark = pytest.mark.skipif(os.name != "posix", reason="SIGKILL and process trees: POSIX")


def _env(tmp_path: Path) -> dict[str, str]:
  env = {k: v for k, v in os.environ.items()
         if k not in ("NUMBA_CACHE_DIR", "LRF_JAX_CACHE_DIR", "XDG_CACHE_HOME")}
  (tmp_path / "tmp").mkdir(parents=True, exist_ok=True)
  env.update(XDG_CACHE_HOME=str(tmp_path / "cache"), TMPDIR=str(tmp_path / "tmp"),
             PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
  return env


def _children(pid: int) -> list[int]:
  """The live descendants of `pid` (psutil, else Linux's /proc)."""
  try:
    import psutil
  except ImportError:
    if not os.path.isdir("/proc"):
      pytest.skip("needs psutil or /proc to list processes")
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
      if entry.isdigit():
        try:
          with open(f"/proc/{entry}/stat") as f:
            parents[int(entry)] = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
          continue
    found, frontier = [], [pid]
    while frontier:
      kids = [p for p, pp in parents.items() if pp in frontier]
      found += kids
      frontier = kids
    return [p for p in found if _alive(p)]
  try:
    return [p.pid for p in psutil.Process(pid).children(recursive=True) if _alive(p.pid)]
  except psutil.Error:
    return []


def _alive(pid: int) -> bool:
  """Whether `pid` runs (a zombie, dead but not yet reaped by its new parent, does not)."""
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:
    return True
  try:
    with open(f"/proc/{pid}/stat") as f:
      return f.read().rsplit(")", 1)[1].split()[0] != "Z"
  except OSError:
    pass
  try:
    import psutil
    return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
  except ImportError:
    return True
  except psutil.Error:
    return False


def _wait_gone(pids: list[int], limit: float = GONE_WITHIN_S) -> list[int]:
  deadline = time.monotonic() + limit
  while time.monotonic() < deadline and any(map(_alive, pids)):
    time.sleep(0.1)
  return [p for p in pids if _alive(p)]


def _kill(pids: list[int]) -> None:
  for pid in pids:
    try:
      os.kill(pid, signal.SIGKILL)
    except OSError:
      pass


def test_lrf_compile_workers_die_when_it_is_killed(tmp_path):
  """Before: `lrf-compile` killed with SIGKILL left its pool's workers compiling, then hung,
  orphaned, for minutes."""
  cmd = [sys.executable, "-m", "lrf_jax.cli.compile", "--jobs", "2", "--only", "frames:uniform",
         "frames:board"]
  proc = subprocess.Popen(cmd, env=_env(tmp_path), cwd=tmp_path, stdin=subprocess.DEVNULL,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
  workers: list[int] = []
  try:
    deadline = time.monotonic() + 120  # a loaded machine may take a while to start them
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
      workers = _children(proc.pid)
      time.sleep(0.1)
    assert len(workers) >= 2, f"no workers started: {proc.poll()}"
    time.sleep(1.0)  # at work (importing, compiling)
    workers = _children(proc.pid)
    proc.kill()
    proc.wait(timeout=30)
    left = _wait_gone(workers)
    assert not left, f"workers still running {GONE_WITHIN_S} s after their parent was killed"
  finally:
    _kill(workers)  # first: a worker left running holds the pipe that communicate() reads
    proc.kill()
    proc.communicate()


_PARENT = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], sys.argv[2]])
print(child.pid, flush=True)
time.sleep(300)
"""

_WORKER_WITHOUT_PRCTL = """
import ctypes, os, sys, time

def no_libc(*args, **kwargs):
  raise OSError("no prctl here")

ctypes.CDLL = no_libc  # as on a system without prctl: only the watch of the parent's pid is left
sys.path.insert(0, sys.argv[1])
from lrf_jax.cli import parallel_compile
parallel_compile.die_with_parent(os.getppid())
print("ready", flush=True)
time.sleep(300)
"""


def test_a_worker_without_prctl_dies_with_its_parent(tmp_path):
  """The portable fallback: a worker watching its parent's pid exits when the parent is
  killed."""
  parent = subprocess.Popen([sys.executable, "-c", textwrap.dedent(_PARENT),
                             textwrap.dedent(_WORKER_WITHOUT_PRCTL), str(REPO)],
                            env=_env(tmp_path), stdout=subprocess.PIPE, text=True)
  worker = 0
  try:
    assert parent.stdout is not None
    worker = int(parent.stdout.readline())
    assert parent.stdout.readline().strip() == "ready"  # the worker's own line, on our pipe
    parent.kill()
    parent.wait(timeout=30)
    assert not _wait_gone([worker]), "the worker outlived its parent"
  finally:
    if worker:
      _kill([worker])
    parent.kill()
    parent.communicate()


def test_die_with_parent_does_nothing_in_the_parent_itself():
  from lrf_jax.cli import parallel_compile
  before = signal.getsignal(signal.SIGINT)
  parallel_compile.die_with_parent(os.getpid())  # lrf-compile's groups run in-process in tests
  assert signal.getsignal(signal.SIGINT) is before


def test_lrf_compile_pool_processes_die_with_their_parent():
  from lrf_jax.cli import parallel_compile
  ctx = parallel_compile.spawn_context()
  assert ctx.get_start_method() == "spawn"
  assert issubclass(ctx.Process, parallel_compile.MortalProcess)
