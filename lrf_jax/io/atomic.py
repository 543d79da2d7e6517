"""Writing files so that a failed or interrupted write never destroys the previous file.

Every file the project writes (frames .npz, transforms, figures, parameters, configs, metrics,
evaluation tables) goes through one of these helpers:

* `atomic_write(path, mode)`: a context manager giving an open file object. The data goes to a
  temporary file in the same folder (`.NAME.XXXX.tmp`), which is flushed, fsynced and renamed
  over `path` (`os.replace`, atomic on POSIX) only when the block ends without an exception. On
  any exception (a full disk, Ctrl-C, a bug in the writer) the temporary file is removed and
  `path` is untouched; after SIGKILL, the old `path` is intact and a stale `.NAME.XXXX.tmp` may be
  left beside it.
* `atomic_path(path)`: the same, for writers that want a file name (`save_params`): it yields
  the temporary path, which keeps `path`'s suffix; `save_figure(fig, path)` is matplotlib's
  `savefig` through it. `write_text` / `write_bytes` write a whole file at once.
* `append_line(path, text)`: one record appended to a log (`metrics.jsonl`) with a single write,
  flush and fsync; if the write fails the file is truncated back to its previous length, so the
  earlier records are intact. A process killed during the write can leave a torn last line,
  which readers of such logs skip.

A write that fails with an `OSError` raises `WriteError` ("could not write PATH: REASON", e.g.
"No space left on device"), an `OSError` itself, which the command-line programs print as one
`error:` line. Only a regular file or a new name is ever replaced: a path naming a FIFO, a
device (such as /dev/null), a socket or a folder, or whose name is longer than `NAME_MAX`
bytes, or that is (or goes through) a symbolic link loop, raises `OutputPathError` (a
`WriteError` and a `ValueError`) before anything is written; the rename would otherwise put a
regular file in the place of the device or the link. `output_problem`, `path_problem`,
`loop_problem` and `same_file` are the checks a program makes on its output paths before doing
any work.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
import threading
from pathlib import Path
from typing import IO, Any
from collections.abc import Iterable, Iterator

__all__ = ["NAME_MAX", "OutputPathError", "OutputProblem", "WriteError", "append_line",
           "atomic_path", "atomic_write", "file_kind", "loop_problem", "output_problem",
           "path_problem", "same_file", "save_figure", "write_bytes", "write_text"]

# The longest file name (one path component), in bytes, on the usual file systems (ext4, XFS,
# btrfs, tmpfs, APFS); a longer one fails with ENAMETOOLONG.
NAME_MAX = 255
# The longest path a system call takes, in bytes (Linux's PATH_MAX, its terminating NUL
# included).
PATH_MAX = 4096


class WriteError(OSError):
  """A file could not be written; `str()` is "could not write PATH: REASON"."""

  def __init__(self, path: str | os.PathLike, cause: BaseException):
    reason = getattr(cause, "strerror", None) or str(cause) or type(cause).__name__
    super().__init__(getattr(cause, "errno", None), reason, str(path))
    self.path = Path(path)
    self.reason = reason

  def __str__(self) -> str:
    return f"could not write {self.path}: {self.reason}"


class OutputPathError(WriteError, ValueError):
  """The path cannot be written as a file: it names a FIFO, a device, a socket or a folder, or
  its name is too long; raised before anything is written. Both a `WriteError` (what the
  programs print as an `error:` line) and a `ValueError` (a bad argument), as
  `io.UnsupportedOperation` is both an `OSError` and a `ValueError`."""

  def __init__(self, path: str | os.PathLike, reason: str, code: int = errno.EINVAL):
    super().__init__(path, OSError(code, reason))


def path_problem(path: str | os.PathLike) -> str | None:
  """What makes `path` impossible as a file name, without touching the disk (None: fine): a NUL
  character, a path component longer than `NAME_MAX` bytes, or a path of `PATH_MAX` bytes or
  more. The message does not repeat the path."""
  text = os.fspath(path)
  if "\0" in text:
    return "holds a NUL character"
  raw = os.fsencode(text)
  if len(raw) >= PATH_MAX:
    return f"is {len(raw)} bytes long; a path must be shorter than {PATH_MAX} bytes"
  for part in raw.split(b"/"):
    if len(part) > NAME_MAX:
      shown = os.fsdecode(part[:24]) + "..."
      return (f"has a name ({shown!r}) of {len(part)} bytes; a file or folder name may be at "
              f"most {NAME_MAX} bytes")
  return None


def _loops(path: str | os.PathLike) -> bool:
  """Whether looking `path` up fails with ELOOP (a symbolic link on it leads back to itself)."""
  try:
    os.stat(path)
  except OSError as e:
    return e.errno == errno.ELOOP
  except ValueError:  # a NUL character: `path_problem` says so
    return False
  return False


def loop_problem(path: str | os.PathLike) -> str | None:
  """What is wrong with `path` when looking it up fails with ELOOP (None otherwise): "is a
  symbolic link loop (...)" when `path` itself is a link that leads back to itself, "goes
  through a symbolic link loop (...)" when a folder on it does. The message does not repeat the
  path."""
  p = Path(path).expanduser()
  if not _loops(p):
    return None
  where = "goes through" if p.parent != p and _loops(p.parent) else "is"
  return f"{where} a symbolic link loop (ELOOP: {os.strerror(errno.ELOOP).lower()})"


_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISDIR, "a folder"))


def file_kind(path: str | os.PathLike) -> str | None:
  """What `path` (symbolic links followed) is when it exists and is not a regular file: "a
  folder", "a FIFO (named pipe)", "a character device", "a block device", "a socket" or "not
  a regular file"; None for a regular file or a name that does not exist (or cannot be looked
  at: the write then reports why)."""
  try:
    mode = os.stat(Path(path).expanduser()).st_mode
  except (OSError, ValueError):
    return None
  if stat.S_ISREG(mode):
    return None
  return next((what for test, what in _KINDS if test(mode)), "not a regular file")


def _check_writable_name(target: Path) -> None:
  """Raise `OutputPathError` unless `target` is a regular file or a new name."""
  problem = path_problem(target)
  if problem:
    raise OutputPathError(target, problem, errno.ENAMETOOLONG)
  problem = loop_problem(target)
  if problem:
    raise OutputPathError(target, f"{problem}; expected a regular file or a new name",
                          errno.ELOOP)
  kind = file_kind(target)
  if kind == "a folder":
    raise OutputPathError(target, "is a folder, expected a file path", errno.EISDIR)
  if kind:
    raise OutputPathError(target, f"is {kind}, not a regular file; expected a regular file or "
                                  "a new name")


def _target(path: str | os.PathLike) -> Path:
  """`path`, or the file a symbolic link at `path` points to (the link itself is kept); `path`
  itself when it is a symbolic link loop (`_check_writable_name` refuses it, naming it)."""
  p = Path(path).expanduser()
  try:
    return Path(os.path.realpath(p)) if p.is_symlink() and not _loops(p) else p
  except (OSError, ValueError):  # a name too long to look at: `_check_writable_name` says so
    return p


def _file_mode(target: Path) -> int:
  """Permission bits for the new file: the old file's, else what `open` would give."""
  try:
    return target.stat().st_mode & 0o7777
  except OSError:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def _temporary_affixes(name: str) -> tuple[str, str]:
  """mkstemp's prefix and suffix for a temporary file beside the file `name`: ".NAME." and
  ".tmpSUFFIX" (the suffix kept, so that writers that read the format from it still can),
  NAME cut so that the whole name (8 random characters included) stays within `NAME_MAX`
  bytes; a suffix longer than 16 bytes is not kept."""
  suffix = Path(name).suffix
  if len(os.fsencode(suffix)) > 16:
    suffix = ""
  suffix = f".tmp{suffix}"
  room = NAME_MAX - 8 - 2 - len(os.fsencode(suffix))
  head = name
  while len(os.fsencode(head)) > room:
    head = head[:-1]
  return f".{head}.", suffix


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
  """Yield a temporary file name beside `path`; on success it is fsynced and renamed to `path`.

  Args:
    path: the file to (re)place. Its folder must exist.

  Yields:
    The temporary file's path (same folder, same suffix as `path`), for the caller to write.

  Raises:
    OutputPathError: `path` (a symbolic link: the file it points to) is a folder, a FIFO, a
      device or a socket, or its name is too long (`path_problem`); nothing is written.
    WriteError: creating, writing or renaming the file failed with an `OSError` (the message
      names `path` and the reason). `path` is then unchanged and the temporary file removed;
      any other exception propagates after the same clean-up.
  """
  target = _target(path)
  _check_writable_name(target)
  prefix, suffix = _temporary_affixes(target.name)
  try:
    fd, tmp_name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=target.parent)
  except OSError as e:
    raise WriteError(target, e) from e
  os.close(fd)
  tmp = Path(tmp_name)
  try:
    yield tmp
    with open(tmp, "rb+") as f:
      os.fsync(f.fileno())
    os.chmod(tmp, _file_mode(target))
    os.replace(tmp, target)
  except BaseException as e:
    with contextlib.suppress(OSError):
      tmp.unlink()
    if isinstance(e, OSError) and not isinstance(e, WriteError):
      raise WriteError(target, e) from e
    raise
  _sync_folder(target.parent)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb", *,
                 encoding: str | None = None) -> Iterator[IO]:
  """Open a temporary file beside `path` for writing; replace `path` with it on success.

  Args:
    path: the file to (re)place. Its folder must exist.
    mode: "wb" (bytes) or "w" (text).
    encoding: the text encoding for mode "w" (default UTF-8).

  Yields:
    The open file object.

  Raises:
    ValueError: `mode` is not "w" or "wb".
    WriteError: as `atomic_path`; `path` is then unchanged and no temporary file remains.
  """
  if mode not in ("w", "wb"):
    raise ValueError(f"atomic_write: mode: expected 'w' or 'wb', got {mode!r}")
  with atomic_path(path) as tmp:
    kw: dict[str, Any] = {"encoding": encoding or "utf-8"} if mode == "w" else {}
    with open(tmp, mode, **kw) as f:
      yield f
      f.flush()


