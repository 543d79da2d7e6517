"""Where compiled code is kept between processes, and a one-time note when code is compiled.

Two caches share one per-user root, `cache_root()` (`$XDG_CACHE_HOME/lrf_jax`, else
`~/.cache/lrf_jax`):

* numba's kernels (`cache=True`) in `cache_root()/numba`: `configure_numba_cache()` (run by
  `import lrf_jax`, before numba is imported) sets `NUMBA_CACHE_DIR` there unless the user has
  set it. numba would otherwise write next to the package's sources. lrf_jax's kernels are keyed
  by the contents of every source they are compiled from and not by the install's path
  (`kernel_cache`): an edited helper recompiles the kernels that call it, and a second
  install of the same code loads the first one's kernels. A cache that cannot take new kernels
  (read-only) is still read; what it lacks is saved in the first of `numba_fallback_dirs()`
  (`cache_root()/numba` when `NUMBA_CACHE_DIR` is elsewhere, then a private folder in the
  temporary directory), never in the package's folder.
* JAX's persistent compilation cache in `cache_root()/jax` (or `$LRF_JAX_CACHE_DIR`):
  `enable()`, called by the command-line programs. A fresh `lrf-register` or `lrf-frames` would
  otherwise recompile every jitted function it calls.

`announce_compiles()` prints one line on stderr the first time a process actually compiles an
lrf_jax kernel (a numba cache miss), waits for a compile worker compiling one it needs
(`kernel_cache`'s claims), or compiles a JAX program (a persistent-cache miss, or a compile over
a second when that cache is off), so that a first run's wait is not a silent one. Nothing else
prints it: a warm cache prints nothing, even when `lrf_jax.cli.parallel_compile` starts its
workers (it starts them whenever its marker of this code's sources is missing, which any edit
of a source, or another program's first run, leaves missing while the kernels are cached).

Nothing here imports numba or JAX at module level: `import lrf_jax` stays light.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any, TextIO

ENV_VAR = "LRF_JAX_CACHE_DIR"
NUMBA_ENV_VAR = "NUMBA_CACHE_DIR"
NOTICE = ("lrf_jax: compiling kernels for this machine (first run only, up to a minute; later "
          "runs load them from {where}) ...")
_JAX_COMPILE_NOTICE_SECS = 1.0  # with JAX's cache off, a compile this long is worth the note

_LOCK = threading.Lock()
_state: dict[str, Any] = {"announced": False, "numba": None, "jax": False, "stream": None,
                         "jax_cache": None}


def cache_root() -> Path:
  """The per-user cache root: `$XDG_CACHE_HOME/lrf_jax`, else `~/.cache/lrf_jax`."""
  base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
  return Path(base).expanduser() / "lrf_jax"


def cache_dir() -> Path:
  """JAX's cache directory: `$LRF_JAX_CACHE_DIR`, else `cache_root()/jax`."""
  explicit = os.environ.get(ENV_VAR)
  if explicit:
    return Path(explicit).expanduser()
  return cache_root() / "jax"


def cache_locations() -> str:
  """Where compiled code is kept, in words: `cache_root()`, or the folders in use when
  `NUMBA_CACHE_DIR` or `LRF_JAX_CACHE_DIR` puts one elsewhere."""
  root = cache_root()
  places = [numba_cache_dir(), cache_dir()]
  if all(root in (p, *p.parents) for p in places):
    return str(root)
  return " and ".join(dict.fromkeys(map(str, places)))


def numba_cache_dir() -> Path:
  """numba's cache directory: `$NUMBA_CACHE_DIR` when set, else `cache_root()/numba`."""
  explicit = os.environ.get(NUMBA_ENV_VAR)
  if explicit:
    return Path(explicit).expanduser()
  return cache_root() / "numba"


def _private_tmp_dir() -> Path:
  user = str(os.getuid()) if hasattr(os, "getuid") else (os.environ.get("USERNAME") or "user")
  return Path(tempfile.gettempdir()) / f"lrf_jax-{user}"


