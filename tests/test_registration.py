"""Pose estimation: Kabsch, one-correspondence poses, the two RANSAC estimators, register(), and
register's bad arguments refused by name (a seeded fuzz judged by `tests.lrf_testing.judge`, and
one regression test per bug it found)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import lrf_jax
from lrf_jax import datasets, io
from lrf_jax.registration import estimators, pipeline
from lrf_jax.geometry.ops import kabsch
from lrf_jax.registration import (icp, lrf_ransac, pose_errors, pose_from_correspondence,
                                  ransac_3point, register, rotation_error_deg, to_transform)
from tests.lrf_testing import random_rotation
from pathlib import Path
from scipy.spatial.transform import Rotation
from tests.lrf_testing import (FUZZ_CASES, FUZZ_SEED, Case, check_registration, pick, rejects,
                               run_cases, short_repr)


def _rigid(seed: int) -> tuple[np.ndarray, np.ndarray]:
  return random_rotation(seed), np.random.default_rng(seed).normal(size=3) * 2.0


def test_kabsch_recovers_a_known_transform():
  rot, t = _rigid(0)
  src = np.random.default_rng(1).normal(size=(40, 3))
  r, tt = kabsch(src.astype(np.float32), (src @ rot.T + t).astype(np.float32))
  np.testing.assert_allclose(np.asarray(r), rot, atol=2e-5)
  np.testing.assert_allclose(np.asarray(tt), t, atol=2e-5)
  assert np.linalg.det(np.asarray(r)) == pytest.approx(1.0, abs=1e-5)


def test_one_correspondence_with_exact_frames_recovers_the_transform():
  rot, t = _rigid(2)
  f_src = random_rotation(3)            # any frame (rows x, y, z)
  f_dst = f_src @ rot.T                 # the equivariance convention: rows rotate with the cloud
  p = np.array([0.3, -1.2, 0.7])
  r, tt = pose_from_correspondence(p, f_src, rot @ p + t, f_dst, scale=0.5)
  np.testing.assert_allclose(np.asarray(r), rot, atol=2e-6)
  np.testing.assert_allclose(np.asarray(tt), t, atol=2e-5)
  # Independent of the arm length for exact frames.
  r2, t2 = pose_from_correspondence(p, f_src, rot @ p + t, f_dst, scale=7.0)
  np.testing.assert_allclose(np.asarray(r2), rot, atol=2e-6)
  np.testing.assert_allclose(np.asarray(t2), t, atol=2e-5)


def test_pose_errors():
  rot = datasets.rotation_matrix(np.array([1.0, 2.0, -0.5]), 37.0)
  est = to_transform(rot, [0.0, 0.3, 0.4])
  err_r, err_t = pose_errors(est, np.eye(4), mr=0.1)
  assert err_r == pytest.approx(37.0, abs=1e-6)
  assert err_t == pytest.approx(5.0)
  assert rotation_error_deg(np.eye(3), np.eye(3)) == 0.0
  assert rotation_error_deg(np.diag([1.0, -1, -1]), np.eye(3)) == pytest.approx(180.0)


def _synthetic_correspondences(seed: int, m: int = 80, outliers: float = 0.6):
  rng = np.random.default_rng(seed)
  rot, t = _rigid(seed)
  src = rng.uniform(-1, 1, (m, 3))
  dst = src @ rot.T + t + rng.normal(scale=0.002, size=(m, 3))
  f_src = np.stack([random_rotation(seed * 1000 + i) for i in range(m)])
  f_dst = f_src @ rot.T
  bad = rng.random(m) < outliers
  dst[bad] = rng.uniform(-3, 3, (bad.sum(), 3))
  f_dst[bad] = np.stack([random_rotation(7 + i) for i in range(int(bad.sum()))])
  return src, dst, f_src, f_dst, to_transform(rot, t), bad


def test_both_estimators_recover_a_pose_among_outliers_deterministically():
  src, dst, f_src, f_dst, gt, bad = _synthetic_correspondences(4)
  a = lrf_ransac(src, dst, f_src, f_dst, inlier_threshold=0.02, scale=0.2, iterations=100,
                 seed=0)
  b = ransac_3point(src, dst, inlier_threshold=0.02, iterations=1000, seed=0)
  for res in (a, b):
    err_r, err_t = pose_errors(res.transform, gt, mr=0.01)
    assert err_r < 0.5 and err_t < 1.0
    np.testing.assert_array_equal(res.inliers, ~bad)
  again = lrf_ransac(src, dst, f_src, f_dst, inlier_threshold=0.02, scale=0.2, iterations=100,
                     seed=0)
  np.testing.assert_array_equal(again.transform, a.transform)
  assert again.best_hypothesis == a.best_hypothesis
  # Without the refit the LRF estimate is exactly the winning correspondence's pose.
  c = lrf_ransac(src, dst, f_src, f_dst, inlier_threshold=0.02, scale=0.2, iterations=100,
                 seed=0, refine=False)
  assert c.hypothesis_inliers == c.n_inliers


def test_host_hypotheses_and_scores_agree_with_the_jitted_ones():
  """register's host steps (registration.host) against the jitted vmap programs of lrf_ransac
  and ransac_3point on the same centred float32 correspondences."""
  import jax
  from lrf_jax.registration import host
  src, dst, f_src, f_dst, _, _ = _synthetic_correspondences(5, m=300)
  s, d, _, _ = estimators.centred(src, dst)
  rs, ts = host.lrf_hypotheses(s, f_src, d, f_dst, 0.2)
  rj, tj = estimators._lrf_hypotheses(s, f_src.astype(np.float32), d,
                                        f_dst.astype(np.float32), 0.2)
  np.testing.assert_allclose(rs, np.asarray(rj), atol=2e-5)
  np.testing.assert_allclose(ts, np.asarray(tj), atol=2e-5)
  np.testing.assert_allclose(np.linalg.det(rs), 1.0, atol=1e-12)
  triples = np.random.default_rng(0).integers(0, 300, (200, 3))
  rk, tk = host.kabsch_batch(s[triples], d[triples])
  rkj, tkj = estimators._kabsch_batch(s[triples], d[triples])
  ok = np.linalg.svd(s[triples] - s[triples].mean(1, keepdims=True))[1][:, 1] > 0.05
  np.testing.assert_allclose(rk[ok], np.asarray(rkj)[ok], atol=1e-4)  # well-posed triples
  thr = 0.02
  counts = host.count_inliers(rs, ts, s, d, thr)
  cj = np.asarray(jax.vmap(lambda r, t: estimators._inlier_mask(r, t, s, d, thr).sum())(
      rj, tj))
  assert counts.max() > 50 and np.abs(counts - cj).max() <= 1  # float32 rounding at the edge
  best = int(np.argmax(counts))
  r, t, mask = host.select_and_refine(rs[best], ts[best], s, d, thr)
  r2, t2, mask2, _, _ = estimators._select_and_refine(rj[best:best + 1], tj[best:best + 1],
                                                        s, d, thr, True)
  np.testing.assert_allclose(r, np.asarray(r2), atol=1e-5)
  np.testing.assert_allclose(t, np.asarray(t2), atol=1e-5)
  np.testing.assert_array_equal(mask, np.asarray(mask2))


@pytest.mark.data
def test_noise_free_br_one_correspondence_is_exact(br_bunny):
  """BR bunny model vs the model under its ground truth: LRF-Net frames of corresponding
  keypoints are equivariant, so every single correspondence gives the pose (< 0.1 deg, 0.1 mr)."""
  points, _, mr, xf = br_bunny
  scene = datasets.transform_points(xf, points)
  kp = np.sort(np.random.default_rng(0).choice(len(points), 40, replace=False))
  radius = 15 * mr
  fm, vm = lrf_jax.compute_frames(points, kp, radius, "lrf_net")
  fs, vs = lrf_jax.compute_frames(scene, kp, radius, "lrf_net")
  ok = np.asarray(vm) & np.asarray(vs)
  assert ok.sum() >= 38
  for i in np.flatnonzero(ok):
    r, t = pose_from_correspondence(points[kp[i]], np.asarray(fm)[i], scene[kp[i]],
                                    np.asarray(fs)[i], scale=radius)
    # pose_from_correspondence runs in float32 on absolute coordinates (~0.1 m): fine at 0.1 mr.
    err_r, err_t = pose_errors(to_transform(np.asarray(r), np.asarray(t)), xf, mr)
    assert err_r < 0.1 and err_t < 0.1, (i, err_r, err_t)
  res = lrf_ransac(points[kp], scene[kp], np.asarray(fm), np.asarray(fs), valid=ok,
                   inlier_threshold=2 * mr, scale=radius, iterations=100, seed=0)
  err_r, err_t = pose_errors(res.transform, xf, mr)
  assert err_r < 0.1 and err_t < 0.1
  assert res.n_inliers == len(kp)


@pytest.mark.data
def test_register_consecutive_bunny_scans(data_root):
  pair = datasets.load_bunny_pairs(data_root)[0]
  reg = register(pair.model_points, pair.scene_points, seed=0)
  err_r, err_t = pose_errors(reg.transform, pair.transform, pair.mr)
  assert err_r < 5.0, (err_r, err_t)
  assert reg.transform.shape == (4, 4) and reg.n_inliers >= 3
  assert reg.inliers.shape == (len(reg.correspondences),)


@pytest.mark.data
def test_register_scans_with_viewpoints_and_lrf_net_plus(data_root):
  """Sensor positions orient the scans' normals; lrf_net_plus with SHOT descriptors registers."""
  pair = datasets.load_bunny_pairs(data_root)[0]
  reg = register(pair.model_points, pair.scene_points, seed=0, method="lrf_net_plus",
                 descriptor="shot", n_keypoints=1500, source_viewpoint=pair.model_viewpoint,
                 target_viewpoint=pair.scene_viewpoint)
  err_r, err_t = pose_errors(reg.transform, pair.transform, pair.mr)
  assert err_r < 5.0, (err_r, err_t)
  with pytest.raises(ValueError, match="source_viewpoint: expected a finite"):
    register(pair.model_points, pair.scene_points, source_viewpoint=[0.0, 1.0])