def write_text(path: str | os.PathLike, text: str) -> Path:
  """Atomically write `text` (UTF-8) to `path`; returns `path` (see `atomic_write`)."""
  with atomic_write(path, "w") as f:
    f.write(text)
  return Path(path)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
  """Atomically write `data` to `path`; returns `path` (see `atomic_write`)."""
  with atomic_write(path, "wb") as f:
    f.write(data)
  return Path(path)


def append_line(path: str | os.PathLike, text: str) -> None:
  """Append `text` plus a newline to `path` (created if missing) with one write and an fsync.

  Raises:
    OutputPathError: `path` is not a regular file or a new name (`atomic_path`).
    WriteError: the write failed (e.g. a full disk); the file is truncated back to its previous
      length, so it holds exactly the lines it held before.
  """
  target = _target(path)
  _check_writable_name(target)
  data = (text.rstrip("\n") + "\n").encode()
  try:
    f = open(target, "ab")
  except OSError as e:
    raise WriteError(target, e) from e
  with f:
    size = f.seek(0, os.SEEK_END)
    try:
      f.write(data)
      f.flush()
      os.fsync(f.fileno())
    except BaseException as e:
      with contextlib.suppress(OSError):
        f.truncate(size)
      if isinstance(e, OSError):
        raise WriteError(target, e) from e
      raise


