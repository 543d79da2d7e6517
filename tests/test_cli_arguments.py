"""Bad arguments of the command-line programs (`lrf_jax.cli`: lrf-frames, lrf-register, its
multiway mode) and Ctrl-C in any program: each bad argument is one `error:` line naming the option,
exit code 2, no traceback and nothing written; a Ctrl-C is one `interrupted:` line and exit 130.
The programs are driven in-process (their `main(argv)`); every case here fails before any
real work (no frames, no registration, no training), so the whole file runs in seconds.
(evaluate.py's bad arguments: tests/test_evaluate_arguments.py; train.py's: tests/test_train.py.)
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from lrf_jax.cli import frames as frames_cli
from lrf_jax.cli import register as register_cli
from lrf_jax.learning import train_lib
from tests.lrf_testing import FakeRegistration, cli_error

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import evaluate  # noqa: E402
import train  # noqa: E402


def _listing(folder: Path) -> list[str]:
  return sorted(p.name for p in folder.iterdir())


# ----------------------------------------------------------------------------- lrf-frames


@pytest.mark.parametrize("extra,fragment", [
    (["--keypoints", "²"], "--keypoints"),          # str.isdigit() is True, int() fails
    (["--keypoints", "-3"], "--keypoints"),
    (["--seed", "-1"], "--seed"),
    (["--seed", str(2**40)], "--seed"),
    (["--keypoint-voxel-mr", "1e-20"], "--keypoint-voxel-mr"),  # 23 keypoints of 3,000 before
    (["--keypoint-voxel-mr", "5", "--keypoints", "10"], "--keypoint-voxel-mr and --keypoints"),
    (["--voxel-mr", "1e-20"], "--voxel-mr:"),      # its name before 0.9, named as typed
    (["--voxel-mr", "5", "--keypoints", "10"], "--voxel-mr and --keypoints"),
    (["--png", "PNG/x.xyz"], "--png"),             # failed after the npz was written before
    (["--png", "PNG/x"], "--png"),
    (["--png", "PNG/same.npz"], "--png"),
])
def test_frames_bad_argument_before_any_work(cloud_npy, tmp_path, capsys, extra, fragment):
  extra = [a.replace("PNG", str(tmp_path)) for a in extra]
  out = tmp_path / "same.npz"
  assert frames_cli.main([str(cloud_npy), "--out", str(out)] + extra) == 2
  assert fragment in cli_error(capsys)
  assert _listing(tmp_path) == []


def test_frames_out_is_a_folder_or_the_input(cloud_npy, tmp_path, capsys):
  assert frames_cli.main([str(cloud_npy), "--out", str(tmp_path)]) == 2
  err = cli_error(capsys)
  assert "--out" in err and "folder" in err
  link = tmp_path / "scan.npz"  # a hard link to the input, as the --out file
  os.link(cloud_npy, link)
  before = cloud_npy.read_bytes()
  for out in (str(link), str(link)[:-4]):  # --out "scan" writes scan.npz too
    assert frames_cli.main([str(cloud_npy), "--out", out]) == 2
    err = cli_error(capsys)
    assert "--out" in err and "input" in err, err
  assert cloud_npy.read_bytes() == before


def test_frames_out_in_a_read_only_folder(cloud_npy, tmp_path, capsys, monkeypatch):
  ro = tmp_path / "ro"
  ro.mkdir()
  ro.chmod(0o555)
  if os.geteuid() == 0:  # root writes anywhere: pretend the folder is read-only
    from lrf_jax.io import atomic
    monkeypatch.setattr(atomic.os, "access", lambda p, mode: Path(p) != ro)
  try:
    assert frames_cli.main([str(cloud_npy), "--out", str(ro / "f.npz")]) == 74
    err = cli_error(capsys)
    assert "--out" in err and "not writable" in err
  finally:
    ro.chmod(0o755)


def test_frames_unreadable_input(cloud_npy, tmp_path, capsys, monkeypatch):
  bad = tmp_path / "locked.ply"
  bad.write_bytes(b"ply\n")
  import lrf_jax.frames.compute  # noqa: F401 -- imported unpatched: it binds as_cloud on import
  from lrf_jax.geometry import cloud as inputs

  def denied(source, name):
    raise PermissionError(13, "Permission denied", str(bad))
  monkeypatch.setattr(inputs, "as_cloud", denied)
  assert frames_cli.main([str(bad), "--out", str(tmp_path / "f.npz")]) == 2
  err = cli_error(capsys)
  assert str(bad) in err and "Permission denied" in err
  assert not (tmp_path / "f.npz").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files without read permission")
@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_frames_unreadable_file_on_disk(cloud_npy, tmp_path, capsys, suffix):
  bad = tmp_path / f"locked{suffix}"
  bad.write_bytes(b"x")
  bad.chmod(0)
  assert frames_cli.main([str(bad), "--out", str(tmp_path / "f.npz")]) == 2
  assert "locked" in cli_error(capsys)


# ----------------------------------------------------------------------------- lrf-register


@pytest.mark.parametrize("extra,fragment", [
    (["--seed", "-1"], "--seed"), (["--keypoints", "0"], "--keypoints"),
    (["--keypoints", "sift"], "--keypoints"), (["--keypoints", "iss", "--detector", "random"],
                                               "--detector"),
    (["--method", "bogus"], "--method"), (["--radius-mr", "0"], "--radius-mr"),
    (["--ratio", "1.5"], "--ratio"), (["--source-viewpoint", "nan", "0", "0"],
                                      "--source-viewpoint"),
    (["--init", "MISSING"], "--init"), (["--weights", "nowhere"], "weights: 'nowhere'"),
    (["--method", "shot", "--weights", "rooms"], "weights: method 'shot' is hand-crafted"),
    (["--weights", "rooms", "--checkpoint", "MISSING"], "--checkpoint and --weights")])
def test_register_bad_argument_before_any_work(cloud_npy, tmp_path, capsys, monkeypatch, extra,
                                               fragment):
  from lrf_jax import registration
  monkeypatch.setattr(registration, "register", lambda *a, **k: pytest.fail("work started"))
  extra = [a.replace("MISSING", str(tmp_path / "none.txt")) for a in extra]
  assert register_cli.main([str(cloud_npy), str(cloud_npy)] + extra) == 2
  err = cli_error(capsys)
  assert fragment in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("extra,expected", [
    ([], dict(n_keypoints=3000)), (["--keypoints", "2000"], dict(n_keypoints=2000)),
    (["--keypoints", "iss"], dict(keypoints="iss")),
    (["--keypoints", "random"], dict(keypoints="random")),
    (["--detector", "iss"], dict(n_keypoints=3000, keypoints="iss")),  # the old spelling
    (["--keypoints", "500", "--detector", "iss"], dict(n_keypoints=500, keypoints="iss"))])
def test_register_keypoints_take_a_count_or_a_detector(cloud_npy, monkeypatch, capsys, extra,
                                                       expected):
  from lrf_jax import registration
  seen = []
  monkeypatch.setattr(registration, "register",
                      lambda *a, **k: seen.append(k) or FakeRegistration())
  assert register_cli.main([str(cloud_npy), str(cloud_npy)] + extra) == 0
  got = {k: seen[-1][k] for k in ("n_keypoints", "keypoints") if k in seen[-1]}
  assert got == expected


def test_register_help_names_multiway(capsys):
  with pytest.raises(SystemExit):
    register_cli.main(["--help"])
  out = " ".join(capsys.readouterr().out.split())
  assert "more than two scans" in out and "--out-dir" in out and "N|DETECTOR" in out
  assert "--detector" not in out  # the deprecated spelling is hidden


@pytest.mark.parametrize("extra,fragment", [
    (["--keypoints", "0"], "--keypoints"), (["--keypoints", "sift"], "--keypoints"),
    (["--method", "bogus"], "--method"), (["--radius-mr", "0"], "--radius-mr"),
    (["--viewpoint", "nan", "0", "0"], "--viewpoint"),
    (["--all-pairs-max", "-1"], "--all-pairs-max"), (["--weights", "nowhere"], "weights")])
def test_multiway_bad_option_before_any_work(cloud_npy, tmp_path, capsys, monkeypatch, extra,
                                             fragment):
  from lrf_jax.multiway import pipeline as multiway_pipeline
  monkeypatch.setattr(multiway_pipeline, "register_all", lambda *a, **k: pytest.fail("work started"))
  monkeypatch.setattr(multiway_pipeline, "load_scans", lambda *a, **k: pytest.fail("work started"))
  scans = [str(cloud_npy)] * 3
  assert register_cli.main(scans + ["--out-dir", str(tmp_path / "D")] + extra) == 2
  err = cli_error(capsys)
  assert fragment in err and len(err.strip().splitlines()) == 1, err
  assert not (tmp_path / "D").exists()


@pytest.mark.parametrize("bad,fragment", [
    (dict(n_keypoints=0), "n_keypoints"), (dict(method="bogus"), "method"),
    (dict(radius_mr=0.0), "radius_mr"), (dict(viewpoints=(np.nan, 0, 0)), "viewpoints"),
    (dict(viewpoints=[None, (0, 0, 0), (np.inf, 0, 0)]), "viewpoints[2]"),
    (dict(all_pairs_max=-1), "all_pairs_max"), (dict(keypoints="sift"), "keypoints"),
    (dict(weights="nowhere"), "weights")])
def test_register_all_checks_register_options_before_any_pair(bad, fragment):
  from lrf_jax import multiway
  clouds = [np.random.default_rng(k).random((50, 3)) for k in range(3)]
  with pytest.raises(ValueError, match=re.escape(fragment)):
    multiway.register_all(clouds, mr=0.05, **bad)


@pytest.mark.parametrize("bad,fragment", [
    (dict(method="bogus"), "method"), (dict(estimator="bogus"), "estimator"),
    (dict(keypoints="bogus"), "keypoints"), (dict(n_keypoints=0), "n_keypoints"),
    (dict(descriptor="bogus"), "descriptor"), (dict(ratio=2.0), "ratio"),
    (dict(source_viewpoint=(np.nan, 0, 0)), "source_viewpoint")])
def test_register_with_init_checks_every_option(bad, fragment):
  """`register(init=...)` only refines by ICP, yet a bogus option is refused, not ignored."""
  from lrf_jax.registration import register
  pts = np.random.default_rng(0).random((200, 3))
  with pytest.raises(ValueError, match=rf"^{re.escape(fragment)}:"):
    register(pts, pts, init=np.eye(4), **bad)


def test_register_refuses_to_overwrite_an_input(cloud_npy, tmp_path, capsys):
  """`lrf-register a b --out a` wrote the 4x4 matrix over the scan a."""
  src, tgt = tmp_path / "a.npy", tmp_path / "b.npy"
  src.write_bytes(cloud_npy.read_bytes())
  tgt.write_bytes(cloud_npy.read_bytes())
  before = src.read_bytes()
  for out in (src, tgt, tmp_path / "." / "a.npy"):
    assert register_cli.main([str(src), str(tgt), "--out", str(out)]) == 2
    err = cli_error(capsys)
    assert "--out" in err and "input" in err
  assert register_cli.main([str(src), str(tgt), "--out", str(tmp_path)]) == 2
  assert "folder" in cli_error(capsys)
  assert src.read_bytes() == before


def test_outputs_refuse_a_fifo_before_any_work(cloud_npy, tmp_path, capsys, monkeypatch):
  """`lrf-register a b --out F` with F a FIFO (or a device such as /dev/null) replaced it with a
  regular file by the atomic rename. Every output option refuses what is neither a regular
  file nor a new name: one `error:` line naming the option and the path, exit code 2, before
  any work, the FIFO left as it was."""
  from lrf_jax import registration
  monkeypatch.setattr(registration, "register", lambda *a, **k: pytest.fail("register ran"))
  fifo, fifo_npz, fifo_png = tmp_path / "T.txt", tmp_path / "f.npz", tmp_path / "f.png"
  for f in (fifo, fifo_npz, fifo_png):
    os.mkfifo(f)
  link = tmp_path / "link.txt"
  link.symlink_to(fifo)
  cases = [
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--out", str(fifo)], "--out", fifo),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--out", str(link)], "--out", link),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--png", str(fifo_png)], "--png",
       fifo_png),
      (frames_cli.main, [str(cloud_npy), "--out", str(fifo_npz)], "--out", fifo_npz),
      (frames_cli.main, [str(cloud_npy), "--out", str(fifo_npz)[:-4]], "--out", fifo_npz),
      (frames_cli.main, [str(cloud_npy), "--out", str(tmp_path / "x.npz"), "--png",
                         str(fifo_png)], "--png", fifo_png),
  ]
  for main, argv, option, path in cases:
    assert main(argv) == 2, argv
    err = cli_error(capsys)
    assert err == (f"error: {option}: {path} is a FIFO (named pipe); expected a regular file or "
                   "a new name\n"), err
  assert all(f.is_fifo() for f in (fifo, fifo_npz, fifo_png))
  assert _listing(tmp_path) == ["T.txt", "f.npz", "f.png", "link.txt"]


def test_output_names_too_long_are_one_error_line(cloud_npy, tmp_path, capsys):
  """An output name over 255 bytes was a traceback (ENAMETOOLONG) in lrf-frames --out,
  lrf-register --out-dir, train.py --workdir and evaluate.py --out; now one `error:` line naming
  the option, exit code 2, before any work."""
  long = str(tmp_path / ("n" * 256))
  cases = [
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--out", long], "--out"),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--png", long + ".png"], "--png"),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--init", long], "--init"),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--checkpoint", long],
       "--checkpoint"),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--out-dir", long], "--out-dir"),
      (register_cli.main, [str(cloud_npy), str(cloud_npy), "--out-dir", long + "/sub"],
       "--out-dir"),
      (frames_cli.main, [str(cloud_npy), "--out", long], "--out"),
      (frames_cli.main, [str(cloud_npy), "--out", str(tmp_path / "f.npz"), "--png",
                         long + ".png"], "--png"),
      (train.main, ["--config", "smoke", "--workdir", long], "--workdir"),
      (evaluate.main, ["--datasets", "demo", "--out", long], "--out"),
  ]
  for main, argv, option in cases:
    assert main(argv) == 2, argv
    err = cli_error(capsys)
    assert err.startswith(f"error: {option}: ") and "at most 255 bytes" in err, err
  assert _listing(tmp_path) == []


def test_register_checkpoint_without_checkpoints(cloud_npy, tmp_path, capsys):
  empty = tmp_path / "empty"
  empty.mkdir()
  assert register_cli.main([str(cloud_npy), str(cloud_npy), "--checkpoint", str(empty)]) == 2
  assert "--checkpoint" in cli_error(capsys)


@pytest.mark.parametrize("content,name", [("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "m.txt"),
                                          ("a b c d\n" * 4, "m.xf"),
                                          (np.eye(3), "m.npy"), (np.eye(4) * 2, "s.npy"),
                                          (np.array(["x"] * 16).reshape(4, 4), "t.npy")])
def test_register_bad_init_names_the_file(cloud_npy, tmp_path, capsys, monkeypatch, content,
                                          name):
  from lrf_jax import registration
  monkeypatch.setattr(registration, "register", lambda *a, **k: pytest.fail("register ran"))
  path = tmp_path / name
  if isinstance(content, str):
    path.write_text(content)
  else:
    np.save(path, content)
  assert register_cli.main([str(cloud_npy), str(cloud_npy), "--init", str(path)]) == 2
  err = cli_error(capsys)
  assert "--init" in err and name in err, err




def test_register_passes_init_only_when_given(cloud_npy, tmp_path, monkeypatch, capsys):
  from lrf_jax import registration
  seen = []
  monkeypatch.setattr(registration, "register",
                      lambda *a, **k: seen.append(k) or FakeRegistration())
  t = np.eye(4)
  t[:3, 3] = (1.0, 2.0, 3.0)
  np.savetxt(tmp_path / "init.txt", t)
  np.save(tmp_path / "init.npy", t)
  assert register_cli.main([str(cloud_npy), str(cloud_npy)]) == 0
  assert "init" not in seen[-1]
  for f in ("init.txt", "init.npy"):
    assert register_cli.main([str(cloud_npy), str(cloud_npy), "--init", str(tmp_path / f)]) == 0
    np.testing.assert_array_equal(seen[-1]["init"], t)


def test_register_unreadable_input(cloud_npy, tmp_path, monkeypatch, capsys):
  from lrf_jax import registration

  def denied(*a, **k):
    raise PermissionError(13, "Permission denied", "/x/locked.pcd")
  monkeypatch.setattr(registration, "register", denied)
  assert register_cli.main([str(cloud_npy), str(cloud_npy)]) == 2
  err = cli_error(capsys)
  assert "/x/locked.pcd" in err and "Permission denied" in err


def test_frames_iss_keypoints(cloud_npy, tmp_path, monkeypatch):
  """`--keypoints iss` takes lrf_jax.geometry.keypoints.iss_keypoints at the cloud's mr (sorted int64)."""
  import lrf_jax
  from lrf_jax.geometry import keypoints
  seen = {}

  def iss(points, mr=None, **kw):
    seen["mr"] = mr
    return np.array([7, 3, 5])
  monkeypatch.setattr(keypoints, "iss_keypoints", iss)
  monkeypatch.setattr(lrf_jax, "compute_frames", lambda cloud, kp, *a, **k: (
      np.tile(np.eye(3), (len(kp), 1, 1)), np.ones(len(kp), bool)))
  out = tmp_path / "iss.npz"
  assert frames_cli.main([str(cloud_npy), "--out", str(out), "--keypoints", "iss",
                          "--method", "toldi"]) == 0
  z = np.load(out)
  assert z["keypoints"].tolist() == [3, 5, 7] and z["keypoints"].dtype == np.int64
  assert seen["mr"] == pytest.approx(float(z["mr"]))