def test_register_cli_on_demo_files(tmp_path):
  """The CLI reads two PLY files and writes the 4x4 transform (synthetic data: no download)."""
  from lrf_jax import io
  from lrf_jax.cli.register import main
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  src, dst = tmp_path / "a.ply", tmp_path / "b.ply"
  io.write_ply(src, pair.model_points, dtype="float64")
  io.write_ply(dst, pair.scene_points, dtype="float64")
  out = tmp_path / "T.txt"
  assert main([str(src), str(dst), "--out", str(out), "--keypoints", "1000",
               "--correspondences", "300", "--mr", str(pair.mr)]) == 0
  est = np.loadtxt(out)
  err_r, err_t = pose_errors(est, pair.transform, pair.mr)
  assert err_r < 2.0 and err_t < 5.0, (err_r, err_t)
  assert main([str(tmp_path / "missing.ply"), str(dst)]) == 2


def test_console_entry_flushes_its_output_and_keeps_the_exit_code(tmp_path):
  """`lrf-register` / `lrf-frames` end with os._exit after flushing (no interpreter teardown):
  what main printed arrives, its return code is the process's, argparse's exits too."""
  import subprocess
  import sys
  code = ("import sys; from lrf_jax.cli.console import run; "
          "run(lambda: (print('out'), print('err', file=sys.stderr), 3)[2])")
  done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
  assert (done.returncode, done.stdout, done.stderr) == (3, "out\n", "err\n")
  bad = subprocess.run([sys.executable, "-c", "from lrf_jax.cli.console import register; register()",
                        str(tmp_path / "missing.ply"), str(tmp_path / "b.ply")],
                       capture_output=True, text=True)
  assert bad.returncode == 2 and "no such file" in bad.stderr
  usage = subprocess.run([sys.executable, "-c", "from lrf_jax.cli.console import frames; frames()",
                          "--no-such-flag"], capture_output=True, text=True)
  assert usage.returncode == 2 and "usage: lrf-frames" in usage.stderr


