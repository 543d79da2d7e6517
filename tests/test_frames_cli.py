"""lrf-frames: frames for one's own file, its outputs, its figure and its clean errors."""

import numpy as np
import pytest

from lrf_jax import datasets, io
from lrf_jax.cli.frames import build_parser, main


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
                          "weights", "descriptors", "confidence"}
  m = len(z["keypoints"])
  conf = z["confidence"]  # lrf_net_plus's sign confidence, 0 where the frame is invalid
  assert conf.shape == (m,) and (conf >= 0).all() and (conf <= 1).all()
  assert (conf[~z["valid"]] == 0).all()
  assert m == 200 and z["frames"].shape == (m, 3, 3) and z["valid"].shape == (m,)
  np.testing.assert_allclose(z["positions"], pair.model_points[z["keypoints"]])
  assert str(z["method"]) == "lrf_net_plus" and str(z["weights"]) == "lrf_net_plus"
  assert float(z["radius"]) == pytest.approx(15 * float(z["mr"]))
  assert z["valid"].mean() > 0.9 and z["descriptors"].shape[0] == m
  det = np.linalg.det(z["frames"][z["valid"]])
  np.testing.assert_allclose(det, 1.0, atol=1e-4)
  assert png.stat().st_size > 10_000


def test_weights_flag_reads_a_parameter_file(demo_ply, tmp_path):
  """--weights PATH: the frames of that file (as compute_frames(weights=PATH)), named in the
  .npz's weights field; the default reads the method's own shipped file."""
  import shutil
  from lrf_jax.frames.weights import WEIGHTS_DIR
  path, _ = demo_ply
  w = tmp_path / "mine.msgpack"
  shutil.copy(WEIGHTS_DIR / "lrf_net.msgpack", w)
  assert main([str(path), "--out", str(tmp_path / "a.npz"), "--keypoints", "100"]) == 0
  assert main([str(path), "--out", str(tmp_path / "b.npz"), "--keypoints", "100",
               "--weights", str(w)]) == 0
  a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
  assert str(b["weights"]) == str(w) and str(a["weights"]) == "lrf_net_plus"
  np.testing.assert_array_equal(a["keypoints"], b["keypoints"])
  assert np.abs(a["frames"] - b["frames"]).max() > 1e-3


def test_voxel_and_all_keypoints(demo_ply, tmp_path):
  path, pair = demo_ply
  assert main([str(path), "--out", str(tmp_path / "v.npz"), "--keypoint-voxel-mr", "10",
               "--method", "toldi"]) == 0
  kv = np.load(tmp_path / "v.npz")["keypoints"]
  assert 10 < len(kv) < len(pair.model_points) and np.all(np.diff(kv) > 0)
  assert main([str(path), "--out", str(tmp_path / "a.npz"), "--keypoints", "all",
               "--method", "toldi"]) == 0
  assert len(np.load(tmp_path / "a.npz")["keypoints"]) == len(pair.model_points)


@pytest.mark.parametrize("args,fragment", [
    (["--method", "nope"], "--method"), (["--keypoints", "ten"], "--keypoints"),
    (["--keypoints", "0"], "--keypoints"), (["--radius-mr", "-1"], "--radius-mr"),
    (["--descriptor", "sift"], "--descriptor"), (["--png", "/nonexistent/dir/f.png"], "--png"),
    (["--weights", "nowhere"], "--weights: 'nowhere' is not one of"),
    (["--method", "toldi", "--weights", "rooms"], "--weights: method 'toldi' is hand-crafted")])
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


@pytest.mark.parametrize("method", ["rops", "gframes"])
def test_mesh_methods_get_the_faces_of_a_ply_mesh(demo_ply, tmp_path, method):
  """A PLY with faces works for the methods that need a mesh (the faces reach compute_frames)."""
  path, pair = demo_ply
  out = tmp_path / "m.npz"
  assert main([str(path), "--out", str(out), "--keypoints", "50", "--method", method]) == 0
  z = np.load(out)
  assert str(z["method"]) == method and z["valid"].mean() > 0.9


@pytest.fixture(scope="module")
def demo_scans(tmp_path_factory):
  """Two partial, noisy scans of one demo object and the ground truth between them, as files."""
  pair = datasets.make_demo_pair(0, noise_mr=0.1, partial=True)
  folder = tmp_path_factory.mktemp("pair")
  a, b, gt = folder / "a.ply", folder / "b.ply", folder / "a_to_b.txt"
  io.write_ply(a, pair.model_points, pair.model_faces)
  io.write_ply(b, pair.scene_points, pair.scene_faces)
  np.savetxt(gt, pair.transform)
  return a, b, gt, pair


def test_pair_gives_meancos_and_the_repeatability_figure(demo_scans, tmp_path, capsys):
  a, b, gt, pair = demo_scans
  out, png = tmp_path / "ab.npz", tmp_path / "ab.png"
  assert main([str(a), "--pair", str(b), "--gt", str(gt), "--out", str(out), "--keypoints",
               "150", "--png", str(png)]) == 0
  z = np.load(out)
  kp, kb = z["keypoints"], z["pair_keypoints"]
  assert len(kp) == len(kb) == 150 and z["meancos"].shape == (150,)
  assert z["confidence"].shape == z["pair_confidence"].shape == (150,)
  # the corresponding points are where the ground truth puts the keypoints (within 0.5 mr)
  moved = datasets.transform_points(pair.transform, pair.model_points[kp])
  assert np.linalg.norm(moved - pair.scene_points[kb], axis=1).max() <= 0.5 * float(z["mr"])
  import lrf_jax
  want = np.asarray(lrf_jax.meancos(z["frames"], z["pair_frames"], pair.transform, z["valid"],
                                    z["pair_valid"]))
  np.testing.assert_allclose(z["meancos"], want, atol=1e-6)
  assert z["meancos"].mean() > 0.8  # lrf_net_plus repeats on this easy pair
  err = capsys.readouterr().err
  assert f"mean MeanCos {z['meancos'].mean():.3f}" in err
  assert png.stat().st_size > 20_000


def test_pair_and_gt_go_together(demo_scans, tmp_path, capsys):
  a, b, gt, _ = demo_scans
  assert main([str(a), "--pair", str(b), "--out", str(tmp_path / "x.npz")]) == 2
  assert "--pair and --gt" in capsys.readouterr().err
  far = tmp_path / "far.txt"
  t = np.eye(4)
  t[:3, 3] = 1e3
  np.savetxt(far, t)
  assert main([str(a), "--pair", str(b), "--gt", str(far), "--out", str(tmp_path / "x.npz")]) == 2
  assert "--gt" in capsys.readouterr().err
  assert not (tmp_path / "x.npz").exists()


def test_help_shows_the_defaults():
  text = " ".join(build_parser().format_help().split())
  assert "(default: 15.0)" in text and "(default: lrf_net_plus)" in text
  assert "confidence (m,) in [0, 1]" in text  # the .npz field is documented
