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
`error:` line. `output_problem` and `same_file` are the checks a program makes on its output
paths before doing any work.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Any
from collections.abc import Iterable, Iterator

__all__ = ["WriteError", "append_line", "atomic_path", "atomic_write", "output_problem",
           "same_file", "save_figure", "write_bytes", "write_text"]


class WriteError(OSError):
  """A file could not be written; `str()` is "could not write PATH: REASON"."""

  def __init__(self, path: str | os.PathLike, cause: BaseException):
    reason = getattr(cause, "strerror", None) or str(cause) or type(cause).__name__
    super().__init__(getattr(cause, "errno", None), reason, str(path))
    self.path = Path(path)
    self.reason = reason

  def __str__(self) -> str:
    return f"could not write {self.path}: {self.reason}"


def _target(path: str | os.PathLike) -> Path:
  """`path`, or the file a symbolic link at `path` points to (the link itself is kept)."""
  p = Path(path).expanduser()
  return Path(os.path.realpath(p)) if p.is_symlink() else p


def _file_mode(target: Path) -> int:
  """Permission bits for the new file: the old file's, else what `open` would give."""
  try:
    return target.stat().st_mode & 0o7777
  except OSError:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
  """Yield a temporary file name beside `path`; on success it is fsynced and renamed to `path`.

  Args:
    path: the file to (re)place. Its folder must exist.

  Yields:
    The temporary file's path (same folder, same suffix as `path`), for the caller to write.

  Raises:
    WriteError: `path` is a folder, or creating, writing or renaming the file failed with an
      `OSError` (the message names `path` and the reason). `path` is then unchanged and the
      temporary file removed; any other exception propagates after the same clean-up.
  """
  target = _target(path)
  if target.is_dir():
    raise WriteError(target, IsADirectoryError(21, "is a folder, expected a file path"))
  try:
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{target.suffix}",
                                    dir=target.parent)
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
    WriteError: the write failed (e.g. a full disk); the file is truncated back to its previous
      length, so it holds exactly the lines it held before.
  """
  target = _target(path)
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
  links, links to folders) when both exist."""
  pa, pb = Path(a).expanduser(), Path(b).expanduser()
  if pa.resolve() == pb.resolve():
    return True
  try:
    return os.path.samefile(pa, pb)
  except OSError:
    return False


def output_problem(path: str | os.PathLike, option: str,
                   inputs: Iterable[tuple[str, str | os.PathLike]] = ()) -> str | None:
  """What is wrong with writing the file `path` (None: fine); checked before any work.

  Args:
    path: the output file.
    option: how the user named it (e.g. "--out"), to start the message with.
    inputs: (name, path) of the files the program reads; `path` may not be one of them.

  Returns:
    A message naming `option`: `path` is one of the inputs, a folder, in a folder that does not
    exist or is not writable; or None.
  """
  p = Path(path).expanduser()
  for name, src in inputs:
    if src is not None and same_file(p, src):
      return (f"{option}: {path} is the input {name} ({src}); refusing to overwrite it, pick "
              "another output path")
  if p.is_dir():
    return f"{option}: {path} is a folder; expected a file path"
  parent = p.resolve().parent
  if not parent.is_dir():
    return f"{option}: the folder {parent} does not exist (create it, or pick another path)"
  if not os.access(parent, os.W_OK | os.X_OK):
    return f"{option}: the folder {parent} is not writable"
  return None


def save_figure(fig, path: str | os.PathLike, **savefig_kw) -> Path:
  """`fig.savefig` into a temporary file renamed to `path` (see `atomic_path`); the format is
  `path`'s suffix. Returns `path`."""
  with atomic_path(path) as tmp:
    fig.savefig(tmp, **savefig_kw)
  return Path(path)