def test_register_cli_rejects_bad_paths_before_any_work(tmp_path, capsys):
  from lrf_jax.cli.register import build_parser, main
  a = tmp_path / "a.ply"
  a.write_text("not read: the path check comes first")
  assert main([str(a), str(a), "--out", str(tmp_path / "missing" / "T.txt")]) == 2
  assert "--out: the folder" in capsys.readouterr().err
  assert main([str(a), str(a), "--checkpoint", str(tmp_path / "nonexistent")]) == 2
  assert "--checkpoint:" in capsys.readouterr().err
  assert build_parser().format_usage().startswith("usage: lrf-register")


def test_registration_reports_every_stage(tmp_path):
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  reg = register(pair.model_points, pair.scene_points, n_keypoints=800, n_correspondences=200,
                 mr=pair.mr)
  assert list(reg.timings) == ["prepare", "frames", "descriptors", "matching", "hypotheses",
                               "verification", "icp"]
  assert all(t >= 0 for t in reg.timings.values())
  assert sum(reg.timings.values()) <= reg.seconds + 1e-6


def test_bad_inputs_raise_clear_errors():
  src, dst, f_src, f_dst, _, _ = _synthetic_correspondences(5, m=10)
  with pytest.raises(ValueError, match=r"same shape \(M, 3\)"):
    ransac_3point(src, dst[:5], inlier_threshold=0.1)
  with pytest.raises(ValueError, match="at least 3"):
    ransac_3point(src[:2], dst[:2], inlier_threshold=0.1)
  with pytest.raises(ValueError, match="iterations"):
    ransac_3point(src, dst, inlier_threshold=0.1, iterations=0)
  with pytest.raises(ValueError, match="inlier_threshold"):
    lrf_ransac(src, dst, f_src, f_dst, inlier_threshold=-1.0, scale=1.0)
  with pytest.raises(ValueError, match=r"frames: expected .*\(10, 3, 3\)"):
    lrf_ransac(src, dst, f_src[:3], f_dst, inlier_threshold=0.1, scale=1.0)
  with pytest.raises(ValueError, match="none has two valid frames"):
    lrf_ransac(src, dst, f_src, f_dst, inlier_threshold=0.1, scale=1.0,
               valid=np.zeros(10, bool))
  with pytest.raises(ValueError, match="finite"):
    ransac_3point(np.full((5, 3), np.nan), dst[:5], inlier_threshold=0.1)
  with pytest.raises(ValueError, match=r"source: expected shape \(n, 3\)"):
    register(np.zeros((100, 2)), np.zeros((100, 3)))
  with pytest.raises(ValueError, match="target: .*at least 10 points"):
    register(np.random.default_rng(0).normal(size=(100, 3)), np.zeros((3, 3)))
  with pytest.raises(ValueError, match="estimator"):
    register(np.random.default_rng(0).normal(size=(100, 3)),
             np.random.default_rng(1).normal(size=(100, 3)), estimator="4point")
  with pytest.raises(FileNotFoundError, match="nowhere.ply"):
    register("/nowhere.ply", np.zeros((100, 3)))
  with pytest.raises(ValueError, match="transform_est"):
    pose_errors(np.eye(3), np.eye(4), 1.0)


