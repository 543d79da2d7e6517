"""What a user reads of a registration: its repr, summary(), the CLI's lines and --png figure."""

import numpy as np
import pytest

from lrf_jax import datasets, io
from lrf_jax.cli.register import build_parser, main
from lrf_jax.registration import Registration
from lrf_jax.registration.evidence import Evidence


def _registration(**kw):
  base = dict(transform=np.eye(4), coarse_transform=np.eye(4), inliers=np.ones(500, bool),
              n_inliers=40, correspondences=np.zeros((500, 2), np.int64), fitness=0.6,
              rmse=0.002, mr=0.004, seconds=1.25, timings={"frames": 0.7, "icp": 0.2},
              success=True, reason="40 consistent correspondences; chance gives 5",
              overlap=0.6, chance_inliers=5, rival_inliers=3, overlap_contrast=1.03)
  base.update(kw)
  return Registration(**base)


def test_repr_is_one_short_line_without_arrays():
  text = repr(_registration())
  assert "\n" not in text and len(text) < 160
  assert "success" in text and "60.0%" in text and "40/500" in text and "1.25 s" in text
  assert "array" not in text
  assert "not sure" in repr(_registration(success=False))


def test_summary_says_verdict_reason_overlap_inliers_time_and_errors_when_known():
  reg = _registration()
  text = reg.summary()
  assert text.splitlines()[0] == "verdict: success: " + reg.reason
  assert "estimated overlap 60.0%" in text and "inliers 40 of 500" in text
  assert "chance level 5" in text and "time 1.25 s (frames 0.70, icp 0.20)" in text
  assert "error" not in text and "contrast" not in text
  gt = np.eye(4)
  gt[:3, 3] = [0.008, 0, 0]  # 2 mr away
  # in mr and in the clouds' units (mr 0.004: 2 mr is 0.008)
  assert "error against the ground truth: 0 deg, 2 mr (0.008 in the clouds' units)" in \
      reg.summary(gt=gt)
  assert _registration(success=False).summary().startswith("verdict: NOT SURE")
  assert "thinned" not in text  # every point kept: nothing to say
  thinned = _registration(voxel_size=0.0075).summary()
  assert "thinned at voxels of 0.0075 first (voxel_size=0 keeps every point)" in thinned


def test_verdict_says_what_decided_in_words_and_as_a_code():
  from lrf_jax.registration.evidence import decide
  d = decide(Evidence(7, 7, 0, 0.42, 2.1, "lrf"))
  assert not d.success and d.code == "chance" and "contrast" not in d.reason
  d = decide(Evidence(40, 3, 2, 0.42, 1.03, "lrf"))
  assert d.success and d.code == "claimed" and d.reason.startswith("40 consistent")


@pytest.fixture(scope="module")
def demo_files(tmp_path_factory):
  pair = datasets.make_demo_pair(0, noise_mr=0.0, partial=True)
  folder = tmp_path_factory.mktemp("reg")
  a, b = folder / "a.ply", folder / "b.ply"
  io.write_ply(a, pair.model_points)
  io.write_ply(b, pair.scene_points)
  return a, b, pair


def test_cli_prints_the_summary_and_draws_the_correspondences(demo_files, tmp_path, capsys):
  a, b, _ = demo_files
  png = tmp_path / "corr.png"
  code = main([str(a), str(b), "--keypoints", "600", "--correspondences", "300", "--png",
               str(png)])
  err = capsys.readouterr().err
  assert code in (0, 3)
  assert "# verdict: " in err and "# estimated overlap" in err and "# time" in err
  assert "contrast" not in err
  assert png.stat().st_size > 20_000 and f"figure: {png}" in err


def test_cli_png_is_checked_before_any_work(demo_files, tmp_path, capsys):
  a, b, _ = demo_files
  assert main([str(a), str(b), "--png", str(tmp_path / "corr.txt")]) == 2
  assert "--png" in capsys.readouterr().err
  assert main([str(a), str(b), "--out", str(tmp_path / "t.png"), "--png",
               str(tmp_path / "t.png")]) == 2
  assert "refusing to overwrite" in capsys.readouterr().err


def test_help_shows_the_defaults():
  text = " ".join(build_parser().format_help().split())
  assert "(default: 3000)" in text and "(default: graph)" in text
  assert "(default: None)" not in text


def test_cli_out_is_written_on_success_only_unless_best_guess(demo_files, tmp_path, capsys):
  """A script that does not read exit codes used the transform of a "not sure" pair: --out now
  writes nothing on exit 3 unless --best-guess asks for the transform anyway."""
  a, b, _ = demo_files
  rng = np.random.default_rng(0)
  blob_a, blob_b = tmp_path / "blob_a.ply", tmp_path / "blob_b.ply"
  io.write_ply(blob_a, rng.normal(size=(3000, 3)), dtype="float64")
  io.write_ply(blob_b, rng.normal(size=(3000, 3)), dtype="float64")
  small = ["--keypoints", "600", "--correspondences", "300"]
  out = tmp_path / "T.txt"
  assert main([str(blob_a), str(blob_b), "--out", str(out), *small]) == 3
  assert not out.exists() and "--best-guess" in capsys.readouterr().err
  assert main([str(blob_a), str(blob_b), "--out", str(out), "--best-guess", *small]) == 3
  assert np.loadtxt(out).shape == (4, 4)
  good = tmp_path / "good.txt"
  assert main([str(a), str(b), "--out", str(good), *small]) == 0
  assert np.loadtxt(good).shape == (4, 4)
