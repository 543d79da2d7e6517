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

The cache heals instead of failing the run (`install()` patches numba's cache for lrf_jax's
kernels only; each case is one line on stderr):

* an unreadable entry (a truncated or corrupt index `*.nbi` or data file `*.nbc`, or data that
  does not rebuild) is set aside, renamed `<name>.corrupt-<timestamp>` (deleted when it cannot be
  renamed), and the kernel is compiled again;
* a cache that cannot be written (read-only; any `OSError` of a save but a full disk's) is
  still read, and a kernel it lacks is saved in the first of
  `compilation_cache.numba_fallback_dirs()` that takes it (where later loads from that folder
  also look), else kept in memory only;
* a full disk (`ENOSPC`, `EDQUOT`) leaves the kernel compiled in memory for the run.

No error of the cache reaches the caller (where a command would report it as an input's).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import hashlib
import inspect
import os
import sys
import threading
import time
import types
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from numba.core import config
from numba.core import caching
from numba.core.caching import UserProvidedCacheLocator

PACKAGE_ROOT = os.path.dirname(os.path.abspath(__file__))  # .../lrf_jax
# The kernels' folders of the cache directory that could not be written in this process: a miss
# there is looked up in the fallback roots too (module docstring).
_UNWRITABLE: set[str] = set()


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
    """The locator of an lrf_jax kernel, also when its folder cannot be written (numba's own
    locators decline then, and numba fell back to the package's folder): its entries still
    load, and saves go elsewhere (module docstring)."""
    if not _cache_dir() or not _inside(py_file) or not os.path.exists(py_file):
      return None
    self = cls(py_func, py_file)
    try:
      self.ensure_cache_path()
    except OSError:
      _UNWRITABLE.add(os.path.abspath(self._cache_path))
    return self


def install(fallbacks: Callable[..., Sequence[Any]] | None = None, *,
            on_wait: Callable[[], None] | None = None) -> None:
  """Put `PackageLocator` first in numba's list of cache locators (idempotent). numba picks a
  function's locator when the function is decorated, so this runs before lrf_jax's kernels are
  defined. Also locks each save of an lrf_jax kernel and lets claims work (module docstring).

  Args:
    fallbacks: where kernels go when the cache directory cannot take them: a function
      `(exclude, create=) -> folders` (`compilation_cache.numba_fallback_dirs`); None keeps
      the one installed before (none: such kernels compile in memory only).
    on_wait: called when this process starts waiting for a kernel another process is
      compiling (`compilation_cache`'s compile notice: the kernel is compiled, if not here);
      None keeps the one installed before.
  """
  if fallbacks is not None:
    _FALLBACKS[:] = [fallbacks]
  if on_wait is not None:
    _ON_WAIT[:] = [on_wait]
  impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
  classes = getattr(impl, "_locator_classes", None)
  if isinstance(classes, list) and PackageLocator not in classes:
    classes.insert(0, PackageLocator)  # a numba without this list keeps its own keys
  _patch_cache_file()
  _patch_cache()


# -- several processes, one cache ---------------------------------------------------------------

# claims: the folder of this run's claims (None: no claims); worker: a compile worker (never
# waits); alive: pid -> whether that claimant is still compiling; held: claims this process holds.
_SHARING: dict[str, Any] = {"claims": None, "worker": False, "alive": None, "held": set()}
_WAIT_LIMIT_S = 600.0
# What a wait for another process's compile calls first (`install`'s `on_wait`).
_ON_WAIT: list[Callable[[], None]] = []


def share(claims: str | None, *, worker: bool = False,
          alive: Callable[[int], bool] | None = None) -> None:
  """Claim kernels in the folder `claims` before compiling them (None: stop claiming). A
  `worker` skips what another process claimed (`claim`); another process waits, while
  `alive(pid)` of the claimant holds, for a kernel a worker is compiling."""
  _SHARING.update(claims=claims, worker=worker, alive=alive)


def _under(path: str, root: str) -> bool:
  return path == root or path.startswith(root + os.sep)


def _ours(cache_file: Any) -> bool:
  """Whether `cache_file` (numba's `IndexDataCacheFile`) is an lrf_jax kernel's in the cache
  directory in use."""
  path = os.path.abspath(str(getattr(cache_file, "_cache_path", "")))
  return bool(_cache_dir()) and _under(path, os.path.join(_cache_dir(), "lrf_jax"))


# Where kernels go when the cache directory cannot take them: `install`'s `fallbacks`, a function
# (exclude, create) -> folders (`compilation_cache.numba_fallback_dirs`); none until installed.
_FALLBACKS: list[Callable[..., Sequence[Any]]] = []


def _fallback_roots(create: bool = False) -> list[str]:
  if not _FALLBACKS:
    return []
  return [str(p) for p in _FALLBACKS[0](_cache_dir() or None, create=create)]


def _managed(cache_file: Any) -> bool:
  """Whether `cache_file` is an lrf_jax kernel's, in the cache directory or a fallback."""
  if _ours(cache_file):
    return True
  path = os.path.abspath(str(getattr(cache_file, "_cache_path", "")))
  return any(_under(path, os.path.join(os.path.abspath(r), "lrf_jax"))
             for r in _fallback_roots())


_HELD = threading.local()  # the lock files this thread holds (a lock is taken once)


@contextlib.contextmanager
def _index_lock(cache_file: Any) -> Iterator[None]:
  """An exclusive lock on `<index>.lock` (POSIX; elsewhere numba's own writes only). Reentrant
  within a thread; without a lock file that can be opened (a read-only folder, a full disk),
  no lock."""
  try:
    import fcntl
  except ImportError:  # Windows
    yield
    return
  path = str(cache_file._index_path) + ".lock"
  held: set[str] = _HELD.__dict__.setdefault("paths", set())
  f = None
  if path not in held:
    for mode in ("ab", "rb"):
      with contextlib.suppress(OSError):
        f = open(path, mode)  # noqa: SIM115 -- closed below
        break
  if f is None:
    yield
    return
  with f:
    try:
      fcntl.flock(f.fileno(), fcntl.LOCK_EX)
    except OSError:  # a file system without locks
      yield
      return
    held.add(path)
    try:
      yield
    finally:
      held.discard(path)
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
  if not os.path.exists(path + ".done") and alive is not None and alive(owner):
    for hook in _ON_WAIT:  # a kernel this process needs is being compiled: say so
      hook()
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
    if not _managed(self):
      return save(self, key, data)
    with _index_lock(self):
      save(self, key, data)
    if _SHARING["claims"] and not _SHARING["worker"]:
      release_claims()

  def claimed_load(self: Any, key: Any) -> Any:
    out = load(self, key)
    if out is None:
      out = _load_elsewhere(self, key)
    if out is None and _SHARING["claims"] and _ours(self) and \
        _wait_for_claimant(str(self._index_path)):
      out = load(self, key)
      if out is None:
        out = _load_elsewhere(self, key)
    return out

  locked_save._lrf_jax = True  # type: ignore[attr-defined]
  cls.save = locked_save  # type: ignore[method-assign]
  cls.load = claimed_load  # type: ignore[method-assign]


# -- a cache that heals -------------------------------------------------------------------------

_NOTES: set[str] = set()
_NOTES_LOCK = threading.Lock()
_FULL = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))


