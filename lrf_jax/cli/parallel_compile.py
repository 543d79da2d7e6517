"""A cold first run compiles its kernels in parallel: `lrf-register` and `lrf-frames` start
worker processes that compile, into the same on-disk cache, the kernels the command will need.

numba compiles one kernel after another within a process (its compiler lock is per process), and a
first `lrf-register` spent nearly all of its time compiling on one core. When a command starts with
this code's kernels not yet compiled (cheap test: `warm_marker`), `start(program)` starts one worker
per core beyond the first (the cores this process may run on), each a fresh interpreter (`python -m
lrf_jax.cli.parallel_compile`). A worker compiles, by explicit signature, the kernels the program's
default call needs (`compile_manifest.json`, recorded by `lrf_jax.cli.record_manifest`; a test fails
when it is stale) from the last one the main process will need backwards, while the main process
runs normally from the first. Both claim a kernel before compiling it (`kernel_cache.share`): a
worker skips a kernel another process claimed, and the main process waits for a worker compiling a
kernel it needs and loads it, so no cached kernel is compiled twice (helpers without `cache=True`
are compiled in each process whose kernels call them). Results are the warm run's, bit for bit: the
same kernels, loaded from the cache.

No process outlives the command: `stop()` (in the command's `finally`, also on Ctrl-C and on
error) terminates the workers, which also die with their parent, a SIGKILL included
(`die_with_parent`: Linux `PR_SET_PDEATHSIG`, and everywhere a watch of the parent's pid), and
ignore Ctrl-C themselves; `lrf-compile`'s workers die with it the same way (`spawn_context`).
A worker compiles nothing a default call would not load. Nothing happens with one core, on a
warm cache, or with `LRF_JAX_PARALLEL_COMPILE=0`.

    python -m lrf_jax.cli.record_manifest   # rewrite compile_manifest.json
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from multiprocessing import context as _mp_context
from pathlib import Path
from typing import Any

ENV_VAR = "LRF_JAX_PARALLEL_COMPILE"  # "0" (or off, false, no) turns the workers off
MANIFEST = Path(__file__).with_name("compile_manifest.json")
PACKAGE = Path(__file__).resolve().parents[1]
PROGRAMS = ("register", "frames")
# Seconds a command that ended normally gives its workers to finish (and mark the cache warm).
FINISH_GRACE_S = 3.0

_STATE: dict[str, Any] = {"procs": [], "claims": None, "marker": None}


def cores() -> int:
  """The cores this process may run on (`taskset` counts)."""
  if hasattr(os, "sched_getaffinity"):
    return len(os.sched_getaffinity(0))
  return os.cpu_count() or 1


def enabled() -> bool:
  return os.environ.get(ENV_VAR, "1").strip().lower() not in ("0", "off", "false", "no")


def _numba_version_bytes() -> bytes:
  """Something that changes with numba's version, read without importing numba."""
  from importlib.util import find_spec
  spec = find_spec("numba")
  origin = getattr(spec, "origin", None)
  if not origin:
    return b""
  path = Path(origin).with_name("_version.py")
  try:
    return path.read_bytes()
  except OSError:
    return str(Path(origin).stat().st_mtime_ns).encode()


def _cpu() -> bytes:
  try:
    with open("/proc/cpuinfo", "rb") as f:
      lines = f.read().split(b"\n\n", 1)[0].splitlines()
    return b"\n".join(x for x in lines if x.startswith((b"model name", b"flags")))
  except OSError:
    return platform.processor().encode()


def warm_marker(program: str) -> Path:
  """The file that says this program's kernels were compiled for this code: its name is a
  SHA-256 of the package's sources, the manifest, numba's version, Python's and the CPU's."""
  from lrf_jax import compilation_cache
  h = hashlib.sha256()
  for part in (program.encode(), sys.version.encode(), _numba_version_bytes(), _cpu()):
    h.update(part)
  for path in sorted(PACKAGE.rglob("*.py")) + [MANIFEST]:
    h.update(str(path.relative_to(PACKAGE)).encode())
    h.update(path.read_bytes())
  return compilation_cache.numba_cache_dir() / "lrf_jax" / "warm" / f"{program}-{h.hexdigest()}"