def _private(folder: Path, create: bool) -> bool:
  """Whether `folder` is a directory (not a link) of this user that no one else may write;
  created (mode 700) first when `create`. Kernels are pickles: one planted in a shared
  temporary directory by another user would run as this one."""
  try:
    if create:
      folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = folder.lstat()
  except OSError:
    return False
  if not stat.S_ISDIR(st.st_mode):
    return False
  return not hasattr(os, "getuid") or (st.st_uid == os.getuid() and not st.st_mode & 0o022)


def numba_fallback_dirs(exclude: str | os.PathLike | None = None, *,
                        create: bool = False) -> list[Path]:
  """Where lrf_jax's kernels are kept when numba's cache directory cannot take them (read-only,
  or a folder that cannot be created), in order of preference: `cache_root()/numba`, then
  `lrf_jax-<uid>/numba` in the temporary directory (used only when it is this user's alone).
  Never the package's own folder.

  Args:
    exclude: a directory left out of the list (the cache directory in use).
    create: create the folders (else only those that exist are listed).

  Returns:
    The folders that exist (or were created) and may be used, best first.
  """
  skip = Path(exclude).expanduser().absolute() if exclude else None
  out = []
  for path, private in ((cache_root() / "numba", None), (_private_tmp_dir() / "numba",
                                                         _private_tmp_dir())):
    if skip is not None and path.absolute() == skip:
      continue
    if private is not None and not _private(private, create):
      continue
    try:
      if create:
        path.mkdir(parents=True, exist_ok=True)
      if path.is_dir():
        out.append(path)
    except OSError:
      continue
  return out


def configure_numba_cache() -> str | None:
  """Point numba's on-disk cache at `numba_cache_dir()` unless `NUMBA_CACHE_DIR` is set.

  Sets the environment variable only (numba reads it when it is imported; if numba was imported
  already, its configuration is reloaded). When the directory cannot be created, the first of
  `numba_fallback_dirs()` that can is set instead; when none can, the directory is set all the
  same (lrf_jax's kernels then compile in memory, `kernel_cache`, rather than into the
  package's own folder, numba's default).

  Returns:
    The directory now set, or None when the user's setting stays.
  """
  if os.environ.get(NUMBA_ENV_VAR):
    return None
  path = numba_cache_dir()
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError:
    path = next(iter(numba_fallback_dirs(path, create=True)), path)
  os.environ[NUMBA_ENV_VAR] = str(path)
  if "numba" in sys.modules:
    from numba.core import config
    config.reload_config()
  return str(path)


def enable(directory: str | os.PathLike | None = None) -> Path | None:
  """Turn on JAX's persistent compilation cache in `directory` (default: `cache_dir()`).

  Every compiled function is stored, however short its compilation. A directory that cannot be
  created leaves the cache off (the program still runs, only slower to start). Also turns on
  `announce_compiles()`.

  JAX is not imported here: when it is not imported yet, the settings wait and are applied
  when the package first uses it (`jax_imported`; a run on the host kernels never imports it).

  Returns:
    The directory in use, or None when the cache stays off.
  """
  announce_compiles()
  path = Path(directory).expanduser() if directory is not None else cache_dir()
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError:
    return None
  _state["jax_cache"] = str(path)
  if "jax" in sys.modules:
    _configure_jax()
  return path


def _configure_jax() -> None:
  if _state["jax_cache"] is None:
    return
  import jax  # pylint: disable=import-outside-toplevel

  jax.config.update("jax_compilation_cache_dir", _state["jax_cache"])
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
  jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def jax_imported() -> None:
  """Apply the package's JAX settings now that JAX is imported (called once, by `lrf_jax._jax`
  when a module first uses JAX): the persistent cache of `enable()`, if it was called, and the
  compile notice of `announce_compiles()`."""
  announce_compiles()
  _configure_jax()


