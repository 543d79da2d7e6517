"""The exit codes of the programs (`lrf_jax.cli.exits.EXIT_CODES`, the table in
docs/api/cli.md): 2 for a bad command line or an input refused before any work, 74 for an output
that cannot be written (a full disk, a read-only file system), each with one `error:` line; a
failed or interrupted write keeps the previous file and leaves no temporary file behind."""

from __future__ import annotations

import errno
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import datasets
from lrf_jax.cli import exits as console, interrupt
from lrf_jax.cli import frames as frames_cli
from lrf_jax.cli import register as register_cli
from lrf_jax.io import atomic
from lrf_jax.learning import train_lib
from tests.lrf_testing import ENOSPC, assert_only_files, full_disk_midway

REPO = Path(__file__).resolve().parents[1]
LOOP = "(ELOOP: too many levels of symbolic links)"


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> tuple[Path, Path]:
  folder = tmp_path_factory.mktemp("scans")
  pair = datasets.make_demo_pair(0)
  a, b = folder / "a.npy", folder / "b.npy"
  np.save(a, pair.model_points[::16])
  np.save(b, pair.scene_points[::16])
  return a, b


@pytest.fixture
def loops(tmp_path, monkeypatch):
  """A working directory holding `loop`, `loop.npz` and `loop.png`: links to themselves."""
  monkeypatch.chdir(tmp_path)
  for name in ("loop", "loop.npz", "loop.png"):
    os.symlink(name, name)
  return tmp_path


@pytest.fixture
def no_work(monkeypatch):
  """Fail the test if a program gets as far as registering or computing frames."""
  import lrf_jax
  from lrf_jax import registration

  def work(*a, **k):
    raise AssertionError("the work started")
  monkeypatch.setattr(registration, "register", work)
  monkeypatch.setattr(lrf_jax, "compute_frames", work)


class _Reg:
  """A registration result, for the tests of the outputs."""
  transform = np.eye(4)
  n_inliers, correspondences, inliers, success, overlap, seconds = 10, [0] * 20, [], True, 0.9, 0.1

  def summary(self, gt=None):
    return "verdict: success: a fake"


@pytest.fixture
def fake_register(monkeypatch):
  from lrf_jax import registration
  monkeypatch.setattr(registration, "register", lambda *a, **k: _Reg())


@pytest.fixture
def fast_frames(monkeypatch):
  """Identity frames instead of the real computation: these tests are about the outputs."""
  import lrf_jax

  def compute_frames(cloud, keypoints, radius, method, **kw):
    return (np.tile(np.eye(3, dtype=np.float32), (len(keypoints), 1, 1)),
            np.ones(len(keypoints), bool))
  monkeypatch.setattr(lrf_jax, "compute_frames", compute_frames)


def _one_error(capsys) -> str:
  err = capsys.readouterr().err
  lines = [line for line in err.splitlines() if line.startswith("error: ")]
  assert len(lines) == 1 and "Traceback" not in err, err
  return lines[0]


def test_the_codes_are_distinct_and_shared():
  assert console.EXIT_INTERRUPTED == interrupt.INTERRUPTED
  codes = [console.EXIT_OK, console.EXIT_BUG, console.EXIT_USAGE, console.EXIT_NOT_SURE,
           console.EXIT_WRITE_FAILED, console.EXIT_INTERRUPTED]
  assert len(set(codes)) == len(codes) and sorted(console.EXIT_CODES) == sorted(codes)
  assert console.EXIT_WRITE_FAILED == 74  # sysexits.h's EX_IOERR


def test_the_docs_list_every_code_of_every_console_script():
  page = (REPO / "docs" / "api" / "cli.md").read_text()
  rows = {int(m.group(1)): m.group(0) for m in re.finditer(r"^\| (\d+) \|.*$", page, re.M)}
  assert sorted(rows) == sorted(console.EXIT_CODES)
  scripts = re.findall(r"^(lrf-[a-z]+) =", (REPO / "pyproject.toml").read_text(), re.M)
  assert scripts and all(script in page for script in scripts)