def start(program: str) -> bool:
  """Start the compile workers for `program` when the cache is cold for this code, there is
  more than one core and `LRF_JAX_PARALLEL_COMPILE` does not say 0; True when they started.
  Call `stop()` in a `finally`."""
  if program not in PROGRAMS or not enabled() or cores() < 2 or _STATE["procs"]:
    return False
  try:
    marker = warm_marker(program)
    if marker.exists():
      return False
    marker.parent.mkdir(parents=True, exist_ok=True)
    claims = tempfile.mkdtemp(prefix="lrf_jax_claims_")
  except OSError:
    return False
  cmd = [sys.executable, "-m", "lrf_jax.cli.parallel_compile", "--worker", program, claims,
         str(os.getpid())]
  env = {**os.environ, "PYTHONPATH": os.pathsep.join(
      [str(PACKAGE.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}
  procs: list[subprocess.Popen] = []
  _STATE.update(procs=procs, claims=claims, marker=marker)
  try:
    for _ in range(cores() - 1):
      procs.append(subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=None if os.environ.get("LRF_JAX_DEBUG_COMPILE") else
                                    subprocess.DEVNULL, env=env))
  except OSError:  # no process to spare: the command compiles alone
    stop()
    _STATE.update(procs=[], claims=None, marker=None)
    shutil.rmtree(claims, ignore_errors=True)
    return False
  from lrf_jax import kernel_cache  # the notice comes when this process compiles or waits
  kernel_cache.share(claims, alive=_alive)
  return True


def _alive(pid: int) -> bool:
  return any(p.pid == pid and p.poll() is None for p in _STATE["procs"])


def stop(grace: float = 0.0) -> None:
  """End the workers (idempotent): those still running after `grace` seconds are terminated;
  when they had all finished their work, mark this code's kernels as compiled
  (`warm_marker`). A worker whose share met the command's own exits on its own within moments
  (a loaded machine may delay that past the command's end: the grace lets it)."""
  procs, claims, marker = _STATE["procs"], _STATE["claims"], _STATE["marker"]
  if not procs:
    return
  deadline = time.monotonic() + grace
  while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
    time.sleep(0.05)
  finished = all(p.poll() == 0 for p in procs)
  for p in procs:
    if p.poll() is None:
      p.terminate()
  for p in procs:
    try:
      p.wait(timeout=5)
    except subprocess.TimeoutExpired:
      p.kill()
      p.wait()
  _STATE.update(procs=[], claims=None, marker=None)
  if "numba" in sys.modules:
    from lrf_jax import kernel_cache
    kernel_cache.share(None)
  shutil.rmtree(claims, ignore_errors=True)
  if finished and marker is not None:
    with contextlib.suppress(OSError):
      marker.touch()


@contextlib.contextmanager
def compiling(program: str) -> Any:
  """`start(program)`, then `stop()` however the block ends (after `FINISH_GRACE_S` for the
  workers to finish when it ends normally; at once on Ctrl-C or an error)."""
  start(program)
  try:
    yield
  except BaseException:
    stop()
    raise
  stop(FINISH_GRACE_S)


# -- the manifest --------------------------------------------------------------------------------

def manifest() -> dict[str, list[list[Any]]]:
  """program -> [[module, function, [argument types as numba writes them]], ...] in the order
  the program first calls them."""
  return json.loads(MANIFEST.read_text())


def kernel_modules() -> dict[str, Any]:
  """The modules that define the kernels of the manifest, imported by name (a static list: the
  manifest's test checks that it covers the manifest)."""
  from lrf_jax.descriptors import matching, toldi
  from lrf_jax.frames import lrf_net_host, lrf_net_plus_sums
  from lrf_jax.geometry import normals, orientation
  from lrf_jax.registration import graph, host, icp_host
  from lrf_jax.search import ball_lists, balls, grid, nearest
  mods = (matching, toldi, lrf_net_host, lrf_net_plus_sums, normals, orientation, graph, host,
          icp_host, ball_lists, balls, grid, nearest)
  return {m.__name__: m for m in mods}


def parse_type(text: str) -> Any:
  """A numba type from its repr (`Array(float64, 2, 'C', False, aligned=True)`, `int64`)."""
  from numba.core import types
  names = {k: v for k, v in vars(types).items() if not k.startswith("_")}
  names["bool"] = types.boolean
  return eval(text, {"__builtins__": {}}, names)  # noqa: S307 -- our own manifest's text


def compile_program(program: str) -> None:
  """Compile (or load) every kernel of `program`'s manifest in this process, then mark this
  code's cache warm for it (`warm_marker`): `lrf-compile`'s group "program:<program>", after
  which a first run starts no worker.

  Raises:
    Exception: a kernel that did not compile (numba's error; nothing is marked).
  """
  from lrf_jax import compilation_cache, kernel_cache
  kernel_cache.install(compilation_cache.numba_fallback_dirs)
  mods = kernel_modules()
  for module, name, sig in manifest()[program]:
    getattr(mods[module], name).compile(tuple(parse_type(t) for t in sig))
  marker = warm_marker(program)
  marker.parent.mkdir(parents=True, exist_ok=True)
  marker.touch()


def _run_worker(program: str, claims: str, parent: int) -> int:
  """Compile `program`'s kernels from the last the main process calls backwards, skipping
  those another process claimed; 0 when every one was compiled (or claimed elsewhere)."""
  die_with_parent(parent)
  from lrf_jax import compilation_cache, kernel_cache
  kernel_cache.install(compilation_cache.numba_fallback_dirs)
  kernel_cache.share(claims, worker=True)
  mods = kernel_modules()
  failed = 0
  for module, name, sig in reversed(manifest()[program]):
    disp = getattr(mods[module], name)
    index = str(disp._cache._cache_file._index_path)  # noqa: SLF001 -- numba has no public one
    if not kernel_cache.claim(index):
      continue
    try:
      disp.compile(tuple(parse_type(t) for t in sig))
    except Exception as e:  # noqa: BLE001 -- the main process compiles it; the others go on
      failed += 1
      print(f"lrf_jax compile worker: {module}.{name}: {type(e).__name__}: {e}",
            file=sys.stderr)
    finally:
      kernel_cache.release_claims()
  return 1 if failed else 0


_WATCH_S = 0.5  # how often a worker checks that its parent still runs (where prctl is missing)


def die_with_parent(parent: int) -> None:
  """End this process (a compile worker) when `parent`, the process that started it, ends,
  however it ends (SIGKILL included), and ignore Ctrl-C (the parent stops its workers).

  Linux: `prctl(PR_SET_PDEATHSIG, SIGKILL)` (the kernel kills this process when the thread that
  started it ends). Everywhere: a daemon thread that exits the process within `_WATCH_S`
  seconds of its parent's pid changing (the orphan is adopted by init or a subreaper). A
  process whose parent ended before this call exits at once. Does nothing in `parent` itself.
  """
  if os.getpid() == parent:
    return
  with contextlib.suppress(ValueError):  # not the main thread: no handler to change
    signal.signal(signal.SIGINT, signal.SIG_IGN)
  if sys.platform.startswith("linux"):
    with contextlib.suppress(Exception):
      import ctypes
      ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PDEATHSIG

  def watch() -> None:
    while True:
      if os.getppid() != parent:
        os._exit(1)
      time.sleep(_WATCH_S)

  if os.getppid() != parent:
    os._exit(1)
  threading.Thread(target=watch, name="lrf_jax-parent-watch", daemon=True).start()


class MortalProcess(_mp_context.SpawnProcess):
  """A spawned process that dies with the process that started it (`die_with_parent`)."""

  def __init__(self, *args: Any, **kwargs: Any) -> None:
    super().__init__(*args, **kwargs)
    self.lrf_jax_parent = os.getpid()

  def run(self) -> None:
    die_with_parent(self.lrf_jax_parent)
    super().run()


class _MortalContext(_mp_context.SpawnContext):
  Process = MortalProcess


def spawn_context() -> _mp_context.SpawnContext:
  """A multiprocessing "spawn" context whose processes die with the process that started them
  (`MortalProcess`): `lrf-compile`'s pool of workers."""
  return _MortalContext()


def main(argv: list[str] | None = None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  if argv[:1] == ["--worker"] and len(argv) == 4:
    return _run_worker(argv[1], argv[2], int(argv[3]))
  print("usage: python -m lrf_jax.cli.record_manifest (this module runs the workers)",
        file=sys.stderr)
  return 2


if __name__ == "__main__":
  sys.exit(main())
