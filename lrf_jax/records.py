"""Records of finished work, kept between runs: what a resumable job (`lrf_jax.batch`'s items,
`lrf_jax.multiway`'s pairs) reads back instead of computing again.

A record is one JSON object in one file, written atomically. It is found by a key, the sha256
of everything its result depends on (the inputs' content, the options, the method's
parameters), never by where its inputs sit in a run: the same inputs in another order, another
list or another folder find the same record. Each record carries the lrf_jax version that
computed it (`version`); a record of another version is not a result of this one (`is_current`)
unless the caller keeps it on purpose. One job at a time writes a folder (`JobLock`).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from lrf_jax.defaults import WEIGHTS_KINDS
from lrf_jax.io import atomic

__all__ = ["FolderInUse", "JobLock", "array_hash", "canonical", "content_key", "is_current",
           "params_hash", "read_record", "version", "write_record"]


def version() -> str:
  """The installed lrf_jax's version (pyproject.toml's `version`, the one place it is written);
  "0+unknown" when lrf_jax runs from a source tree that was never installed."""
  from importlib import metadata
  try:
    return metadata.version("lrf_jax")
  except metadata.PackageNotFoundError:
    return "0+unknown"


def canonical(value: Any) -> str:
  """`value` as JSON with sorted keys, arrays and numpy scalars as lists and numbers: equal
  values give equal text."""
  return json.dumps(value, sort_keys=True, default=lambda v: np.asarray(v).tolist())


def weights_hash(weights: Any) -> str:
  """What a record's key holds of the `weights` option: "" for a shipped kind ("objects",
  "rooms", "streets": part of the version a record carries), the sha256 of a parameter file's
  bytes for a path (a file retrained in place makes new records), "" where it cannot be read
  (the run reports that)."""
  if weights is None or weights in WEIGHTS_KINDS:
    return ""
  try:
    return hashlib.sha256(Path(weights).read_bytes()).hexdigest()
  except (OSError, TypeError):
    return ""


def content_key(*parts: str) -> str:
  """The sha256 (hex) of `parts` joined by "|": a record's key."""
  return hashlib.sha256("|".join(parts).encode()).hexdigest()


def array_hash(*arrays: Any) -> str:
  """sha256 (hex) of arrays' dtypes, shapes and bytes, in order (None hashes as an empty
  array): the content of a scan (points, faces, viewpoint)."""
  h = hashlib.sha256()
  for arr in arrays:
    a = np.ascontiguousarray(np.zeros(0) if arr is None else np.asarray(arr))
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
  return h.hexdigest()


def params_hash(params: Any) -> str:
  """sha256 (hex) of a parameter tree's leaves, or "shipped" for None (the shipped weights)."""
  if params is None:
    return "shipped"
  import jax
  return array_hash(*jax.tree_util.tree_leaves(params))


def read_record(path: str | os.PathLike) -> dict[str, Any] | None:
  """The record at `path`, or None when there is none or it is not a JSON object (a damaged
  record costs its work again, not the job)."""
  try:
    rec = json.loads(Path(path).read_text())
  except (OSError, ValueError):
    return None
  return rec if isinstance(rec, dict) else None


def write_record(path: str | os.PathLike, record: dict[str, Any]) -> None:
  """Write `record` to `path` atomically, its `version` set to this lrf_jax's unless the record
  names the version that computed it (a worker's)."""
  atomic.write_text(path, canonical({"version": version(), **record}))


def is_current(record: dict[str, Any], keep_other_versions: bool = False) -> bool:
  """Whether `record` stands as a result of this lrf_jax: computed by this version, or by any
  when `keep_other_versions`."""
  return keep_other_versions or record.get("version") == version()


# --- one job per folder -----------------------------------------------------------------------

try:  # POSIX file locks, released by the system when their process ends
  import fcntl as _fcntl
except ImportError:  # Windows
  _fcntl = None  # type: ignore[assignment]

class FolderInUse(ValueError):
  """Another job holds the folder's lock (the message names its host, pid and command)."""


def _command_line() -> str:
  """This process's command line (the program's name, then its arguments), for messages."""
  import shlex
  import sys
  if not sys.argv or not sys.argv[0]:
    return sys.executable
  return shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])


def _proc_stat(pid: int) -> list[str] | None:
  """The fields of /proc/<pid>/stat after the command's name (Linux), or None."""
  try:
    return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
  except OSError:
    return None


def _process_start(pid: int) -> str | None:
  """A token of when process `pid` started (Linux: /proc's start time in clock ticks), or None
  where it cannot be read: tells a live holder from a new process that reuses its pid."""
  stat = _proc_stat(pid)
  return None if stat is None else stat[19]


def _alive(pid: int, start: str | None) -> bool:
  """Whether the process `pid` that started at `start` still runs: not gone, not a zombie (a
  killed job whose parent has not collected it yet), not a later process with its pid."""
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # another user's process: it exists
    pass
  stat = _proc_stat(pid)
  if stat is not None and stat[0] in ("Z", "X"):
    return False
  now = None if stat is None else stat[19]
  return start is None or now is None or now == start