def _announce(stream: TextIO | None = None) -> None:
  """Print the notice, once per process: numba compiles kernels from several threads (a
  parallel kernel's gufuncs, lrf-batch's local items), so the test and the set are one step."""
  with _LOCK:
    if _state["announced"]:
      return
    _state["announced"] = True
  out = stream or _state["stream"] or sys.stderr
  print(NOTICE.format(where=cache_locations()), file=out, flush=True)


# numba compiles running in this process (any thread), and a Ctrl-C that arrived during one
# (`defer_interrupt`): LLVM calls back into Python while it compiles, and a KeyboardInterrupt
# raised in such a callback is dropped by Python and leaves numba without its object code (a
# RuntimeError, or a crash later), so a Ctrl-C waits for the compile to end.
_COMPILES: dict[str, Any] = {"depth": 0, "pending": False}
_COMPILES_LOCK = threading.Lock()


def numba_compiling() -> bool:
  """Whether numba is compiling a function in this process now (from the "numba:compile"
  events, once `announce_compiles` hooked them)."""
  return _COMPILES["depth"] > 0


def defer_interrupt() -> None:
  """Send SIGINT again as soon as the numba compiles running now have ended (the Ctrl-C
  handler of `lrf_jax.cli.interrupt` calls this instead of raising inside a compile)."""
  with _COMPILES_LOCK:
    _COMPILES["pending"] = True
    if _COMPILES["depth"] > 0:
      return
    _COMPILES["pending"] = False
  _resend_interrupt()


def _resend_interrupt() -> None:
  import signal
  os.kill(os.getpid(), signal.SIGINT)


def _numba_listener() -> Any:
  from numba.core import event

  class _CompileNotice(event.Listener):
    """Announces the first compile of an lrf_jax kernel (numba fires "numba:compile" only on
    a cache miss), and counts the compiles running (`numba_compiling`): a Ctrl-C deferred
    during one is sent again when the last ends."""

    def on_start(self, ev: Any) -> None:
      with _COMPILES_LOCK:
        _COMPILES["depth"] += 1
      dispatcher = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
      module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
      if module.startswith("lrf_jax"):
        _announce()

    def on_end(self, ev: Any) -> None:
      with _COMPILES_LOCK:
        _COMPILES["depth"] = max(_COMPILES["depth"] - 1, 0)
        resend = _COMPILES["pending"] and _COMPILES["depth"] == 0
        if resend:
          _COMPILES["pending"] = False
      if resend:
        _resend_interrupt()

  return _CompileNotice()


def _on_jax_event(event: str, **kwargs: Any) -> None:
  if event == "/jax/compilation_cache/cache_misses":
    _announce()


def _on_jax_duration(event: str, duration: float, **kwargs: Any) -> None:
  if event == "/jax/core/compile/backend_compile_duration" and \
      duration >= _JAX_COMPILE_NOTICE_SECS:
    _announce()


def announce_compiles(stream: TextIO | None = None) -> None:
  """Say once per process, on stderr (or `stream`), when lrf_jax code is being compiled.

  Hooks numba's compile event (fired on a cache miss only) and `kernel_cache`'s wait for a
  worker compiling a kernel when numba is imported, and JAX's monitoring events when JAX is
  imported; idempotent, cheap, and it imports neither library.
  With numba it also installs lrf_jax's cache locator (`kernel_cache.install`): every
  module that defines a cached kernel calls this first.
  """
  if stream is not None:
    _state["stream"] = stream
  if _state["numba"] is None and "numba" in sys.modules:
    from numba.core import event

    from lrf_jax import kernel_cache
    kernel_cache.install(numba_fallback_dirs, on_wait=_announce)
    _state["numba"] = _numba_listener()
    event.register("numba:compile", _state["numba"])
  if not _state["jax"] and "jax" in sys.modules:
    from jax import monitoring
    monitoring.register_event_listener(_on_jax_event)
    # jax passes the duration positionally; its listener protocol names it `duration_secs`
    monitoring.register_event_duration_secs_listener(_on_jax_duration)  # type: ignore[arg-type]
    _state["jax"] = True