def test_icp_refines_a_small_misalignment():
  """A bumpy, irregularly sampled height field (no symmetry, no grid aliasing) moved by 3 deg."""
  rng = np.random.default_rng(0)
  x, y = rng.uniform(-1, 1, (2, 20000))
  pts = np.stack([x, y, 0.3 * np.sin(3 * x) * np.cos(2 * y) + 0.2 * x ** 2], axis=1)
  gt = to_transform(datasets.rotation_matrix(np.array([0.3, 1.0, 0.2]), 3.0), [0.01, -0.02, 0.005])
  target = datasets.transform_points(gt, pts)
  est, fitness, rmse = icp(pts[::5], target, np.eye(4), max_distance=0.1, iterations=60)
  err_r, err_t = pose_errors(est, gt, mr=0.01)
  assert err_r < 1e-3 and err_t < 1e-3 and fitness == 1.0 and rmse < 1e-9
  tree = cKDTree(target)
  fits = pipeline.overlap_scores(np.stack([est[:3, :3], np.eye(3)]),
                                     np.stack([est[:3, 3], np.zeros(3)]), pts[::5], tree, 0.005)
  assert fits[0] == 1.0 and fits[1] < 0.5


def test_pose_protocol_on_a_rigidly_moved_cloud():
  """Scene = model under a rigid motion: both estimators recover it from the matched keypoints;
  the records carry the documented fields and serialise to JSON."""
  import json

  from lrf_jax.evaluation.pose import evaluate_pose_pair, pose_report
  pts, faces = datasets.make_demo_mesh("blob", 0)
  mr, _ = datasets.mesh_resolution(pts, faces)
  tr = to_transform(random_rotation(8), [0.5, -1.0, 2.0])
  pair = datasets.Pair("moved", "demo", pts, datasets.transform_points(tr, pts), faces, faces,
                       tr, mr, "mean_edge_length", "index")
  recs = evaluate_pose_pair(pair, n_keypoints=120, n_correspondences=50, seed=1)
  json.dumps(recs)
  assert [r["method"] for r in recs] == ["lrf_ransac", "ransac_3point"]
  assert [r["setting"]["iterations"] for r in recs] == [100, 1000]
  for r in recs:
    assert r["experiment"] == "pose" and r["n_correspondences"] == 50
    assert r["n_correct_correspondences"] == 50 and r["n_inliers"] == 50
    assert r["err_r"] < 0.05 and r["err_t"] < 0.05
  assert "| demo | lrf_ransac | 1 |" in pose_report(recs)