# ------------------------------------------------------------------- symbolic link loops: 2


@pytest.mark.parametrize("which", [0, 1])
def test_register_a_looping_scan_is_exit_2(scans, loops, no_work, capsys, which):
  argv = [str(scans[0]), str(scans[1])]
  argv[which] = "loop"
  assert register_cli.main(argv) == 2
  assert _one_error(capsys) == (f"error: loop: file: expected a readable file, found a symbolic "
                                f"link loop {LOOP}")


@pytest.mark.parametrize("flag,value", [("--out", "loop"), ("--out", "loop/T.txt"),
                                        ("--png", "loop.png"), ("--init", "loop")])
def test_register_looping_paths_are_exit_2(scans, loops, no_work, capsys, flag, value):
  assert register_cli.main([str(scans[0]), str(scans[1]), flag, value]) == 2
  line = _one_error(capsys)
  assert line.startswith(f"error: {flag}: {value}") and LOOP in line, line


@pytest.mark.parametrize("argv", [["loop", "--out", "f.npz"], ["SCAN", "--out", "loop.npz"],
                                  ["SCAN", "--out", "f.npz", "--png", "loop.png"],
                                  ["SCAN", "--pair", "loop", "--gt", "loop", "--out", "f.npz"]])
def test_frames_looping_paths_are_exit_2(scans, loops, no_work, capsys, argv):
  argv = [str(scans[0]) if a == "SCAN" else a for a in argv]
  assert frames_cli.main(argv) == 2
  line = _one_error(capsys)
  assert "symbolic link loop" in line and LOOP in line, line
  assert sorted(os.listdir()) == ["loop", "loop.npz", "loop.png"]


# ------------------------------------------------------------------- huge coordinates: 2


def test_huge_coordinates_are_exit_2_naming_the_file(scans, tmp_path, capsys):
  huge = tmp_path / "huge.npy"
  np.save(huge, np.load(scans[1]) * 1e200)
  for run, argv in ((register_cli.main, [str(scans[0]), str(huge)]),
                    (frames_cli.main, [str(huge), "--out", str(tmp_path / "f.npz")])):
    assert run(argv) == 2
    line = _one_error(capsys)
    assert line.startswith(f"error: {huge}: x/y/z columns: expected coordinates of magnitude at "
                           "most 1e+42, got"), line
    assert "fold" not in line and "same units" not in line


# ------------------------------------------------------------------- outputs not written: 74


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS])
def test_register_out_not_written_is_exit_74(scans, tmp_path, capsys, monkeypatch,
                                             fake_register, code):
  out = tmp_path / "T.txt"
  out.write_text("the old transform\n")

  def fsync(fd):
    raise OSError(code, os.strerror(code))
  monkeypatch.setattr(atomic.os, "fsync", fsync)
  assert register_cli.main([str(scans[0]), str(scans[1]), "--out", str(out)]) == 74
  assert _one_error(capsys) == f"error: could not write {out}: {os.strerror(code)}"
  assert out.read_text() == "the old transform\n"


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS])
def test_frames_out_not_written_is_exit_74(scans, tmp_path, capsys, monkeypatch, fast_frames,
                                           code):
  def savez(f, **arrays):
    f.write(b"partial")
    raise OSError(code, os.strerror(code))
  monkeypatch.setattr(frames_cli.np, "savez", savez)
  out = tmp_path / "f.npz"
  assert frames_cli.main([str(scans[0]), "--out", str(out), "--keypoints", "10", "--method",
                          "toldi"]) == 74
  assert _one_error(capsys) == f"error: could not write {out}: {os.strerror(code)}"
  assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_read_only_output_folder_is_exit_74_before_any_work(scans, tmp_path, capsys,
                                                              monkeypatch, no_work):
  """A read-only file system (or a folder without write permission): os.access says so before
  the work; simulated, since chmod does not bind root."""
  real_access = os.access
  monkeypatch.setattr(atomic.os, "access",
                      lambda p, mode: False if Path(p) == tmp_path else real_access(p, mode))
  out = tmp_path / "T.txt"
  assert register_cli.main([str(scans[0]), str(scans[1]), "--out", str(out)]) == 74
  assert _one_error(capsys) == f"error: --out: the folder {tmp_path} is not writable"
  assert frames_cli.main([str(scans[0]), "--out", str(tmp_path / "f.npz")]) == 74
  assert _one_error(capsys) == f"error: --out: the folder {tmp_path} is not writable"