class JobLock:
  """The lock of a job's folder: the file `path` holds the holder's host, pid, process start and
  command. On POSIX the holder also holds an exclusive `lockf` on it, which the system releases
  when the holder ends in any way; elsewhere the file is created exclusively (`_create`).

  `acquire()` takes it or raises `FolderInUse` naming the holder. A lock left by a dead process
  of this host (its pid gone, or reused by a process that started later) is taken over with a
  note on stderr; a lock of another host (a shared file system) is taken over only with
  `force`. `release()` removes it if this process still holds it, and the folders `acquire`
  made for it if the job left them empty. Use as a context manager.
  """

  def __init__(self, path: str | os.PathLike, command: str | None = None, *,
               force: bool = False, folder: str | os.PathLike | None = None):
    self.path = Path(path)
    self.force = force
    self.folder = str(self.path.parent if folder is None else folder)  # named in messages
    import socket
    self.me = dict(host=socket.gethostname(), pid=os.getpid(), start=_process_start(os.getpid()),
                   command=command if command is not None else _command_line())
    self.held = False
    self.made: list[Path] = []
    self.fd: int | None = None

  def _holder(self) -> dict[str, Any] | None:
    rec = read_record(self.path)
    return rec if rec is not None and isinstance(rec.get("pid"), int) else None

  def _describe(self, h: dict[str, Any]) -> str:
    return (f"{self.folder} is in use by another job (host {h.get('host')}, pid "
            f"{h.get('pid')}, command: {h.get('command')})")

  def _create(self) -> bool:
    """Create the lock whole or not at all: its content is written to a temporary file first,
    then hard-linked to the lock's name (atomic, and refused when the name exists), so that no
    reader ever sees a lock half written; where the file system has no hard links, an exclusive
    create."""
    tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(self.me))
    try:
      os.link(tmp, self.path)
      return True
    except FileExistsError:
      return False
    except OSError:  # no hard links here
      try:
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
      except FileExistsError:
        return False
      with os.fdopen(fd, "w") as f:
        f.write(json.dumps(self.me))
      return True
    finally:
      tmp.unlink(missing_ok=True)

  def acquire(self) -> JobLock:
    """Take the lock, or raise `FolderInUse` naming its holder (class docstring)."""
    missing = [d for d in (self.path.parent, *self.path.parent.parents) if not d.exists()]
    self.path.parent.mkdir(parents=True, exist_ok=True)
    self.made = missing  # removed again on release when the job left them empty
    for _ in range(3):  # a lock released and made anew between our steps: try again
      if (self._take_os_lock() if _fcntl is not None else self._take_file_lock()):
        self.held = True
        return self
    raise FolderInUse(f"{self.folder}: could not take the job lock {self.path}")

  def _judge(self, h: dict[str, Any] | None, text: str) -> None:
    """Raise `FolderInUse` unless the lock's content `text` (holder `h`) may be taken over: no
    holder, a damaged lock, or a holder of this host that no longer runs (of another host: only
    with `force`); print the note of a takeover."""
    import socket
    import sys
    if not text.strip():
      return
    if h is None:
      print(f"note: {self.path}: not a readable lock (damaged); taking it over", file=sys.stderr)
      return
    same_host = h.get("host") == socket.gethostname()
    if same_host and _alive(int(h["pid"]), h.get("start")):
      raise FolderInUse(self._describe(h))
    if not same_host and not self.force:
      raise FolderInUse(self._describe(h) + "; if that job is gone, run again with --force "
                        "(the folder is on a file system shared with that host)")
    print(f"note: {self._describe(h).replace('is in use by', 'was locked by')}, which is no "
          "longer running; taking its lock over", file=sys.stderr)

  def _take_os_lock(self) -> bool:
    """POSIX: an exclusive `lockf` on the lock file, which the system releases when the holder
    ends in any way (SIGKILL too); the content names the holder for messages and for a holder
    on a file system that does not carry locks. False: the file changed under us, try again."""
    assert _fcntl is not None
    try:
      fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
      if self.path.exists() and not self.path.is_file():
        raise FolderInUse(f"{self.path}: expected this job folder's lock file, found "
                          "something else; remove it if no job is running") from None
      raise
    try:
      _fcntl.lockf(fd, _fcntl.LOCK_EX | _fcntl.LOCK_NB)
    except OSError:
      os.close(fd)
      h = self._holder()
      raise FolderInUse(self._describe(h) if h is not None
                        else f"{self.folder} is in use by another job") from None
    try:
      if os.stat(self.path).st_ino != os.fstat(fd).st_ino:  # released and made anew meanwhile
        os.close(fd)
        return False
    except FileNotFoundError:
      os.close(fd)
      return False
    text = Path(self.path).read_text(errors="replace")
    try:
      self._judge(self._holder(), text)
    except BaseException:
      os.close(fd)
      raise
    data = json.dumps(self.me).encode()
    os.ftruncate(fd, 0)
    os.pwrite(fd, data, 0)
    os.fsync(fd)
    self.fd = fd
    return True

  def _take_file_lock(self) -> bool:
    """Where `lockf` does not exist: the lock file created whole (`_create`) or judged by its
    content and removed (`_judge`)."""
    if self._create():
      return True
    if not self.path.is_file():
      if not self.path.exists() and not self.path.is_symlink():
        return False  # released between our two looks
      raise FolderInUse(f"{self.path}: expected this job folder's lock file, found "
                        "something else; remove it if no job is running")
    self._judge(self._holder(), self.path.read_text(errors="replace"))
    self.path.unlink(missing_ok=True)
    return False

  def release(self) -> None:
    """Remove the lock if this process holds it, then the folders `acquire` made and the job
    left empty."""
    if not self.held:
      return
    if self.fd is not None:
      try:
        if os.stat(self.path).st_ino == os.fstat(self.fd).st_ino:
          self.path.unlink()  # before the lock goes: a waiting job then finds no file
      except OSError:
        pass
      os.close(self.fd)
      self.fd = None
    else:
      h = self._holder()
      if h is not None and h.get("pid") == self.me["pid"] and h.get("host") == self.me["host"]:
        self.path.unlink(missing_ok=True)
    self.held = False
    for d in self.made:  # deepest first: folders the lock made and the job left empty
      try:
        d.rmdir()
      except OSError:
        break

  def __enter__(self) -> JobLock:
    return self.acquire()

  def __exit__(self, *exc: Any) -> None:
    self.release()
