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
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import sys
import types
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
  defined."""
  impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
  classes = getattr(impl, "_locator_classes", None)
  if isinstance(classes, list) and PackageLocator not in classes:
    classes.insert(0, PackageLocator)  # a numba without this list keeps its own keys