def test_verdict_rule_of_the_one_point_estimator():
  """"lrf" answers to the default's rule: far above both chance and the best distinct pose (its
  old overlap-contrast escape claimed blobs and mirror images)."""
  from lrf_jax.registration.evidence import Evidence, verdict

  def ok(n, chance, fitness, contrast, rival=0):
    return verdict(Evidence(n, chance, rival, fitness, contrast, "lrf"))[0]
  assert ok(40, 5, 0.6, 1.0)            # far above the chance level
  assert not ok(7, 7, 0.42, 2.1)        # few inliers: an overlap that stands out is not enough
  assert not ok(54, 36, 0.98, 1.0)      # blobs: chance reaches nearly as many inliers
  assert not ok(9, 5, 0.37, 1.3)        # a mirror image
  assert not ok(40, 5, 0.6, 1.0, 20)    # a distinct pose explains 20 others
  assert not ok(400, 5, 0.04, 3.0)      # ICP pairs almost nothing


def test_register_verdict_on_a_real_pair_and_on_unrelated_blobs(tmp_path, capsys):
  from lrf_jax import io
  from lrf_jax.cli.register import main
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  good = register(pair.model_points, pair.scene_points, n_keypoints=800, n_correspondences=200,
                  mr=pair.mr)
  assert good.success is True and good.n_inliers > good.chance_inliers
  rng = np.random.default_rng(0)
  a, b = rng.normal(size=(4000, 3)), rng.normal(size=(4000, 3))
  bad = register(a, b, n_keypoints=800, n_correspondences=200)
  assert bad.success is False, (bad.n_inliers, bad.chance_inliers, bad.overlap_contrast)
  io.write_ply(tmp_path / "a.ply", a, dtype="float64")
  io.write_ply(tmp_path / "b.ply", b, dtype="float64")
  assert main([str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--keypoints", "800",
               "--correspondences", "200"]) == 3
  assert "verdict: NOT SURE" in capsys.readouterr().err


# ----------------- register arguments: the fuzz (few: a valid call is slow) and its regressions


N_POINTS = 300
_PTS = np.random.default_rng(0).normal(size=(N_POINTS, 3))