# ----------------------------------------------------------------------------- Ctrl-C


def _interrupt(*args, **kwargs):
  raise KeyboardInterrupt


def _interrupted(capsys) -> str:
  err = capsys.readouterr().err
  assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
  lines = [line for line in err.splitlines() if not line.startswith("#")]
  assert len(lines) == 1 and lines[0].startswith("interrupted: "), err
  return err


@pytest.mark.parametrize("program", ["lrf-register", "multiway", "lrf-frames", "train.py",
                                     "evaluate.py"])
def test_ctrl_c_is_exit_130_with_one_line_and_no_partial_file(program, cloud_npy, tmp_path,
                                                              capsys, monkeypatch):
  """Ctrl-C in the middle of the work: one `interrupted:` line, exit 130, no traceback, no
  output file (each program's work replaced by one that raises KeyboardInterrupt)."""
  from lrf_jax import registration
  from lrf_jax.evaluation import runner
  from lrf_jax.multiway import pipeline as multiway_pipeline
  out = tmp_path / "out"
  if program == "lrf-register":
    monkeypatch.setattr(registration, "register", _interrupt)
    rc = register_cli.main([str(cloud_npy), str(cloud_npy), "--out", str(out)])
  elif program == "multiway":
    monkeypatch.setattr(multiway_pipeline, "register_all", _interrupt)
    rc = register_cli.main([str(cloud_npy)] * 3 + ["--out-dir", str(out), "--quiet"])
  elif program == "lrf-frames":
    monkeypatch.setattr(frames_cli, "frames_outputs", _interrupt)
    rc = frames_cli.main([str(cloud_npy), "--out", str(out)])
  elif program == "train.py":
    monkeypatch.setattr(train_lib, "train_and_evaluate", _interrupt)
    rc = train.main(["--config", "smoke", "--workdir", str(out), "--no-progress"])
  else:
    monkeypatch.setattr(runner, "method_runs", _interrupt)
    rc = evaluate.main(["--out", str(out), "--datasets", "demo", "--experiments", "repeatability"])
  assert rc == 130
  _interrupted(capsys)
  assert not out.exists() or not any(out.iterdir())


