"""The repeatability protocol, MeanCos, and the report/figures."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lrf_jax
from lrf_jax import datasets, evaluation
from lrf_jax.evaluation import MethodRun, PatchCache, evaluate_pair
from tests.lrf_testing import random_rotation


def test_meancos_identical_frames_is_one_and_known_angle_gives_its_cosine():
  frames = np.stack([random_rotation(i) for i in range(5)])
  np.testing.assert_allclose(lrf_jax.meancos(frames, frames, np.eye(3)), 1.0, atol=1e-6)
  theta = 0.7
  rz = Rotation.from_rotvec([0, 0, theta]).as_matrix()  # rotate each frame about its own z
  turned = np.einsum("ij,njk->nik", rz, frames)
  np.testing.assert_allclose(lrf_jax.meancos(frames, turned, np.eye(3)),
                             (np.cos(theta) + 1) / 2, atol=1e-6)
  rot = random_rotation(9)  # a scene frame under the ground truth maps back exactly
  np.testing.assert_allclose(lrf_jax.meancos(frames, frames @ rot.T, rot), 1.0, atol=1e-6)
  valid = np.array([True, False, True, True, True])
  assert float(lrf_jax.meancos(frames, frames, np.eye(3), valid)[1]) == 0.0
  with pytest.raises(ValueError, match="rotation"):
    lrf_jax.meancos(frames, frames, np.eye(2))


@pytest.fixture(scope="module")
def demo_pair():
  return datasets.make_demo_pair(0, seed=0, partial=False)


def test_protocol_recovers_a_known_transform(demo_pair):
  """A full, noise-free rigid copy: every neighborhood is the same set, so MeanCos is 1; the
  transposed (wrong-direction) ground truth is caught."""
  runs = [MethodRun("toldi", "toldi"), MethodRun("uniform", "uniform", k=None)]
  recs = evaluate_pair(demo_pair, runs, experiment="t", n_keypoints=200)
  for r in recs:
    assert r["meancos"] > 0.999 and r["n_valid"] >= 199 and r["n_keypoints"] == 200
  wrong = demo_pair.replace(transform=np.linalg.inv(demo_pair.transform))
  recs = evaluate_pair(wrong, runs[:1], experiment="t", n_keypoints=200)
  assert recs[0]["meancos"] < 0.6


def test_partial_scan_keypoints_have_counterparts_within_half_mr():
  pair = datasets.make_demo_pair(1, seed=0, partial=True)
  mi, si = evaluation.correspondences(pair, 300, 0)
  mapped = datasets.transform_points(pair.transform, pair.model_points[mi])
  assert np.linalg.norm(mapped - pair.scene_points[si], axis=1).max() <= 0.5 * pair.mr
  dec = datasets.with_decimation(datasets.make_demo_pair(0, seed=0, partial=False), 1 / 8)
  mi, si = evaluation.correspondences(dec, 300, 0, scene_first=True)
  assert len(si) == len(np.unique(si)) == 300


def test_host_kernels_give_the_jitted_records_and_yield_to_the_cap():
  """kernel="auto" runs the host fast paths (float64, every neighbor) where no ball exceeds the
  cap: the same frames as the jitted path on the capped patches, so the same records."""
  pair = datasets.make_demo_pair(1, seed=0, partial=True, noise_mr=0.3)
  runs = [MethodRun(m, m) for m, s in lrf_jax.METHODS.items()
          if s.host_frames is not None and s.default_k is None]
  assert {"shot", "rops", "gframes", "flare"} <= {r.method for r in runs}
  auto = evaluate_pair(pair, runs, experiment="t", n_keypoints=150)
  jit = evaluate_pair(pair, runs, experiment="t", n_keypoints=150, kernel="jit")
  for a, b in zip(auto, jit):
    assert a["kernel"] == "host" and b["kernel"] == "jit", a["method"]
    if a["method"] == "mian":  # x's sign is each eigen-solver's own (mian.py): frames agree up
      continue                 # to it (test_method_properties), MeanCos need not
    assert abs(a["meancos"] - b["meancos"]) < 2e-3, (a["method"], a["meancos"], b["meancos"])
    assert abs(a["n_valid"] - b["n_valid"]) <= 1, a["method"]
  capped = evaluate_pair(pair, runs[:1], experiment="t", n_keypoints=20, max_neighbors=16)
  assert capped[0]["kernel"] == "jit"  # the cap binds: the capped patches decide
  with pytest.raises(ValueError, match="kernel"):
    evaluate_pair(pair, runs[:1], experiment="t", n_keypoints=5, kernel="host")


def test_patch_cache_shares_searches(demo_pair):
  cache = PatchCache()
  runs = [MethodRun("lrf_net", "lrf_net"), MethodRun("uniform", "uniform")]  # both K = 256
  evaluate_pair(demo_pair, runs, experiment="t", n_keypoints=50, cache=cache)
  assert cache.misses == 2 and cache.hits == 2


def test_normals_estimated_once_per_side(demo_pair, monkeypatch):
  from lrf_jax.evaluation import repeatability

  calls = []
  real = repeatability.estimate_normals

  def counting(points, radius, faces=None, viewpoint=None):
    calls.append(viewpoint)
    return real(points, radius, faces, viewpoint)

  monkeypatch.setattr(repeatability, "estimate_normals", counting)
  runs = [MethodRun(m, m) for m in ("flare", "board", "mian", "uniform")]
  recs = evaluate_pair(demo_pair, runs, experiment="t", n_keypoints=30)
  assert len(calls) == 2  # model and scene, shared by the three normal-based methods
  assert calls[1] is demo_pair.scene_viewpoint
  assert all(r["meancos"] is not None and r["max_neighbors"] == evaluation.MAX_NEIGHBORS
             for r in recs)


def test_report_and_figures_render(tmp_path, demo_pair):
  runs = [MethodRun("toldi", "toldi"), MethodRun("uniform", "uniform")]
  records = evaluate_pair(demo_pair, runs, experiment="repeatability", n_keypoints=50)
  for level in (0.1, 0.3):
    noisy = datasets.with_noise(demo_pair, level, 0)
    records += evaluate_pair(noisy, runs, experiment="noise", setting={"noise_mr": level},
                             n_keypoints=50)
  evaluation.write_results(records, tmp_path, notes=["test run"])
  data = json.loads((tmp_path / "results.json").read_text())
  keys = {"experiment", "dataset", "pair", "method", "setting", "meancos", "frac_above_0.97",
          "n_keypoints", "n_valid"}
  assert all(keys <= set(r) for r in data["records"]) and len(data["records"]) == 6
  md = (tmp_path / "report.md").read_text()
  assert "| demo |" in md and "## noise" in md and "toldi" in md
  for png in ("repeatability.png", "noise.png"):
    assert (tmp_path / png).stat().st_size > 5000


def test_mesh_method_on_cloud_is_reported_na(demo_pair):
  needs_mesh = [n for n, s in lrf_jax.METHODS.items() if s.needs_mesh]
  if not needs_mesh:
    pytest.skip("no mesh-only method registered")
  cloud = demo_pair.replace(scene_faces=None)
  rec = evaluate_pair(cloud, [MethodRun(needs_mesh[0], needs_mesh[0])], experiment="t",
                      n_keypoints=20)[0]
  assert rec["meancos"] is None and rec["note"].startswith("n/a")


def test_ablation_variants_load_and_normal_sum1_is_equivariant():
  """Shipped ablation weights load; the invariant variants are rotation equivariant and the
  raw-coordinate ones (Sum2, DR) are not, which is what the paper's rotation experiment shows."""
  from lrf_jax.evaluation.experiments import ablation_runs
  runs = {r.label: r for r in ablation_runs()}
  assert len(runs) == 8
  pair = datasets.make_demo_pair(0, seed=0, partial=False)
  recs = {r["method"]: r["meancos"] for r in evaluate_pair(
      pair, [runs["Normal+Sum1"], runs["Normal+Max"], runs["Normal+Sum2"], runs["DR+DR"]],
      experiment="t", n_keypoints=100, scene_first=False)}
  assert recs["Normal+Sum1"] > 0.999 and recs["Normal+Max"] > 0.999
  assert recs["Normal+Sum2"] < 0.99 and recs["DR+DR"] < 0.9