def _note(key: str, text: str) -> None:
  """Print `lrf_jax: <text>` on stderr, once per process for each `key`."""
  with _NOTES_LOCK:
    if key in _NOTES:
      return
    _NOTES.add(key)
  print(f"lrf_jax: {text}", file=sys.stderr, flush=True)


def _why(error: BaseException) -> str:
  if isinstance(error, OSError) and error.strerror:
    return error.strerror
  return f"{type(error).__name__}: {error}" if str(error) else type(error).__name__


def _set_aside(path: str, error: BaseException) -> None:
  """Move the unreadable cache file `path` out of the way (`<name>.corrupt-<timestamp>`, or
  deleted when it cannot be renamed), with one line on stderr naming it."""
  target = f"{path}.corrupt-{time.strftime('%Y%m%d-%H%M%S')}"
  try:
    os.replace(path, target)
    done = f"set aside as {os.path.basename(target)}"
  except FileNotFoundError:
    return  # set aside by another process already
  except OSError:
    try:
      os.unlink(path)
      done = "deleted"
    except FileNotFoundError:
      return
    except OSError as e:
      done = f"left in place ({e.strerror or e})"
  _note(f"corrupt:{path}", f"unreadable kernel cache entry {path} ({_why(error)}): {done}; "
        "the kernel is compiled again")