@pytest.mark.skipif(os.geteuid() == 0, reason="chmod does not bind root")
def test_a_chmod_read_only_folder_is_exit_74(scans, tmp_path, capsys, no_work):
  folder = tmp_path / "ro"
  folder.mkdir(mode=0o500)
  assert register_cli.main([str(scans[0]), str(scans[1]), "--out", str(folder / "T.txt")]) == 74
  assert _one_error(capsys) == f"error: --out: the folder {folder} is not writable"


def test_a_missing_output_folder_is_still_exit_2(scans, tmp_path, capsys, no_work):
  out = tmp_path / "missing" / "T.txt"
  assert register_cli.main([str(scans[0]), str(scans[1]), "--out", str(out)]) == 2
  assert "does not exist" in _one_error(capsys)


# --------------------------------------------- the programs' writes through `lrf_jax.io.atomic`


def test_frames_result_path_and_failed_rewrites(cloud_npy, tmp_path, capsys, monkeypatch,
                                                fast_frames):
  """`--out result` wrote result.npz but printed "-> result"; a full disk or Ctrl-C during a
  rewrite destroyed the previous result."""
  argv = [str(cloud_npy), "--out", str(tmp_path / "result"), "--keypoints", "20", "--method",
          "toldi"]
  assert frames_cli.main(argv) == 0
  assert capsys.readouterr().err.rstrip().endswith(f"-> {tmp_path / 'result.npz'}")
  assert_only_files(tmp_path, "result.npz")
  good = (tmp_path / "result.npz").read_bytes()
  assert len(np.load(tmp_path / "result.npz")["keypoints"]) == 20

  monkeypatch.setattr(frames_cli.np, "savez", full_disk_midway)
  assert frames_cli.main(argv) == 74
  err = capsys.readouterr().err
  assert err == f"error: could not write {tmp_path / 'result.npz'}: No space left on device\n"
  assert (tmp_path / "result.npz").read_bytes() == good
  assert_only_files(tmp_path, "result.npz")

  def interrupted(f, **kw):
    f.write(b"half")
    raise KeyboardInterrupt
  monkeypatch.setattr(frames_cli.np, "savez", interrupted)
  assert frames_cli.main(argv) == 130  # Ctrl-C: one 'interrupted:' line, no traceback
  assert capsys.readouterr().err.startswith("interrupted: ")
  assert (tmp_path / "result.npz").read_bytes() == good
  assert_only_files(tmp_path, "result.npz")


def test_frames_png_on_a_full_disk(cloud_npy, tmp_path, capsys, monkeypatch, fast_frames):
  from lrf_jax.cli import plot
  png = tmp_path / "f.png"
  png.write_bytes(b"old figure")

  def full(fig, path, **kw):
    raise atomic.WriteError(path, ENOSPC)
  monkeypatch.setattr(plot.atomic, "save_figure", full)
  assert frames_cli.main([str(cloud_npy), "--out", str(tmp_path / "f.npz"), "--keypoints", "10",
                          "--method", "toldi", "--png", str(png)]) == 74
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
  assert register_cli.main([str(cloud_npy), str(cloud_npy), "--out", str(out)]) == 74
  assert capsys.readouterr().err.endswith(
      f"error: could not write {out}: No space left on device\n")
  assert out.read_text() == "the old transform\n"
  assert_only_files(tmp_path, "T.txt")


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