def _sync_folder(folder: Path) -> None:
  """fsync a folder so that a rename in it survives a power cut (best effort)."""
  with contextlib.suppress(OSError):
    fd = os.open(folder, os.O_RDONLY)
    try:
      os.fsync(fd)
    finally:
      os.close(fd)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
  """True when `a` and `b` are one file: the same resolved path, or `os.path.samefile` (hard
  links, links to folders) when both exist. A symbolic link loop is the same file only as
  itself (it resolves to no file)."""
  pa, pb = Path(a).expanduser(), Path(b).expanduser()
  if os.path.realpath(pa) == os.path.realpath(pb):  # Path.resolve raises on a symbolic link loop
    return True
  try:
    return os.path.samefile(pa, pb)
  except OSError:
    return False


class OutputProblem(str):
  """`output_problem`'s message. `io_error` is True when the path is fine but the system will
  not let it be written (its folder is not writable: a read-only file system, permissions), as
  opposed to a wrong path (the programs exit with different codes)."""

  io_error: bool = False

  def __new__(cls, text: str, io_error: bool = False) -> OutputProblem:
    made = super().__new__(cls, text)
    made.io_error = io_error
    return made


def output_problem(path: str | os.PathLike, option: str,
                   inputs: Iterable[tuple[str, str | os.PathLike]] = ()) -> str | None:
  """What is wrong with writing the file `path` (None: fine); checked before any work.

  Args:
    path: the output file.
    option: how the user named it (e.g. "--out"), to start the message with.
    inputs: (name, path) of the files the program reads; `path` may not be one of them.

  Returns:
    A message naming `option`: `path` is too long a name (`path_problem`), a symbolic link loop
    or goes through one (`loop_problem`), one of the inputs, a folder, a FIFO, a device or a
    socket (`file_kind`: only a regular file or a new name is replaced), in a folder that does
    not exist, or is not writable (an `OutputProblem` whose `io_error` is True); or None.
  """
  problem = path_problem(path)
  if problem:
    return f"{option}: {path} {problem}"
  problem = loop_problem(path)
  if problem:
    return f"{option}: {path} {problem}; expected a regular file or a new name"
  p = Path(path).expanduser()
  for name, src in inputs:
    if src is not None and same_file(p, src):
      return (f"{option}: {path} is the input {name} ({src}); refusing to overwrite it, pick "
              "another output path")
  kind = file_kind(p)
  if kind == "a folder":
    return f"{option}: {path} is a folder; expected a file path"
  if kind:
    return f"{option}: {path} is {kind}; expected a regular file or a new name"
  parent = Path(os.path.realpath(p)).parent
  if not parent.is_dir():
    return f"{option}: the folder {parent} does not exist (create it, or pick another path)"
  if not os.access(parent, os.W_OK | os.X_OK):
    return OutputProblem(f"{option}: the folder {parent} is not writable", io_error=True)
  return None