def _patch_cache() -> None:
  """Heal lrf_jax's entries: set aside unreadable files, read a cache that cannot be written
  and save elsewhere, keep a kernel that cannot be saved in memory (idempotent)."""
  file_cls, cache_cls = caching.IndexDataCacheFile, caching.Cache
  if getattr(cache_cls.save_overload, "_lrf_jax", False):
    return
  load_index, load_data = file_cls._load_index, file_cls._load_data
  load_overload, save_overload = cache_cls._load_overload, cache_cls.save_overload

  def healing_load_index(self: Any) -> dict:
    if not _managed(self):
      return load_index(self)
    try:
      return _checked_index(load_index(self))
    except FileNotFoundError:
      return {}
    except Exception:  # noqa: BLE001 -- anything unreadable: check again under the lock
      with _index_lock(self):  # a save in progress elsewhere replaces the file whole
        try:
          return _checked_index(load_index(self))
        except FileNotFoundError:
          return {}
        except Exception as e:  # noqa: BLE001
          _set_aside(str(self._index_path), e)
      return {}

  def healing_load_data(self: Any, name: str) -> Any:
    if not _managed(self):
      return load_data(self, name)
    try:
      return load_data(self, name)
    except OSError:
      raise  # numba's `load` takes a missing file as a miss
    except Exception:  # noqa: BLE001
      with _index_lock(self):
        try:
          return load_data(self, name)
        except OSError:
          raise
        except Exception as e:  # noqa: BLE001
          _set_aside(self._data_path(name), e)
      return None

  def healing_load_overload(self: Any, sig: Any, target_context: Any) -> Any:
    if not _managed(self._cache_file) or not self._enabled:
      return load_overload(self, sig, target_context)
    started = time.time()
    key = self._index_key(sig, target_context.codegen())
    data = self._cache_file.load(key)
    if data is None:
      return None
    try:
      return self._impl.rebuild(target_context, data)
    except Exception as e:  # noqa: BLE001 -- data that unpickled but does not rebuild
      _set_aside_entry(self._cache_file, key, e, started)
      return None

  def healing_save_overload(self: Any, sig: Any, data: Any) -> None:
    if not _ours(self._cache_file):
      return save_overload(self, sig, data)
    try:
      save_overload(self, sig, data)
    except OSError as e:
      _save_elsewhere(self, sig, data, e)

  healing_save_overload._lrf_jax = True  # type: ignore[attr-defined]
  file_cls._load_index = healing_load_index  # type: ignore[method-assign]
  file_cls._load_data = healing_load_data  # type: ignore[method-assign]
  cache_cls._load_overload = healing_load_overload  # type: ignore[method-assign]
  cache_cls.save_overload = healing_save_overload  # type: ignore[method-assign]


def _checked_index(overloads: Any) -> dict:
  if not isinstance(overloads, dict):
    raise TypeError(f"an index of {type(overloads).__name__}, not of a dict")
  return overloads


def _elsewhere(cache_file: Any, root: str) -> Any:
  """numba's `IndexDataCacheFile` of the same kernel (name and stamp) under the cache root
  `root` instead of the cache directory in use."""
  rel = os.path.relpath(os.path.abspath(cache_file._cache_path), os.path.abspath(_cache_dir()))
  base = cache_file._index_name[:-len(".nbi")]
  return caching.IndexDataCacheFile(cache_path=os.path.join(root, rel), filename_base=base,
                                    source_stamp=cache_file._source_stamp)


def _load_elsewhere(cache_file: Any, key: Any) -> Any:
  """The entry `key` of the kernel of `cache_file` from the fallback roots when its folder in
  the cache directory could not be written, else (or when absent there) None."""
  if os.path.abspath(cache_file._cache_path) not in _UNWRITABLE or not _ours(cache_file):
    return None
  for root in _fallback_roots():
    other = _elsewhere(cache_file, root)
    if os.path.exists(other._index_path):
      out = other.load(key)
      if out is not None:
        return out
  return None


def _set_aside_entry(cache_file: Any, key: Any, error: BaseException, started: float) -> None:
  """Set aside the data file of `key` that failed to rebuild: the first (in load order) whose
  index holds `key`, unless it was rewritten since the load began."""
  files = [cache_file]
  if os.path.abspath(cache_file._cache_path) in _UNWRITABLE and _ours(cache_file):
    files += [_elsewhere(cache_file, r) for r in _fallback_roots()]
  for f in files:
    name = f._load_index().get(key)
    if name is None:
      continue
    path = f._data_path(name)
    with _index_lock(f):
      with contextlib.suppress(OSError):
        if os.stat(path).st_mtime < started:
          _set_aside(path, error)
    return


def _save_elsewhere(cache: Any, sig: Any, data: Any, error: OSError) -> None:
  """After a failed save of a compiled kernel: keep it in a fallback root when the cache cannot
  be written, else in memory only; one line on stderr says which."""
  root = _cache_dir()
  if _SHARING["claims"] and not _SHARING["worker"]:
    release_claims()
  if error.errno in _FULL:
    _note("full", f"could not save compiled kernels in {root} ({_why(error)}): they are "
          "compiled in memory only for this run")
    return
  _UNWRITABLE.add(os.path.abspath(cache._cache_file._cache_path))
  for fallback in _fallback_roots(create=True):
    other = _elsewhere(cache._cache_file, fallback)
    try:
      os.makedirs(other._cache_path, exist_ok=True)
      other.save(cache._index_key(sig, data.codegen), cache._impl.reduce(data))
    except OSError:
      continue
    _note("elsewhere", f"the kernel cache {root} cannot be written ({_why(error)}): kernels "
          f"it lacks are compiled and saved in {fallback}")
    return
  _note("elsewhere", f"the kernel cache {root} cannot be written ({_why(error)}): kernels it "
        "lacks are compiled in memory only for this run")
