"""`lrf_jax.io.atomic`: no write destroys a user's file. A failed, interrupted or killed write
leaves the previous file intact and no temporary file behind; a rewrite keeps the permissions;
only a regular file or a new name is replaced; names too long are refused. (The programs' writes
on a full disk, exit code 74: tests/test_cli_exit_codes.py.)
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from lrf_jax.io import atomic
from tests.lrf_testing import ENOSPC, assert_only_files

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("error", [ENOSPC, KeyboardInterrupt(), RuntimeError("writer bug")])
def test_interrupted_write_keeps_the_old_file(tmp_path, error):
  path = tmp_path / "result.bin"
  path.write_bytes(b"the good result")
  raised = atomic.WriteError if isinstance(error, OSError) else type(error)
  with pytest.raises(raised) as e:
    with atomic.atomic_write(path) as f:
      f.write(b"half of a new")
      raise error
  assert path.read_bytes() == b"the good result"
  assert_only_files(tmp_path, "result.bin")
  if isinstance(error, OSError):
    assert str(e.value) == f"could not write {path}: No space left on device"


def test_write_replaces_and_keeps_permissions(tmp_path):
  path = tmp_path / "t.txt"
  path.write_text("old")
  path.chmod(0o640)
  atomic.write_text(path, "new")
  assert path.read_text() == "new" and (path.stat().st_mode & 0o777) == 0o640
  atomic.write_text(tmp_path / "fresh.txt", "x")  # a new file gets the umask's mode, not 0600
  umask = os.umask(0)
  os.umask(umask)
  assert (tmp_path / "fresh.txt").stat().st_mode & 0o777 == 0o666 & ~umask
  with pytest.raises(atomic.WriteError, match="is a folder"):
    atomic.write_text(tmp_path, "x")
  with pytest.raises(atomic.WriteError, match="could not write"):
    atomic.write_text(tmp_path / "no" / "such.txt", "x")


def test_full_disk_at_fsync(tmp_path, monkeypatch):
  path = tmp_path / "p.msgpack"
  path.write_bytes(b"old params")

  def fsync(fd):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
  monkeypatch.setattr(atomic.os, "fsync", fsync)
  with pytest.raises(atomic.WriteError, match="No space left on device"):
    atomic.write_bytes(path, b"new params")
  assert path.read_bytes() == b"old params"
  assert_only_files(tmp_path, "p.msgpack")


def test_failed_append_is_truncated_away(tmp_path, monkeypatch):
  log = tmp_path / "metrics.jsonl"
  atomic.append_line(log, '{"step": 1}')
  atomic.append_line(log, '{"step": 2}')

  def fsync(fd):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
  monkeypatch.setattr(atomic.os, "fsync", fsync)
  with pytest.raises(atomic.WriteError, match="metrics.jsonl: No space left"):
    atomic.append_line(log, '{"step": 3}')
  assert log.read_text() == '{"step": 1}\n{"step": 2}\n'


def test_figure_that_fails_to_save_keeps_the_old_png(tmp_path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  path = tmp_path / "curves.png"
  path.write_bytes(b"old png")
  fig = plt.figure()

  def savefig(fname, **kw):
    Path(fname).write_bytes(b"half a png")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
  fig.savefig = savefig
  with pytest.raises(atomic.WriteError, match="curves.png: No space"):
    atomic.save_figure(fig, path, dpi=50)
  plt.close(fig)
  assert path.read_bytes() == b"old png"
  assert_only_files(tmp_path, "curves.png")


def _socket_file(path: Path):
  """A Unix socket bound at `path` (a file of another kind than FIFO or device, made without
  privileges); close it when done."""
  import socket
  sock = socket.socket(socket.AF_UNIX)
  sock.bind(str(path))
  return sock


def test_only_a_regular_file_or_a_new_name_is_replaced(tmp_path):
  """The rename of an atomic write replaced a FIFO or a device (/dev/null, as root) with a
  regular file. Each is refused before anything is written, as an `OutputPathError` (a
  `WriteError` for the programs' `error:` line and a `ValueError` for a library caller) naming
  the path; a symbolic link is followed to what it points to."""
  fifo = tmp_path / "pipe"
  os.mkfifo(fifo)
  link = tmp_path / "link.txt"
  link.symlink_to(fifo)
  sock = _socket_file(tmp_path / "sock")
  try:
    for path, kind in ((fifo, "FIFO"), (link, "FIFO"), (tmp_path / "sock", "socket")):
      for write, data in ((atomic.write_text, "x"), (atomic.write_bytes, b"x"),
                          (atomic.append_line, "x")):
        with pytest.raises(atomic.OutputPathError, match=kind) as e:
          write(path, data)
        assert isinstance(e.value, ValueError) and isinstance(e.value, atomic.WriteError)
        assert str(e.value).startswith(f"could not write {os.path.realpath(path)}: is a")
    assert fifo.is_fifo() and link.is_symlink() and (tmp_path / "sock").is_socket()
    assert_only_files(tmp_path, "pipe", "link.txt", "sock")
    # The programs' check before any work says the same, /dev/null included (only looked at).
    for path, kind in ((fifo, "a FIFO (named pipe)"), (tmp_path / "sock", "a socket"),
                       ("/dev/null", "a character device")):
      assert atomic.output_problem(path, "--out") == (
          f"--out: {path} is {kind}; expected a regular file or a new name")
    assert atomic.output_problem(tmp_path / "new.txt", "--out") is None
  finally:
    sock.close()


def test_names_too_long_are_refused_and_a_long_one_still_written(tmp_path):
  """A 256-byte file name was a traceback (ENAMETOOLONG) in every program; a 255-byte one
  failed too, on the longer temporary name beside it."""
  long = tmp_path / ("é" * 128)  # 256 bytes in UTF-8
  with pytest.raises(atomic.OutputPathError, match="256 bytes; a file or folder name may be at "
                                                     "most 255 bytes"):
    atomic.write_text(long, "x")
  assert "256 bytes" in atomic.output_problem(long, "--out")
  assert "256 bytes" in atomic.output_problem(long / "sub.txt", "--out")
  assert "4096 bytes" in atomic.path_problem("a/" * 2048)
  assert "NUL" in atomic.path_problem("a\0b")
  for name in ("x" * 255, "y" * 250 + ".png", "z" * 200 + "." + "s" * 54):
    atomic.write_text(tmp_path / name, "kept")
    assert (tmp_path / name).read_text() == "kept"
  assert_only_files(tmp_path, "x" * 255, "y" * 250 + ".png", "z" * 200 + "." + "s" * 54)


_KILLED_WRITER = """
import importlib.util, sys, time
spec = importlib.util.spec_from_file_location("atomic", sys.argv[1])
atomic = importlib.util.module_from_spec(spec)
spec.loader.exec_module(atomic)
with atomic.atomic_write(sys.argv[2]) as f:
  f.write(b"x" * 100000)
  f.flush()
  print("writing", flush=True)
  time.sleep(60)
"""


def test_sigkill_during_a_write_keeps_the_old_file(tmp_path):
  """SIGKILL during lrf-frames' in-place write left a 0-byte file where a good result had been."""
  path = tmp_path / "f.npz"
  path.write_bytes(b"the good result")
  proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER,
                           str(REPO / "lrf_jax" / "io" / "atomic.py"), str(path)],
                          stdout=subprocess.PIPE)
  try:
    assert proc.stdout.readline() == b"writing\n"
  finally:
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
  assert path.read_bytes() == b"the good result"
  # What a kill can leave: one hidden temporary file beside it, never a damaged `path`.
  assert all(p.name.startswith(".f.npz.") for p in tmp_path.iterdir() if p != path)
