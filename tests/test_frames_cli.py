"""lrf-frames: frames for one's own file, its outputs, its figure and its clean errors."""

import numpy as np
import pytest

from lrf_jax import datasets, io
from lrf_jax.frames_cli import build_parser, main


@pytest.fixture(scope="module")
def demo_ply(tmp_path_factory):
  """The README's one-liner: a demo cloud written as a PLY mesh."""
  pair = datasets.make_demo_pair(0)
  path = tmp_path_factory.mktemp("cli") / "demo.ply"
  io.write_ply(path, pair.model_points, pair.model_faces)
  return path, pair


def test_writes_frames_npz_and_png(demo_ply, tmp_path):
  path, pair = demo_ply
  out, png = tmp_path / "f.npz", tmp_path / "f.png"
  assert main([str(path), "--out", str(out), "--keypoints", "200", "--png", str(png),
               "--descriptor", "toldi"]) == 0
  z = np.load(out)
  assert set(z.files) >= {"keypoints", "positions", "frames", "valid", "radius", "mr", "method",
                          "weights", "descriptors"}
  m = len(z["keypoints"])
  assert m == 200 and z["frames"].shape == (m, 3, 3) and z["valid"].shape == (m,)
  np.testing.assert_allclose(z["positions"], pair.model_points[z["keypoints"]])
  assert str(z["method"]) == "lrf_net_plus" and str(z["weights"]) == "lrf_net_plus"
  assert float(z["radius"]) == pytest.approx(15 * float(z["mr"]))
  assert z["valid"].mean() > 0.9 and z["descriptors"].shape[0] == m
  det = np.linalg.det(z["frames"][z["valid"]])
  np.testing.assert_allclose(det, 1.0, atol=1e-4)
  assert png.stat().st_size > 10_000


def test_voxel_and_all_keypoints(demo_ply, tmp_path):
  path, pair = demo_ply
  assert main([str(path), "--out", str(tmp_path / "v.npz"), "--voxel-mr", "10",
               "--method", "toldi"]) == 0
  kv = np.load(tmp_path / "v.npz")["keypoints"]
  assert 10 < len(kv) < len(pair.model_points) and np.all(np.diff(kv) > 0)
  assert main([str(path), "--out", str(tmp_path / "a.npz"), "--keypoints", "all",
               "--method", "toldi"]) == 0
  assert len(np.load(tmp_path / "a.npz")["keypoints"]) == len(pair.model_points)


@pytest.mark.parametrize("args,fragment", [
    (["--method", "nope"], "--method"), (["--keypoints", "ten"], "--keypoints"),
    (["--keypoints", "0"], "--keypoints"), (["--radius-mr", "-1"], "--radius-mr"),
    (["--descriptor", "sift"], "--descriptor"), (["--png", "/nonexistent/dir/f.png"], "--png")])
def test_bad_arguments_exit_2_before_any_work(demo_ply, tmp_path, capsys, args, fragment):
  path, _ = demo_ply
  assert main([str(path), "--out", str(tmp_path / "f.npz")] + args) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: ") and fragment in err
  assert not (tmp_path / "f.npz").exists()


def test_missing_file_and_out_folder(tmp_path, capsys):
  assert main([str(tmp_path / "none.ply"), "--out", str(tmp_path / "f.npz")]) == 2
  assert "none.ply" in capsys.readouterr().err
  assert main([str(tmp_path / "none.ply"), "--out", str(tmp_path / "no" / "f.npz")]) == 2
  assert "--out" in capsys.readouterr().err


def test_help_names_the_program():
  assert build_parser().format_usage().startswith("usage: lrf-frames")