def test_weights_figure_renders(tmp_path, demo_pair):
  from lrf_jax.evaluation.report import weights_figure
  path = weights_figure(demo_pair, lrf_jax.init_params(0), tmp_path, n=2)
  assert path.stat().st_size > 5000


def test_weight_maps_figure_renders(tmp_path):
  from lrf_jax.evaluation.report import weight_maps_figure
  path = weight_maps_figure(tmp_path, size=21)
  assert path.name == "weight_maps.png" and path.stat().st_size > 5000


def test_plus_ablation_switches_and_figure(tmp_path):
  opts = evaluation.EvalOptions(n_keypoints=30, max_pairs=1)
  recs = list(evaluation.run_experiment("plus_ablation", ["demo"], [], opts, PatchCache()))
  labels = [r["method"] for r in recs]
  assert labels[0] == "LRF-Net (paper)" and labels[-1] == "lrf_net_plus (shipped)"
  assert len(recs) == 7
  assert all(r["meancos"] is not None for r in recs)
  evaluation.write_results(recs, tmp_path)
  assert (tmp_path / "plus_ablation.png").stat().st_size > 5000
  assert "## plus_ablation" in (tmp_path / "report.md").read_text()


@pytest.mark.slow
def test_plus_with_switches_off_is_the_ball_sign_construction(demo_pair):
  from lrf_jax.frames.lrf_net import lrf_net_frames
  from lrf_jax.frames.weights import default_params
  from lrf_jax.search.neighborhoods import build_patches

  pts = demo_pair.scene_points
  kp = np.arange(0, len(pts), 37)
  r = 15 * demo_pair.mr
  # The jitted function on both sides (test_lrf_net holds the host kernel to it).
  f, v = lrf_jax.compute_frames(pts, kp, r, "lrf_net_plus", faces=demo_pair.scene_faces,
                                viewpoint=demo_pair.scene_viewpoint, density=False,
                                oriented_sign=False, kernel="jit")
  k = lrf_jax.METHODS["lrf_net_plus"].default_k
  # compute_frames works in units of the radius (`neighborhoods.unit_scaled`): the same patches
  g, w = lrf_net_frames(default_params("lrf_net_plus"), build_patches(pts / r, kp, 1.0, k),
                        z_sign="ball", x_mode="softmax", lut=257)
  np.testing.assert_array_equal(np.asarray(v), np.asarray(w))
  np.testing.assert_allclose(np.asarray(f), np.asarray(g), atol=1e-5)
  h, _ = lrf_jax.compute_frames(pts, kp, r, "lrf_net_plus", faces=demo_pair.scene_faces,
                                viewpoint=demo_pair.scene_viewpoint)
  assert np.abs(np.asarray(h) - np.asarray(f)).max() > 1e-2  # the switches do something