def test_fuzz_register_arguments(tmp_path: Path) -> None:
  """FUZZ_CASES["register"] bad (and two valid) argument sets to register, on 300-point clouds."""
  rng = np.random.default_rng([FUZZ_SEED, 7])
  src = rng.normal(size=(N_POINTS, 3))
  dst = src @ Rotation.random(random_state=1).as_matrix().T + 0.1
  nan = src.copy()
  nan[int(rng.integers(0, N_POINTS)), 1] = np.nan
  path = io.write_ply(tmp_path / "target.ply", dst, dtype="float64")
  fast = {"n_keypoints": 60, "n_correspondences": 30, "icp_iterations": 3}
  draws = [
      ("source NaN", {"source": nan}, "source"),
      ("target shape", {"target": dst[:, :2]}, "target"),
      ("source 5 points", {"source": src[:5]}, "source"),
      ("n_keypoints", {"n_keypoints": pick(rng, ["a", 0, 2.5, None, -3])}, "n_keypoints"),
      ("radius_mr", {"radius_mr": pick(rng, ["x", 0, np.nan, None, -1.0])}, "radius_mr"),
      ("verify", {"verify": pick(rng, [2.5, -1, "a", [1]])}, "verify"),
      ("iterations", {"iterations": pick(rng, [None, 0, "10", 1.5])}, "iterations"),
      ("method", {"method": pick(rng, ["nope", ["toldi"], None])}, "method"),
      ("descriptor", {"descriptor": pick(rng, ["nope", ["toldi"], 3])}, "descriptor"),
      ("estimator", {"estimator": pick(rng, ["4point", None, ["lrf"]])}, "estimator"),
      ("source_viewpoint", {"source_viewpoint": pick(rng, [np.zeros(2), [0, 0, np.nan], "a"])},
       "source_viewpoint"),
      ("mr", {"mr": pick(rng, [-1.0, np.nan, "x", 0])}, "mr"),
      ("icp_iterations", {"icp_iterations": pick(rng, [-1, 0.5, "3", None])}, "icp_iterations"),
      ("seed", {"seed": pick(rng, ["x", None, 1.5])}, "seed"),
  ]
  cases = [Case(f"register {label} {short_repr(kw)[:60]}",
                lambda a={"source": src, "target": dst} | fast | kw: lrf_jax.register(**a),
                name, check_registration, "error", file=False) for label, kw, name in draws]
  for label, kw in (("valid arrays", {}), ("valid target path", {"target": str(path)})):
    cases.append(Case(f"register {label}", lambda a={"source": src, "target": dst} | fast | kw:
                      lrf_jax.register(**a), "", check_registration, "result", file=False))
  run_cases(cases, FUZZ_CASES["register"])


@pytest.mark.parametrize("kw, name", [
    ({"n_keypoints": None}, "n_keypoints"),  # TypeError from int()
    ({"n_correspondences": "a"}, "n_correspondences"),  # ValueError from int(), unnamed
    ({"verify": [1]}, "verify"),  # TypeError from int()
    ({"radius_mr": "x"}, "radius_mr"),  # TypeError from np.isfinite
    ({"mr": "x"}, "mr"),
    ({"method": ["toldi"]}, "method"),  # TypeError: unhashable type: 'list'
    ({"descriptor": ["toldi"]}, "descriptor"),
    ({"seed": "x"}, "seed"),  # TypeError from numpy's SeedSequence
    ({"icp_iterations": None}, "icp_iterations"),  # TypeError inside icp
])
def test_regression_register_arguments(kw: dict, name: str) -> None:
  args = {"source": _PTS, "target": _PTS + 0.1} | kw
  rejects(lambda: lrf_jax.register(**args), name, file=False)


@pytest.mark.parametrize("kw", [
    {"n_keypoints": 10, "n_correspondences": 1, "inlier_mr": 1e-6, "ratio": 0.9},
    {"n_keypoints": 200, "n_correspondences": 40, "inlier_mr": 1e-9},
])
def test_regression_register_without_a_hypothesis(kw: dict) -> None:
  """The graph estimator builds no hypothesis when no two correspondences are compatible (one
  correspondence, or a tiny inlier distance): `register` raised IndexError in its verification.
  It returns the identity, not sure, with the reason, and `estimated` False."""
  pair = lrf_jax.datasets.make_demo_pair(0)
  reg = lrf_jax.register(pair.model_points, pair.scene_points, **kw)
  assert not reg.estimated and not reg.success and reg.n_inliers == 0
  np.testing.assert_array_equal(reg.transform, np.eye(4))
  np.testing.assert_array_equal(reg.coarse_transform, np.eye(4))
  assert reg.reason.startswith("no pose hypothesis: ") and "identity" in reg.reason
  assert len(reg.correspondences) == len(reg.inliers) and not reg.inliers.any()
  assert 0.0 <= reg.overlap <= 1.0 and "no pose hypothesis" in reg.summary()


def test_a_voxel_size_that_leaves_no_cloud_is_named():
  """Before: voxel_size=1e300 thinned each cloud to one point and register said "only 0
  descriptor matches ... too sparse for r = 15.0 mr"; 1e-20 was voxel_downsample's error."""
  from lrf_jax import datasets
  from lrf_jax.registration import register
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.05, partial=True)
  with pytest.raises(ValueError, match=r"^voxel_size: voxels of 1e\+300 leave 1 points"):
    register(pair.model_points, pair.scene_points, voxel_size=1e300)
  with pytest.raises(ValueError, match=r"^voxel_size: size 1e-20 is too small"):
    register(pair.model_points, pair.scene_points, voxel_size=1e-20)
