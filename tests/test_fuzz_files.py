"""No write destroys a user's file: a failed, interrupted or killed write leaves the previous
file intact and no temporary file behind (`lrf_jax.io.atomic`), and a full disk is one
`error: could not write PATH: No space left on device` line with exit code 2.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import datasets
from lrf_jax.cli import frames as frames_cli
from lrf_jax.cli import register as register_cli
from lrf_jax.learning import train_lib
from lrf_jax.io import atomic

REPO = Path(__file__).resolve().parents[1]
ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.fixture(scope="module")
def cloud_npy(tmp_path_factory) -> Path:
  path = tmp_path_factory.mktemp("cloud") / "scan.npy"
  np.save(path, datasets.make_demo_pair(0).model_points[::16])
  return path


def _only(folder: Path, *names: str) -> None:
  """`folder` holds exactly `names`: no temporary file was left."""
  assert sorted(p.name for p in folder.iterdir()) == sorted(names)


def _full_disk_midway(f, *args, **kwargs):
  """A writer that gets half-way and then finds the disk full."""
  f.write(b"partial data")
  raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


# ----------------------------------------------------------------------------- the helper


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
  _only(tmp_path, "result.bin")
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
  _only(tmp_path, "p.msgpack")


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
  _only(tmp_path, "curves.png")


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
    _only(tmp_path, "pipe", "link.txt", "sock")
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
  _only(tmp_path, "x" * 255, "y" * 250 + ".png", "z" * 200 + "." + "s" * 54)


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


# ----------------------------------------------------------------------------- the programs


@pytest.fixture
def fast_frames(monkeypatch):
  """lrf-frames with identity frames instead of the real computation (tested elsewhere): these
  tests are about its writes."""
  import lrf_jax

  def compute_frames(cloud, keypoints, radius, method, **kw):
    return np.tile(np.eye(3, dtype=np.float32), (len(keypoints), 1, 1)), np.ones(len(keypoints),
                                                                                  bool)
  monkeypatch.setattr(lrf_jax, "compute_frames", compute_frames)


def test_frames_result_path_and_failed_rewrites(cloud_npy, tmp_path, capsys, monkeypatch,
                                                fast_frames):
  """`--out result` wrote result.npz but printed "-> result"; a full disk or Ctrl-C during a
  rewrite destroyed the previous result."""
  argv = [str(cloud_npy), "--out", str(tmp_path / "result"), "--keypoints", "20", "--method",
          "toldi"]
  assert frames_cli.main(argv) == 0
  assert capsys.readouterr().err.rstrip().endswith(f"-> {tmp_path / 'result.npz'}")
  _only(tmp_path, "result.npz")
  good = (tmp_path / "result.npz").read_bytes()
  assert len(np.load(tmp_path / "result.npz")["keypoints"]) == 20

  monkeypatch.setattr(frames_cli.np, "savez", _full_disk_midway)
  assert frames_cli.main(argv) == 2
  err = capsys.readouterr().err
  assert err == f"error: could not write {tmp_path / 'result.npz'}: No space left on device\n"
  assert (tmp_path / "result.npz").read_bytes() == good
  _only(tmp_path, "result.npz")

  def interrupted(f, **kw):
    f.write(b"half")
    raise KeyboardInterrupt
  monkeypatch.setattr(frames_cli.np, "savez", interrupted)
  assert frames_cli.main(argv) == 130  # Ctrl-C: one 'interrupted:' line, no traceback
  assert capsys.readouterr().err.startswith("interrupted: ")
  assert (tmp_path / "result.npz").read_bytes() == good
  _only(tmp_path, "result.npz")


def test_frames_png_on_a_full_disk(cloud_npy, tmp_path, capsys, monkeypatch, fast_frames):
  from lrf_jax.cli import plot
  png = tmp_path / "f.png"
  png.write_bytes(b"old figure")

  def full(fig, path, **kw):
    raise atomic.WriteError(path, ENOSPC)
  monkeypatch.setattr(plot.atomic, "save_figure", full)
  assert frames_cli.main([str(cloud_npy), "--out", str(tmp_path / "f.npz"), "--keypoints", "10",
                          "--method", "toldi", "--png", str(png)]) == 2
  assert capsys.readouterr().err == f"error: could not write {png}: No space left on device\n"
  assert png.read_bytes() == b"old figure"


def test_register_out_on_a_full_disk(cloud_npy, tmp_path, capsys, monkeypatch):
  from lrf_jax import registration

  class Reg:
    transform = np.diag([1.0, 1.0, 1.0, 1.0])
    n_inliers, correspondences, chance_inliers = 10, [0] * 20, 1.0
    overlap_contrast, fitness, rmse, mr, seconds, success = 3.0, 0.9, 0.1, 1.0, 0.1, True
    rival_inliers, overlap, reason = 1, 0.9, "a fake"

    def summary(self, gt=None):
      return "verdict: success: a fake"
  monkeypatch.setattr(registration, "register", lambda *a, **k: Reg())
  out = tmp_path / "T.txt"
  assert register_cli.main([str(cloud_npy), str(cloud_npy), "--out", str(out)]) == 0
  np.testing.assert_array_equal(np.loadtxt(out), np.eye(4))
  out.write_text("the old transform\n")

  def fsync(fd):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
  monkeypatch.setattr(atomic.os, "fsync", fsync)
  assert register_cli.main([str(cloud_npy), str(cloud_npy), "--out", str(out)]) == 2
  assert capsys.readouterr().err.endswith(
      f"error: could not write {out}: No space left on device\n")
  assert out.read_text() == "the old transform\n"
  _only(tmp_path, "T.txt")


def test_params_on_a_full_disk_keep_the_old_file(tmp_path, monkeypatch):
  """train.py on a full disk: a traceback and a truncated best_params.msgpack."""
  params = {"enc0": {"kernel": np.ones((2, 16), np.float32), "bias": np.zeros(16, np.float32)}}
  path = tmp_path / "best_params.msgpack"
  train_lib._save_params(params, path)
  good = path.read_bytes()
  def half_written(p, tmp):
    with open(tmp, "wb") as f:
      _full_disk_midway(f)
  monkeypatch.setattr(train_lib, "save_params", half_written)
  with pytest.raises(atomic.WriteError, match="best_params.msgpack: No space left"):
    train_lib._save_params(params, path)
  assert path.read_bytes() == good
  _only(tmp_path, "best_params.msgpack")


def test_train_and_evaluate_write_errors_are_clean(tmp_path, capsys, monkeypatch):
  sys.path.insert(0, str(REPO))
  import evaluate
  import train
  from lrf_jax.evaluation import runner
  target = tmp_path / "run" / "best_params.msgpack"

  def full(*a, **k):
    raise atomic.WriteError(target, ENOSPC)
  monkeypatch.setattr(train_lib, "train_and_evaluate", full)
  assert train.main(["--config", "smoke", "--workdir", str(tmp_path / "run")]) == 2
  assert capsys.readouterr().err == f"error: could not write {target}: No space left on device\n"
  monkeypatch.setattr(runner, "evaluate", full)
  assert evaluate.main(["--datasets", "demo", "--methods", "toldi", "--out",
                        str(tmp_path / "ev")]) == 2
  assert capsys.readouterr().err.endswith(
      f"error: could not write {target}: No space left on device\n")


def test_curves_skip_notes_and_torn_lines(tmp_path):
  log = tmp_path / "metrics.jsonl"
  log.write_text('{"step": 4, "loss": 1.0}\n{"step": 4, "note": "config replaced"}\n'
                 '{"step": 8, "loss": 0.5, "epoch": 1.0, "val_meancos": 0.5}\n{"step": 9, "lo')
  train_lib.plot_curves(log, tmp_path / "curves.png")
  assert (tmp_path / "curves.png").stat().st_size > 1000
  train_lib._trim_log(log, 8)
  assert [json.loads(l)["step"] for l in log.read_text().splitlines()] == [4, 4, 8]
  _only(tmp_path, "metrics.jsonl", "curves.png")
