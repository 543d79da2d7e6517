"""numba's on-disk cache for lrf_jax's kernels, keyed by everything a kernel is compiled from.

numba keys a cached kernel by its own source file: its path and (numba >= 0.61) its contents. A
kernel compiles in the numba functions it calls from other files (the shared helpers of
`frames/host_geometry.py`, `search/bits.py`'s popcount, `search/nearest.py`'s insertion) and the
global constants it reads, so an edited helper or constant in another file left every cached
kernel that inlines it stale: the old code ran, silently. And an install at another path (a
second clone, another venv) compiled everything again.

`PackageLocator` keys lrf_jax's kernels instead by:

* the stamp: SHA-256 of the sources of `dependency_files(kernel)`: the kernel's file and every
  lrf_jax file that defines a function it calls or a global it reads, followed through the calls
  (`numba` checks the stamp on every load, and recompiles on a mismatch);
* the directory: `NUMBA_CACHE_DIR/lrf_jax/<subpackage>`, the same for every install of the
  package, so a second clone or venv loads the kernels the first one compiled.

`install()` (run by `compilation_cache.announce_compiles`, which every module that defines a
cached kernel calls before defining it) puts it first in numba's locator list; functions outside
lrf_jax fall through to numba's own locators. The index file still records numba's version and
the CPU, so a cache is never loaded by another numba or another kind of machine.

Several processes may write one cache at once (`lrf-compile`'s workers, the compile workers of
`lrf_jax.cli.parallel_compile`). numba writes each file atomically (a temporary file, then
`os.replace`), but an entry is two files: its index is read, a data file name chosen, the index
and then the data written. Two processes saving different signatures of one kernel at once both
chose the same data file, and the index could end pointing at the other signature's code.
`install()` therefore also takes an exclusive lock (`flock` on `<index>.lock`) around each save
of an lrf_jax kernel. With `share(claims)`, a process also *claims* a kernel in the folder
`claims` before compiling it: a compile worker skips a kernel claimed by another process, and the
main process waits for a worker that is compiling the kernel it needs, then loads it, instead of
compiling it a second time.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import os
import sys
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

from numba.core import config
from numba.core import caching
from numba.core.caching import UserProvidedCacheLocator

PACKAGE_ROOT = os.path.dirname(os.path.abspath(__file__))  # .../lrf_jax


def _cache_dir() -> str:
  return str(getattr(config, "CACHE_DIR", "") or "")  # NUMBA_CACHE_DIR, read by numba's config


def _inside(path: str | None) -> bool:
  return path is not None and os.path.abspath(path).startswith(PACKAGE_ROOT + os.sep)


def _names(code: types.CodeType) -> set[str]:
  """The global and attribute names a code object reads, with those of the code nested in it."""
  names = set(code.co_names)
  for const in code.co_consts:
    if isinstance(const, types.CodeType):
      names |= _names(const)
  return names


def _python_function(value: Any) -> types.FunctionType | None:
  """The Python function behind a numba dispatcher (`py_func`), an intrinsic (`_defn`) or a
  plain function; None for anything else."""
  for attr in ("py_func", "_defn"):
    inner = getattr(value, attr, None)
    if isinstance(inner, types.FunctionType):
      return inner
  return value if isinstance(value, types.FunctionType) else None


def _defining_files(name: str, value: Any) -> set[str]:
  """lrf_jax's loaded modules that bind `name` to `value` at module level (where a constant read
  by a kernel was defined, or imported from)."""
  files = set()
  for mod_name, module in list(sys.modules.items()):
    if not mod_name.startswith("lrf_jax") or vars(module).get(name, None) is not value:
      continue
    file = getattr(module, "__file__", None)
    if file is not None and _inside(file):
      files.add(os.path.abspath(file))
  return files


def dependency_files(py_func: types.FunctionType) -> list[str]:
  """Sorted absolute paths of the lrf_jax sources a kernel is compiled from: the file of
  `py_func`, then, for every name its code reads in its globals, the file of the function called
  (a dispatcher, an intrinsic, or a module's attribute such as `hg.write_frame`, followed through
  its own calls) or the modules that define the constant read."""
  files: set[str] = set()
  seen: set[types.FunctionType] = set()
  stack = [py_func]
  while stack:
    func = stack.pop()
    if func in seen:
      continue
    seen.add(func)
    file = inspect.getsourcefile(func)
    if file is None or not _inside(file):
      continue
    files.add(os.path.abspath(file))
    names = _names(func.__code__)
    for name in names & set(func.__globals__):
      value = func.__globals__[name]
      if isinstance(value, types.ModuleType):
        if _inside(getattr(value, "__file__", None)):
          stack.extend(f for n in names if (f := _python_function(getattr(value, n, None))))
      elif (callee := _python_function(value)) is not None:
        stack.append(callee)
      elif not isinstance(value, type):
        files |= _defining_files(name, value)
  return sorted(files)


@functools.cache
def _file_digest(path: str, mtime_ns: int, size: int) -> bytes:
  with open(path, "rb") as f:
    return hashlib.sha256(f.read()).digest()


def source_stamp(py_func: types.FunctionType) -> str:
  """SHA-256 (hex) over the paths relative to the package and the contents of
  `dependency_files(py_func)`."""
  h = hashlib.sha256()
  for path in dependency_files(py_func):
    st = os.stat(path)
    h.update(os.path.relpath(path, PACKAGE_ROOT).encode())
    h.update(_file_digest(path, st.st_mtime_ns, st.st_size))
  return h.hexdigest()


class PackageLocator(UserProvidedCacheLocator):
  """numba cache locator for functions defined in lrf_jax (module docstring); needs
  `NUMBA_CACHE_DIR` (which `import lrf_jax` sets) and declines everything else."""

  def __init__(self, py_func: types.FunctionType, py_file: str):
    super().__init__(py_func, py_file)
    sub = os.path.relpath(os.path.dirname(os.path.abspath(py_file)), PACKAGE_ROOT)
    self._cache_path = os.path.join(_cache_dir(), "lrf_jax", sub)
    self._stamp = source_stamp(py_func)

  def get_source_stamp(self) -> str:
    return self._stamp

  @classmethod
  def from_function(cls, py_func: types.FunctionType, py_file: str) -> PackageLocator | None:
    if not _cache_dir() or not _inside(py_file):
      return None
    return super().from_function(py_func, py_file)



def install() -> None:
  """Put `PackageLocator` first in numba's list of cache locators (idempotent). numba picks a
  function's locator when the function is decorated, so this runs before lrf_jax's kernels are
  defined. Also locks each save of an lrf_jax kernel and lets claims work (module docstring)."""
  impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
  classes = getattr(impl, "_locator_classes", None)
  if isinstance(classes, list) and PackageLocator not in classes:
    classes.insert(0, PackageLocator)  # a numba without this list keeps its own keys
  _patch_cache_file()


# -- several processes, one cache ---------------------------------------------------------------

# claims: the folder of this run's claims (None: no claims); worker: a compile worker (never
# waits); alive: pid -> whether that claimant is still compiling; held: claims this process holds.
_SHARING: dict[str, Any] = {"claims": None, "worker": False, "alive": None, "held": set()}
_WAIT_LIMIT_S = 600.0


def share(claims: str | None, *, worker: bool = False,
          alive: Callable[[int], bool] | None = None) -> None:
  """Claim kernels in the folder `claims` before compiling them (None: stop claiming). A
  `worker` skips what another process claimed (`claim`); another process waits, while
  `alive(pid)` of the claimant holds, for a kernel a worker is compiling."""
  _SHARING.update(claims=claims, worker=worker, alive=alive)


def _ours(cache_file: Any) -> bool:
  root = os.path.join(_cache_dir(), "lrf_jax")
  path = os.path.abspath(str(getattr(cache_file, "_cache_path", "")))
  return bool(_cache_dir()) and (path == root or path.startswith(root + os.sep))


@contextlib.contextmanager
def _index_lock(cache_file: Any) -> Iterator[None]:
  """An exclusive lock on `<index>.lock` (POSIX; elsewhere numba's own writes only)."""
  try:
    import fcntl
  except ImportError:  # Windows
    yield
    return
  with open(str(cache_file._index_path) + ".lock", "ab") as f:
    fcntl.flock(f.fileno(), fcntl.LOCK_EX)
    try:
      yield
    finally:
      fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _claim_path(index_path: str) -> str:
  name = hashlib.sha256(os.path.abspath(index_path).encode()).hexdigest()[:32]
  return os.path.join(_SHARING["claims"], name)


def _owner(claim: str) -> int:
  try:
    with open(claim) as f:
      return int(f.read() or 0)
  except (OSError, ValueError):
    return 0


def claim(index_path: str) -> bool:
  """Claim the kernel whose cache index is `index_path` for this process: True when this
  process holds the claim now (taken, or held already), False when another process holds it.
  Without a claims folder (`share`), always True."""
  if not _SHARING["claims"]:
    return True
  path = _claim_path(index_path)
  if path in _SHARING["held"]:
    return True
  tmp = f"{path}.{os.getpid()}.tmp"
  with open(tmp, "w") as f:
    f.write(str(os.getpid()))
  try:
    os.link(tmp, path)  # atomic, and the claim carries its owner from the start
  except FileExistsError:
    return _owner(path) == os.getpid()
  finally:
    os.unlink(tmp)
  _SHARING["held"].add(path)
  _debug(f"claimed {os.path.basename(index_path)}")
  return True


def _debug(text: str) -> None:
  if os.environ.get("LRF_JAX_DEBUG_COMPILE"):
    print(f"[{time.time() % 1000:.2f} {os.getpid()}] {text}", file=sys.stderr, flush=True)


def release_claims() -> None:
  """Mark every kernel this process claimed as done (compiled and saved, or given up)."""
  for path in list(_SHARING["held"]):
    with contextlib.suppress(OSError):
      open(path + ".done", "w").close()
    _SHARING["held"].discard(path)


def _wait_for_claimant(index_path: str) -> bool:
  """After a cache miss: claim the kernel, or wait for the live worker compiling it. True when
  a worker finished it (load again), False when this process compiles it."""
  if claim(index_path) or _SHARING["worker"]:
    return False
  path = _claim_path(index_path)
  owner, alive = _owner(path), _SHARING["alive"]
  deadline = time.monotonic() + _WAIT_LIMIT_S
  _debug(f"waits for {owner}: {os.path.basename(index_path)}")
  while not os.path.exists(path + ".done"):
    if alive is None or not alive(owner) or time.monotonic() > deadline:
      return False
    time.sleep(0.01)
  _debug(f"waited for {os.path.basename(index_path)}")
  return True


def _patch_cache_file() -> None:
  """Lock saves of lrf_jax kernels, and claim (or wait) on their cache misses (idempotent)."""
  cls = caching.IndexDataCacheFile
  if getattr(cls.save, "_lrf_jax", False):
    return
  save, load = cls.save, cls.load

  def locked_save(self: Any, key: Any, data: Any) -> None:
    if not _ours(self):
      return save(self, key, data)
    with _index_lock(self):
      save(self, key, data)
    if _SHARING["claims"] and not _SHARING["worker"]:
      release_claims()

  def claimed_load(self: Any, key: Any) -> Any:
    out = load(self, key)
    if out is None and _SHARING["claims"] and _ours(self) and \
        _wait_for_claimant(str(self._index_path)):
      out = load(self, key)
    return out

  locked_save._lrf_jax = True  # type: ignore[attr-defined]
  cls.save = locked_save  # type: ignore[method-assign]
  cls.load = claimed_load  # type: ignore[method-assign]