def test_evaluate_with_missing_data_says_where_it_looked_and_exits_2(tmp_path, monkeypatch,
                                                                     capsys):
  import sys
  from pathlib import Path
  sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
  import evaluate
  monkeypatch.delenv("LRF_DATA", raising=False)
  monkeypatch.chdir(tmp_path)
  rc = evaluate.main(["--data", str(tmp_path / "nowhere"), "--datasets", "bunny",
                      "--out", str(tmp_path / "out")])
  err = capsys.readouterr().err
  assert rc == 2
  assert "Looked in:" in err and str(tmp_path / "nowhere") in err
  assert "LRF_DATA" in err and "data/README.md" in err
  assert not (tmp_path / "out").exists()  # nothing ran


def test_method_styles_are_distinct_for_any_number_of_methods():
  from lrf_jax.evaluation.report import method_styles
  for n in (3, 11, 20, 45):
    styles = method_styles([f"m{i}" for i in range(n)])
    assert len({(tuple(c), h) for c, h in styles.values()}) == n


@pytest.mark.slow
def test_evaluate_progress_total_is_the_number_of_records(tmp_path):
  """The bar's total (its ETA) is computed before any work: it equals the records run."""
  from lrf_jax.evaluation import runner
  runs, _ = runner.method_runs(["shot", "uniform"])
  opts = evaluation.EvalOptions(n_keypoints=40, max_pairs=1)
  plan = runner.EvalPlan(["demo"], ["repeatability", "rotation"], runs, opts)
  cache = PatchCache()
  for exp, expected in (("repeatability", 2), ("rotation", 8)):
    assert runner.count_records(exp, plan) == expected
    assert sum(1 for _ in runner._records(exp, plan, cache)) == expected
  plan.experiments = ["repeatability"]
  text = runner.evaluate(plan, tmp_path, progress=False)
  assert "shot" in text and (tmp_path / "results.json").exists()
  assert len(json.loads((tmp_path / "results.json").read_text())["records"]) == 2


@pytest.mark.slow
def test_complete_evaluation_removes_its_partial_records(tmp_path, monkeypatch):
  """partial_records.jsonl is written while the run goes and gone after it completes."""
  from lrf_jax.evaluation import runner
  monkeypatch.setattr(runner, "PARTIAL_EVERY", 1)
  written = []
  real = runner.atomic.write_text
  monkeypatch.setattr(runner.atomic, "write_text",
                      lambda path, text: written.append(Path(path).name) or real(path, text))
  runs, _ = runner.method_runs(["shot"])
  plan = runner.EvalPlan(["demo"], ["repeatability"], runs,
                         evaluation.EvalOptions(n_keypoints=30, max_pairs=1))
  runner.evaluate(plan, tmp_path, progress=False)
  assert "partial_records.jsonl" in written
  assert (tmp_path / "results.json").exists()
  assert not (tmp_path / "partial_records.jsonl").exists()


def test_evaluate_rejects_a_malformed_params_item():
  from lrf_jax.evaluation import runner
  with pytest.raises(ValueError, match="LABEL=PATH"):
    runner.method_runs(["shot"], params=("no-equals-sign",))
