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

class FolderInUse(ValueError):
  """Another job holds the folder's lock (the message names its host, pid and command)."""


def _process_start(pid: int) -> str | None:
  """A token of when process `pid` started (Linux: /proc's start time in clock ticks), or None
  where it cannot be read: tells a live holder from a new process that reuses its pid."""
  try:
    stat = Path(f"/proc/{pid}/stat").read_text()
  except OSError:
    return None
  return stat.rpartition(")")[2].split()[19]


def _alive(pid: int, start: str | None) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:  # another user's process: it exists
    pass
  now = _process_start(pid)
  return start is None or now is None or now == start


class JobLock:
  """The lock of a job's folder: the file `path` holds the holder's host, pid, process start and
  command; created exclusively (O_EXCL), so two jobs never both hold it.

  `acquire()` takes it or raises `FolderInUse` naming the holder. A lock left by a dead process
  of this host (its pid gone, or reused by a process that started later) is taken over with a
  note on stderr; a lock of another host (a shared file system) is taken over only with
  `force`. `release()` removes it if this process still holds it, and the folders `acquire`
  made for it if the job left them empty. Use as a context manager.
  """

  def __init__(self, path: str | os.PathLike, command: str, *, force: bool = False,
               folder: str | os.PathLike | None = None):
    self.path = Path(path)
    self.force = force
    self.folder = str(self.path.parent if folder is None else folder)  # named in messages
    import socket
    self.me = dict(host=socket.gethostname(), pid=os.getpid(), start=_process_start(os.getpid()),
                   command=command)
    self.held = False
    self.made: list[Path] = []

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
    import socket
    import sys
    missing = [d for d in (self.path.parent, *self.path.parent.parents) if not d.exists()]
    self.path.parent.mkdir(parents=True, exist_ok=True)
    self.made = missing  # removed again on release when the job left them empty
    for _ in range(3):  # a lock removed or taken over between our reads: try again
      if self._create():
        self.held = True
        return self
      if not self.path.is_file():
        if not self.path.exists() and not self.path.is_symlink():
          continue  # released between our two looks: try again
        raise FolderInUse(f"{self.path}: expected this job folder's lock file, found "
                          "something else; remove it if no job is running")
      h = self._holder()
      if h is None:  # not a lock of ours (written whole, never half): a damaged one
        print(f"note: {self.path}: not a readable lock (damaged); taking it over",
              file=sys.stderr)
        self.path.unlink(missing_ok=True)
        continue
      same_host = h.get("host") == socket.gethostname()
      if same_host and _alive(int(h["pid"]), h.get("start")):
        raise FolderInUse(self._describe(h))
      if not same_host and not self.force:
        raise FolderInUse(self._describe(h) + "; if that job is gone, run again with --force "
                          "(the folder is on a file system shared with that host)")
      print(f"note: {self._describe(h).replace('is in use by', 'was locked by')}, which is no "
            "longer running; taking its lock over", file=sys.stderr)
      self.path.unlink(missing_ok=True)
    raise FolderInUse(f"{self.folder}: could not take the job lock {self.path}")

  def release(self) -> None:
    if self.held:
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
