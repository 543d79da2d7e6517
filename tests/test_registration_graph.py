"""The compatibility-graph estimator (`lrf_jax.registration.graph`) and the verdict's evidence."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax.registration import graph
from lrf_jax.registration import host
from lrf_jax.registration import rotation_error_deg
from lrf_jax.registration.evidence import Evidence, verdict


def _scene(n=400, inlier_fraction=0.08, seed=0, noise=0.002):
  """N correspondences, a fraction of them consistent with one rigid motion (R, t)."""
  rng = np.random.default_rng(seed)
  r = Rotation.random(random_state=seed).as_matrix()
  t = rng.normal(size=3)
  p = rng.uniform(-1, 1, size=(n, 3))
  q = p @ r.T + t + rng.normal(scale=noise, size=(n, 3))
  good = rng.random(n) < inlier_fraction
  q[~good] = rng.uniform(-1, 1, size=((~good).sum(), 3)) + t
  rots = np.stack([Rotation.random(random_state=seed + 1 + i).as_matrix() for i in range(n)])
  near = (Rotation.from_matrix(r) * Rotation.from_rotvec(
      rng.normal(scale=0.1, size=(n, 3)))).as_matrix()  # about 10 degrees off the truth
  rots[good] = near[good]
  return p, q, rots, r, t, good


def test_compatibility_matches_brute_force():
  p, q, rots, *_ = _scene(n=60, inlier_fraction=0.3)
  c = graph.compatibility(p, q, 0.05, rots, 40.0)
  want = np.zeros((60, 60), np.float32)
  for i in range(60):
    for j in range(60):
      if i == j:
        continue
      dist_ok = abs(np.linalg.norm(p[i] - p[j]) - np.linalg.norm(q[i] - q[j])) < 0.05
      ang = rotation_error_deg(rots[i], rots[j])
      want[i, j] = dist_ok and ang < 40.0
  np.testing.assert_array_equal(c, want)
  np.testing.assert_array_equal(c, c.T)
  # distances only: a superset
  c0 = graph.compatibility(p, q, 0.05)
  assert np.all(c0 >= c) and c0.sum() > c.sum()


def test_compatibility_refuses_a_matrix_beyond_the_memory_bound():
  n = graph.MAX_CORRESPONDENCES + 1
  with pytest.raises(ValueError, match="correspondences"):
    graph.compatibility(np.zeros((n, 3)), np.zeros((n, 3)), 0.1)


def test_leading_eigenvector_matches_eigh_and_is_batched():
  rng = np.random.default_rng(3)
  a = rng.random((3, 20, 20))
  a = a + np.swapaxes(a, 1, 2)
  v = graph.leading_eigenvector(a, iterations=200)
  for k in range(3):
    w, vecs = np.linalg.eigh(a[k])
    ref = np.abs(vecs[:, -1])
    np.testing.assert_allclose(v[k], ref / ref.max(), atol=1e-6)
  np.testing.assert_allclose(graph.leading_eigenvector(a[1], iterations=200), v[1])
  assert np.all(graph.leading_eigenvector(np.zeros((4, 4))) == 0)


def test_seeds_are_suppressed_spatially_and_ordered_by_score():
  rng = np.random.default_rng(1)
  pts = rng.uniform(size=(200, 3))
  scores = rng.random(200)
  seeds = graph.select_seeds(pts, scores, 30, 0.15)
  assert len(seeds) <= 30 and len(set(seeds.tolist())) == len(seeds)
  assert np.all(np.diff(scores[seeds]) <= 0)
  d = np.linalg.norm(pts[seeds][:, None] - pts[seeds][None], axis=2) + np.eye(len(seeds))
  assert d.min() >= 0.15
  assert seeds[0] == np.argmax(scores)
  assert len(graph.select_seeds(pts, np.zeros(200), 10, 0.1)) == 0


@pytest.mark.parametrize("use_frames", [True, False])
def test_graph_hypotheses_find_the_motion_among_92_percent_outliers(use_frames):
  p, q, rots, r, t, good = _scene()
  rs, ts, seeds, _ = graph.graph_hypotheses(
      p, q, rots if use_frames else None, distance=0.02, angle_deg=45.0 if use_frames else None,
      n_seeds=40, consensus=20, nms=0.05)
  counts = host.count_inliers(rs, ts, p, q, 0.02)
  b = int(np.argmax(counts))
  assert rotation_error_deg(rs[b], r) < 1.0
  assert np.linalg.norm(ts[b] - t) < 0.02
  assert counts[b] >= 0.9 * good.sum()
  again = graph.graph_hypotheses(p, q, rots if use_frames else None, distance=0.02,
                                 angle_deg=45.0 if use_frames else None, n_seeds=40,
                                 consensus=20, nms=0.05)
  np.testing.assert_array_equal(again[0], rs)  # deterministic
  np.testing.assert_array_equal(again[2], seeds)


def test_rotation_agreement_removes_outlier_edges():
  """Outliers whose distances agree by chance rarely agree in rotation as well: the LRF check
  keeps most inlier-inlier edges and removes most other edges."""
  p, q, rots, _, _, good = _scene(n=300, inlier_fraction=0.2, seed=4)
  c0 = graph.compatibility(p, q, 0.05)
  c1 = graph.compatibility(p, q, 0.05, rots, 45.0)
  ii = np.outer(good, good)
  assert c1[ii].sum() >= 0.9 * c0[ii].sum()
  assert c1[~ii].sum() <= 0.2 * c0[~ii].sum()


def test_verdict_requires_support_above_chance_and_rivals():
  base = dict(n_inliers=40, chance_inliers=5, rival_inliers=4, fitness=0.5, contrast=0.0,
              estimator="graph")
  ok, reason = verdict(Evidence(**base))
  assert ok and "40" in reason
  for change in ({"rival_inliers": 20}, {"chance_inliers": 20}, {"fitness": 0.04},
                 {"n_inliers": 8}):
    ok, reason = verdict(Evidence(**{**base, **change}))
    assert not ok and reason.startswith("not sure")


def _demo():
  from lrf_jax import datasets
  return datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)


def test_register_default_graph_succeeds_with_a_reason_and_options_work():
  from lrf_jax.registration import pose_errors, register
  pair = _demo()
  kw = dict(n_keypoints=800, n_correspondences=200, mr=pair.mr)
  reg = register(pair.model_points, pair.scene_points, **kw)
  re, te = pose_errors(reg.transform, pair.transform, pair.mr)
  assert reg.success and re < 2.0 and te < 2.0
  assert "consistent correspondences" in reg.reason and 0 < reg.overlap <= 1
  assert reg.n_inliers >= 3 * max(reg.chance_inliers, reg.rival_inliers) + 3
  for extra in ({"mutual": True}, {"ratio": 0.95}, {"keypoints": "iss"},
                {"icp_mode": "point_to_point"}):
    r2 = register(pair.model_points, pair.scene_points, **kw, **extra)
    re2, _ = pose_errors(r2.transform, pair.transform, pair.mr)
    assert re2 < 2.0, extra
  for bad, match in (({"keypoints": "harris"}, "keypoints"), ({"ratio": 1.5}, "ratio"),
                     ({"mutual": "yes"}, "mutual"), ({"icp_mode": "plane"}, "icp_mode"),
                     ({"estimator": "cliques"}, "estimator")):
    with pytest.raises(ValueError, match=match):
      register(pair.model_points, pair.scene_points, **kw, **bad)


def test_register_with_init_refines_it_and_judges_it_on_the_default_evidence():
  from lrf_jax.registration import pose_errors, register
  pair = _demo()
  off = Rotation.from_rotvec([0.0, 0.0, np.radians(3.0)]).as_matrix()
  init = pair.transform.copy()
  init[:3, :3] = off @ init[:3, :3]
  reg = register(pair.model_points, pair.scene_points, init=init, mr=pair.mr)
  re0, _ = pose_errors(init, pair.transform, pair.mr)
  re, te = pose_errors(reg.transform, pair.transform, pair.mr)
  assert re < re0 / 3 and te < 1.0
  assert reg.reason.startswith("refined from init") and len(reg.correspondences) > 0
  assert reg.success and reg.reason_code == "claimed"  # the refined pose is the truth's
  np.testing.assert_array_equal(reg.coarse_transform, init)
  bad = init.copy()
  bad[:3, :3] *= -1  # a reflection, not a rotation
  with pytest.raises(ValueError, match="init"):
    register(pair.model_points, pair.scene_points, init=bad, mr=pair.mr)
  with pytest.raises(ValueError, match="init"):
    register(pair.model_points, pair.scene_points, init=np.eye(3), mr=pair.mr)


def test_second_order_equals_the_matrix_product():
  """The popcount kernel against SC2-PCR's C_s (C C)_s, for N across word boundaries."""
  rng = np.random.default_rng(5)
  for n in (1, 63, 64, 65, 200):
    c = (rng.random((n, n)) < 0.3).astype(np.float32)
    c = np.triu(c, 1)
    c = c + c.T
    seeds = rng.choice(n, size=min(n, 7), replace=False)
    np.testing.assert_array_equal(graph.second_order(c, seeds), c[seeds] * (c[seeds] @ c))


def test_seeds_match_a_brute_force_greedy_suppression():
  rng = np.random.default_rng(2)
  pts = rng.uniform(size=(150, 3))
  scores = np.round(rng.random(150), 1)  # ties: the smaller index first
  scores[::7] = 0.0
  want: list[int] = []
  for i in sorted(range(150), key=lambda i: (-scores[i], i)):
    if scores[i] <= 0 or len(want) >= 25:
      break
    if all(np.sum((pts[j] - pts[i]) ** 2) >= 0.1 ** 2 for j in want):
      want.append(i)
  np.testing.assert_array_equal(graph.select_seeds(pts, scores, 25, 0.1), want)
  assert len(graph.select_seeds(pts, scores, 0, 0.1)) == 0