def test_ctrl_c_inside_a_numba_kernel_call_is_still_an_interrupt(cloud_npy, capsys, monkeypatch):
  """Ctrl-C while numba dispatches surfaces as a SystemError raised from the KeyboardInterrupt
  (seen in a real SIGINT during multiway): still exit 130 and one line."""
  from lrf_jax import registration

  def numba_like(*args, **kwargs):
    try:
      raise KeyboardInterrupt
    except KeyboardInterrupt as e:
      raise SystemError("CPUDispatcher(<function _bin>) returned a result with an exception "
                        "set") from e
  monkeypatch.setattr(registration, "register", numba_like)
  assert register_cli.main([str(cloud_npy), str(cloud_npy)]) == 130
  _interrupted(capsys)
  monkeypatch.setattr(registration, "register", _interrupt_not)
  with pytest.raises(SystemError):  # any other error is not taken for an interrupt
    register_cli.main([str(cloud_npy), str(cloud_npy)])


def _interrupt_not(*args, **kwargs):
  raise SystemError("a bug")


def test_frames_cloud_without_spacing_names_the_file(tmp_path, capsys):
  path = tmp_path / "dup.npy"
  np.save(path, np.ones((100, 3)))
  assert frames_cli.main([str(path), "--out", str(tmp_path / "f.npz")]) == 2
  err = cli_error(capsys)
  assert f"{path}: the cloud has no spacing" in err and "radius" not in err, err