def save_figure(fig, path: str | os.PathLike, **savefig_kw) -> Path:
  """`fig.savefig` into a temporary file renamed to `path` (see `atomic_path`); the format is
  `path`'s suffix. Returns `path`."""
  with atomic_path(path) as tmp:
    fig.savefig(tmp, **savefig_kw)
  return Path(path)


# Set by the Ctrl-C handlers of a running `lrf_jax.cli.interrupt.interruptible` program (cleared
# when one starts): a Ctrl-C arrived, whether or not its KeyboardInterrupt reached the code.
CTRL_C_RECEIVED = threading.Event()


def caused_by_interrupt(error: BaseException) -> bool:
  """Whether `error` is a Ctrl-C's consequence: a KeyboardInterrupt is in its chain of causes
  (Ctrl-C inside a numba dispatcher surfaces as a `SystemError`, "returned a result with an
  exception set", raised from the KeyboardInterrupt), or a command-line program received a
  Ctrl-C before it (`CTRL_C_RECEIVED`: a KeyboardInterrupt raised inside a C callback is
  dropped by Python, and the library then fails for want of the callback's result, as numba's
  RuntimeError "no compiled object yet" after LLVM's object-code hook)."""
  if CTRL_C_RECEIVED.is_set():
    return True
  seen: set[int] = set()
  e: BaseException | None = error
  while e is not None and id(e) not in seen:
    if isinstance(e, KeyboardInterrupt):
      return True
    seen.add(id(e))
    e = e.__cause__ or e.__context__
  return False
