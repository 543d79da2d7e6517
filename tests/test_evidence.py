"""One verdict for every estimator and option: `Registration.success` and `.reason_code`.

The evidence (the inliers of the winner, chance alignment, the best distinct pose, the aligned
overlap and whether it pins the pose down) is counted the same way whatever produced the winner,
so no option claims what the default's evidence would not.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax import datasets
from lrf_jax.registration import register
from lrf_jax.registration.evidence import (RIVAL_DEG, REASON_CODES, Evidence, constraint_spectrum,
                                           decide, distinct, distinct_from, poses_apart,
                                           verdict)

KW = dict(n_keypoints=800, n_correspondences=200)


def _evidence(**change):
  base = dict(n_inliers=40, chance_inliers=5, rival_inliers=4, fitness=0.5, contrast=0.0,
              estimator="graph")
  return Evidence(**{**base, **change})


@pytest.mark.parametrize("estimator", ["graph", "lrf", "3point"])
def test_decide_gives_one_code_per_branch_and_the_same_rule_for_every_estimator(estimator):
  assert decide(_evidence(estimator=estimator)).code == "claimed"
  assert decide(_evidence(estimator=estimator, fitness=0.04)).code == "low_overlap"
  assert decide(_evidence(estimator=estimator, chance_inliers=20)).code == "chance"
  assert decide(_evidence(estimator=estimator, rival_inliers=20)).code == "rival"
  d = decide(_evidence(estimator=estimator, degeneracy=0.001,
                       free_direction="translation along (1.00, 0.00, 0.00)"))
  assert (d.success, d.code) == (False, "degenerate") and "translation along" in d.reason
  # the old rule of "lrf" and "3point" claimed few inliers on an overlap contrast: no more
  assert decide(_evidence(estimator=estimator, n_inliers=7, chance_inliers=7,
                          contrast=2.1)).success is False
  for change in ({}, {"fitness": 0.04}, {"rival_inliers": 20}):
    ok, reason = verdict(_evidence(estimator=estimator, **change))
    d = decide(_evidence(estimator=estimator, **change))
    assert (ok, reason) == (d.success, d.reason) and d.code in REASON_CODES


def test_constraint_spectrum_finds_the_free_motion_of_a_plane_and_none_of_a_corner():
  rng = np.random.default_rng(0)
  xy = rng.uniform(-1, 1, size=(500, 2))
  plane = np.c_[xy, np.zeros(len(xy))]
  ratio, words = constraint_spectrum(plane, np.tile([0.0, 0.0, 1.0], (len(xy), 1)))
  assert ratio < 1e-6 and words.startswith(("translation along", "rotation about"))
  # three walls of a box corner pin every motion down
  pts, nrm = [], []
  for axis in range(3):
    p = rng.uniform(0, 1, size=(300, 3))
    p[:, axis] = 0.0
    n = np.zeros((300, 3))
    n[:, axis] = 1.0
    pts.append(p)
    nrm.append(n)
  ratio, _ = constraint_spectrum(np.concatenate(pts), np.concatenate(nrm))
  assert ratio > 0.05
  assert constraint_spectrum(plane[:3], np.tile([0.0, 0.0, 1.0], (3, 1)))[0] == 1.0


@pytest.fixture(scope="module")
def demo():
  return datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)


def test_a_real_pair_is_claimed_with_its_code_and_so_is_its_pose_as_an_init(demo):
  reg = register(demo.model_points, demo.scene_points, mr=demo.mr, **KW)
  assert reg.success and reg.reason_code == "claimed"
  # n_correspondences=200: the evidence is the default matching's 1000 (here every match)
  assert reg.evidence_inliers > reg.n_inliers
  own = register(demo.model_points, demo.scene_points, mr=demo.mr, n_keypoints=800)
  assert own.evidence_inliers == own.n_inliers  # the default: the evidence is its own matching
  ref = register(demo.model_points, demo.scene_points, mr=demo.mr, init=reg.transform, **KW)
  assert ref.success and ref.reason_code == "claimed" and ref.reason.startswith("refined from init")
  # the same evidence at (nearly) the same pose: the counts the verdict compared agree
  assert ref.chance_inliers == reg.chance_inliers
  assert abs(ref.evidence_inliers - reg.evidence_inliers) <= 0.1 * reg.evidence_inliers


@pytest.mark.parametrize("degrees", [30.0, 90.0, 180.0])
def test_a_wrong_init_is_never_claimed(demo, degrees):
  """Before: an init was refined and never judged (`init_only`). Now it is judged on the
  default's evidence: the truth turned about the target's centre is not claimed, whichever
  pose ICP settles in, unless ICP brings it back to the truth."""
  from lrf_jax.registration import pose_errors
  turn = np.eye(4)
  turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.6, 0.0, 0.8])).as_matrix()
  centre = demo.scene_points.mean(axis=0)
  turn[:3, 3] = centre - turn[:3, :3] @ centre
  init = turn @ demo.transform
  ref = register(demo.model_points, demo.scene_points, mr=demo.mr, init=init, **KW)
  err, _ = pose_errors(ref.transform, demo.transform, demo.mr)
  np.testing.assert_allclose(ref.coarse_transform, init, atol=1e-12)
  assert not ref.success or err < 2.0, (ref.reason, err)
  if err > 10.0:  # ICP kept a wrong pose: the right one, among the graph's, is its rival
    assert ref.reason_code in ("rival", "chance", "low_overlap", "degenerate", "moved"), ref.reason


@pytest.mark.parametrize("degrees", [9.0, 20.0, 45.0])
def test_a_wrong_init_held_unmoved_is_never_claimed(demo, degrees):
  """With icp_iterations=0 the init is the pose returned, and its support is counted at it. A
  few true correspondences lie near the turn's axis: refitted on them (as it was), the pose
  landed on the truth with all of its support, and the wrong init was claimed (at 9 deg the
  refit is within RIVAL_DEG of the init, so "moved" does not catch it: only the count at the
  pose itself does)."""
  from lrf_jax.registration import pose_errors
  turn = np.eye(4)
  turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.6, 0.0, 0.8])).as_matrix()
  centre = demo.scene_points.mean(axis=0)
  turn[:3, 3] = centre - turn[:3, :3] @ centre
  init = turn @ demo.transform
  ref = register(demo.model_points, demo.scene_points, mr=demo.mr, init=init, icp_iterations=0,
                 **KW)
  np.testing.assert_allclose(ref.transform, init, atol=1e-12)
  assert pose_errors(ref.transform, demo.transform, demo.mr)[0] == pytest.approx(degrees)
  assert not ref.success, ref.reason
  # the truth held unmoved is still claimed
  same = register(demo.model_points, demo.scene_points, mr=demo.mr, init=demo.transform,
                  icp_iterations=0, **KW)
  assert same.success and same.reason_code == "claimed", same.reason


def test_poses_apart_measures_the_turn_and_the_shift_at_the_point():
  rng = np.random.default_rng(3)
  a = np.eye(4)
  a[:3, :3] = Rotation.random(random_state=4).as_matrix()
  a[:3, 3] = rng.normal(size=3)
  point = rng.normal(size=3)
  assert poses_apart(a, a, point) == pytest.approx((0.0, 0.0), abs=1e-6)
  turn = np.eye(4)  # 25 deg about an axis through the image of `point`: it stays put
  turn[:3, :3] = Rotation.from_rotvec(np.radians(25.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
  image = a[:3, :3] @ point + a[:3, 3]
  turn[:3, 3] = image - turn[:3, :3] @ image
  assert poses_apart(turn @ a, a, point) == pytest.approx((25.0, 0.0), abs=1e-6)
  shift = np.eye(4)
  shift[:3, 3] = [0.3, -0.4, 0.0]
  assert poses_apart(shift @ a, a, point) == pytest.approx((0.0, 0.5), abs=1e-6)


@pytest.mark.parametrize("at_point", [False, True])
def test_distinct_from_is_distinct_for_every_pose(at_point):
  """The vectorised test against `distinct` of `poses_apart`, pose by pose, on poses drawn
  around the two thresholds (turns of 0-20 deg, shifts of 0-2x the radius), away from exact
  ties (within 1e-6 of a threshold)."""
  rng = np.random.default_rng(11)
  r = Rotation.random(random_state=5).as_matrix()
  t = rng.normal(size=3)
  point = rng.normal(size=3) if at_point else np.zeros(3)
  radius = 0.7
  axes = rng.normal(size=(400, 3))
  axes /= np.linalg.norm(axes, axis=1, keepdims=True)
  turns = Rotation.from_rotvec(axes * np.radians(rng.uniform(0, 20, 400))[:, None]).as_matrix()
  rs = turns @ r
  ts = t + rng.normal(size=(400, 3)) * rng.uniform(0, 2 * radius, (400, 1)) / np.sqrt(3)
  got = distinct_from(rs, ts, r, t, radius, point if at_point else None)
  want, away = [], []
  for rh, th in zip(rs, ts):
    a, b = np.eye(4), np.eye(4)
    a[:3, :3], a[:3, 3], b[:3, :3], b[:3, 3] = rh, th, r, t
    deg, dist = poses_apart(a, b, point)
    want.append(distinct(deg, dist, radius))
    away.append(abs(deg - RIVAL_DEG) > 1e-6 and abs(dist - radius) > 1e-6)
  want, away = np.array(want), np.array(away)
  assert 50 < want.sum() < 350  # both kinds drawn
  np.testing.assert_array_equal(got[away], want[away])


def test_a_pose_distinct_from_the_one_its_inliers_support_is_not_claimed():
  """The rule of rivals, applied to the pose returned: more than RIVAL_DEG degrees or the
  support radius from the pose whose inliers were counted is another pose."""
  from lrf_jax.registration.evidence import RIVAL_DEG
  assert decide(_evidence(moved_deg=RIVAL_DEG - 0.5, moved_distance=0.2,
                          distinct_distance=0.3)).code == "claimed"
  d = decide(_evidence(moved_deg=RIVAL_DEG + 0.5))
  assert (d.success, d.code) == (False, "moved") and "support a pose 10.5 deg" in d.reason
  d = decide(_evidence(moved_distance=0.4, distinct_distance=0.3))
  assert (d.success, d.code) == (False, "moved") and "0.4 from the one returned" in d.reason
  # its place in the order: after the overlap's tests, before the support's
  moved = dict(moved_deg=RIVAL_DEG + 5.0)
  assert decide(_evidence(fitness=0.04, **moved)).code == "low_overlap"
  assert decide(_evidence(degeneracy=0.001, **moved)).code == "degenerate"
  assert decide(_evidence(rival_inliers=20, **moved)).code == "moved"
  assert decide(_evidence(chance_inliers=20, **moved)).code == "moved"


@pytest.mark.parametrize("degrees, code", [(2.0, "claimed"), (20.0, "moved")])
def test_the_pipeline_says_moved_where_icp_leaves_the_winner(demo, monkeypatch, degrees, code):
  """`register` measures the pose it returns against the winner whose inliers it counted: ICP
  (here made to turn its result about the source's centroid) moving 20 deg is another pose, 2
  deg the same one."""
  import lrf_jax.registration.pipeline as pipeline
  real = pipeline.refine

  def turned(prepared, verified, icp_opts, timer):
    out = real(prepared, verified, icp_opts, timer)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 0.6, 0.8])
                                        ).as_matrix()
    centre = demo.model_points.mean(axis=0)
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    return out._replace(transform=out.transform @ turn)

  monkeypatch.setattr(pipeline, "refine", turned)
  reg = register(demo.model_points, demo.scene_points, mr=demo.mr, effort="fast", **KW)
  assert reg.reason_code == code and reg.success is (code == "claimed"), reg.reason


def test_fewer_correspondences_are_judged_on_the_default_count(demo):
  """`n_correspondences` chooses the hypotheses' correspondences, not the evidence: the verdict
  counts on the default matching's (`EVIDENCE_CORRESPONDENCES`), so a pose on a repeated
  structure cannot outnumber a truth that few of 300 correspondences witness (a room crop was
  claimed 42 deg off with 300)."""
  from lrf_jax.registration import stages
  from lrf_jax.registration.options import RegisterOptions
  few = RegisterOptions(mr=demo.mr, n_keypoints=800, n_correspondences=60)
  prepared = stages.prepare(demo.model_points, demo.scene_points, few)
  features = stages.describe(prepared, few.description, None, stages.StageTimer())
  m = stages.match(features, few)
  assert len(m.source) == 60 and not m.own
  default = stages.match(features, few.with_overrides(n_correspondences=1000))
  assert default.own and stages.EVIDENCE_CORRESPONDENCES == 1000
  np.testing.assert_array_equal(m.evidence_source, default.source)
  np.testing.assert_array_equal(m.evidence_target, default.target)


@pytest.mark.parametrize("options", [{"estimator": "lrf"}, {"estimator": "3point"},
                                     {"ratio": 0.9}, {"mutual": True}])
def test_no_option_claims_blobs_or_a_mirror_image(demo, options):
  """The findings: estimator "lrf" / "3point" claimed two Gaussian blobs and a mirror image on
  their overlap contrast; every option now answers to the default's evidence."""
  rng = np.random.default_rng(0)
  a, b = rng.normal(size=(4000, 3)), rng.normal(size=(4000, 3))
  reg = register(a, b, **KW, **options)
  assert reg.success is False and reg.reason_code in ("chance", "rival", "no_hypothesis")
  mirrored = register(demo.model_points, demo.scene_points * [-1, 1, 1], mr=demo.mr, **KW,
                      **options)
  assert mirrored.success is False, (options, mirrored.reason)
  assert mirrored.reason_code != "claimed"


def test_graph_hypotheses_without_seeds_fall_back_to_not_sure(monkeypatch, demo):
  """ratio=0.9 raised an IndexError where no two of the few correspondences agreed (no seed,
  no hypothesis): now the one-correspondence poses stand in and the verdict says so."""
  from lrf_jax.registration import graph
  empty = (np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0))
  monkeypatch.setattr(graph, "graph_hypotheses", lambda *a, **k: empty)
  reg = register(demo.model_points, demo.scene_points, mr=demo.mr, **KW)
  assert reg.success is False and reg.reason_code == "no_hypothesis"
  assert np.all(np.isfinite(reg.transform))


def test_two_identical_copies_side_by_side_are_a_rival_not_a_success():
  """The correspondences split between two copies of the object: the winner's seeds used to
  suppress the second copy's, so no hypothesis saw it and the verdict claimed one copy."""
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=False)
  src = pair.model_points
  r = Rotation.from_euler("xyz", [30, 50, 10], degrees=True).as_matrix()
  copy = src @ r.T
  shift = 1.5 * np.ptp(src, axis=0).max()
  twin = np.concatenate([copy, copy + [shift, 0, 0]])
  reg = register(src, twin, mr=pair.mr, n_keypoints=1500, n_correspondences=500)
  assert reg.success is False and reg.reason_code == "rival", reg.reason
  single = register(src, copy, mr=pair.mr, n_keypoints=1500, n_correspondences=500)
  assert single.success and single.reason_code == "claimed"


@pytest.mark.parametrize("estimator", ["graph", "lrf"])
def test_a_plane_against_itself_shifted_is_degenerate_and_names_the_free_direction(estimator):
  rng = np.random.default_rng(0)
  a = np.c_[rng.uniform(-20, 20, size=(6000, 2)), 0.02 * rng.normal(size=6000)]
  b = np.c_[rng.uniform(-20, 20, size=(6000, 2)) + [8, 0], 0.02 * rng.normal(size=6000)]
  reg = register(a, b, estimator=estimator, **KW)
  assert reg.success is False and reg.reason_code == "degenerate", reg.reason
  assert "translation along" in reg.reason or "rotation about" in reg.reason


@pytest.mark.parametrize("period, shift, seed", [(4.0, 4.0, 0), (4.0, 2.0, 1)])
def test_a_street_of_repeating_facades_is_not_claimed_a_period_off(period, shift, seed):
  """Two LiDAR sweeps along a street whose facades repeat every `period` m: a pose a period off
  lays the facades and the ground on each other nearly as well as the true one (checked), so
  the verdict must not claim it; the true pose may be claimed."""
  from lrf_jax.registration import rotation_error_deg
  from scipy.spatial import cKDTree
  pair = datasets.make_street_pair(period, shift, seed=seed)
  tree = cKDTree(pair.scene_points)
  off = pair.transform.copy()
  off[0, 3] += period

  def overlap(t):  # model points within 0.1 m of the scene under t
    moved = datasets.transform_points(t, pair.model_points)
    return float(np.mean(tree.query(moved, distance_upper_bound=0.1)[0] <= 0.1))

  assert overlap(off) > 0.7 * overlap(pair.transform)  # a rival pose indeed
  reg = register(pair.model_points, pair.scene_points)
  right = (rotation_error_deg(reg.transform[:3, :3], pair.transform[:3, :3]) < 2.0
           and np.linalg.norm(reg.transform[:3, 3] - pair.transform[:3, 3]) < 0.5)
  assert right or not reg.success, (reg.reason, reg.transform[:3, 3])


@pytest.mark.parametrize("fitness,shown,needed", [
    (0.0499, "4.99%", "5.00%"), (0.04996, "4.996%", "5.000%"), (0.049999999, "4.9999999%",
                                                                 "5.0000000%"),
    (0.01, "1%", "5%"), (0.0, "0%", "5%")])
def test_a_low_overlap_never_reads_as_its_floor(fitness, shown, needed):
  reason = decide(_evidence(fitness=fitness)).reason
  assert reason == (f"not sure: only {shown} of the source lies on the target after ICP (needs "
                    f"{needed})")


@pytest.mark.parametrize("ratio,shown", [(0.009996, "0.009996"), (0.0099, "0.0099"),
                                         (0.0012, "0.0012"), (0.0, "0")])
def test_a_degenerate_overlap_never_reads_as_its_floor(ratio, shown):
  reason = decide(_evidence(degeneracy=ratio)).reason
  assert f"holds {shown} of the strongest's (needs 0.01)" in reason


def test_the_needed_inliers_are_printed_in_full():
  reason = decide(_evidence(n_inliers=1200002, chance_inliers=400000, rival_inliers=1)).reason
  assert reason.startswith("not sure: 1200002 consistent correspondences, chance gives 400000 "
                           "(needs 1200003); ")
  assert "(needs 21)" in decide(_evidence(n_inliers=9, chance_inliers=1, rival_inliers=6)).reason


def test_an_init_is_kept_where_icp_slides_away_from_what_it_explains(demo, monkeypatch):
  """ICP from an init that moves to a pose explaining fewer of the matched correspondences (a
  slide along a floor and a wall) is undone: the init, measured unmoved, is the pose judged,
  and `reason` says so; where ICP's pose explains at least as many, it is kept (the truth turned
  by 3 deg comes back)."""
  from lrf_jax.registration import from_init, pose_errors
  from lrf_jax.registration.refine import refine as real_refine
  truth = demo.transform

  def sliding(prepared, start, icp_opts, timer):
    out = real_refine(prepared, start, icp_opts, timer)
    if icp_opts.icp_iterations == 0:
      return out
    slide = np.eye(4)
    slide[:3, :3] = Rotation.from_rotvec(np.radians(12.0) * np.array([0.0, 0.0, 1.0])).as_matrix()
    return out._replace(transform=slide @ out.transform)

  monkeypatch.setattr(from_init, "refine", sliding)
  ref = register(demo.model_points, demo.scene_points, mr=demo.mr, init=truth, **KW)
  assert ref.reason.startswith("init kept as given: ICP from it explains "), ref.reason
  np.testing.assert_allclose(ref.transform, truth, atol=1e-9)
  monkeypatch.setattr(from_init, "refine", real_refine)
  turn = np.eye(4)
  turn[:3, :3] = Rotation.from_rotvec(np.radians(3.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
  centre = demo.model_points.mean(axis=0)
  turn[:3, 3] = centre - turn[:3, :3] @ centre
  back = register(demo.model_points, demo.scene_points, mr=demo.mr, init=truth @ turn, **KW)
  assert back.reason.startswith("refined from init"), back.reason
  assert pose_errors(back.transform, truth, demo.mr)[0] < 1.0


def test_an_init_is_kept_where_icp_moves_to_a_distinct_pose_that_explains_no_more():
  """`kept_init` on correspondences that lie on one axis (a rotation about it moves none of
  them): ICP's turn about that axis explains as many as the init; 15 deg is a distinct pose
  (over RIVAL_DEG), so the init stays; 5 deg within the support radius is the same pose, and
  ICP's pose stands; correspondences explaining no more than chance judge nothing."""
  from types import SimpleNamespace
  from lrf_jax.registration.from_init import kept_init
  rng = np.random.default_rng(0)
  axis = np.c_[np.zeros(12), np.zeros(12), np.linspace(-1.0, 1.0, 12)]
  off = rng.uniform(-1.0, 1.0, size=(12, 3)) + np.array([2.0, 0.0, 0.0])
  pts = np.concatenate([axis, off])
  side = SimpleNamespace(points=pts, keypoints=np.arange(len(pts)))
  prepared = SimpleNamespace(sides=(side, side), mr=0.01, radius=0.5)
  # the axis points match themselves; the others match a shuffled partner (wrong matches)
  matches = SimpleNamespace(source=np.arange(len(pts)),
                            target=np.r_[np.arange(12), 12 + np.roll(np.arange(12), 1)])

  def about_z(deg):
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.0, 1.0])).as_matrix()
    return t

  note = kept_init(prepared, matches, np.eye(4), about_z(15.0), 1.0, chance=3)
  assert note.startswith("init kept as given: ICP from it moved 15.0 deg"), note
  assert "explains 12 of the correspondences, as many as the init" in note
  assert kept_init(prepared, matches, np.eye(4), about_z(5.0), 1.0, chance=3) == ""
  assert kept_init(prepared, matches, np.eye(4), about_z(15.0), 1.0, chance=12) == ""


def _turned(demo, degrees):
  turn = np.eye(4)
  turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.6, 0.0, 0.8])).as_matrix()
  centre = demo.scene_points.mean(axis=0)
  turn[:3, 3] = centre - turn[:3, :3] @ centre
  return turn @ demo.transform


@pytest.mark.parametrize("degrees", [4.0, 25.0, 60.0])
def test_verify_near_starts_from_the_best_hypothesis_not_distinct_from_the_pose(demo, degrees):
  """`stages.verify_near` against a brute-force reference: over the graph's hypotheses (world
  poses), those `evidence.distinct` from the anchor excluded, the one with the most inliers, or
  the anchor itself where it explains more; its refit is `verify`'s refit of that start."""
  from lrf_jax.registration import stages
  from lrf_jax.registration.effort import one_pass
  from lrf_jax.registration.estimators import uncentre
  from lrf_jax.registration.evidence import distinct
  from lrf_jax.registration.options import resolve
  opts = resolve(None, dict(mr=demo.mr, **KW))
  prepared, features, matches = one_pass(demo.model_points, demo.scene_points, opts, None,
                                         stages.StageTimer())
  hyps = stages.hypothesize(prepared, features, matches, opts.hypotheses)
  anchor = _turned(demo, degrees)
  got = stages.verify_near(prepared, hyps, anchor, opts.hypotheses, opts.icp.icp_mr, matches.own)
  point = hyps.evidence.cs
  best, count = -1, int(np.sum(np.linalg.norm(
      (hyps.src + hyps.cs) @ anchor[:3, :3].T + anchor[:3, 3] - (hyps.dst + hyps.cd), axis=1)
      <= opts.hypotheses.inlier_mr * prepared.mr))
  for h in range(len(hyps.counts)):
    r, t = uncentre(hyps.rotations[h], hyps.translations[h], hyps.cs, hyps.cd)
    world = np.eye(4)
    world[:3, :3], world[:3, 3] = r, t
    if not distinct(*poses_apart(world, anchor, point), prepared.radius) and hyps.counts[h] > count:
      best, count = h, int(hyps.counts[h])
  assert got.coarse.best_hypothesis == best
  if degrees == 4.0:  # the truth's hypotheses are near: the refit lands on the truth
    assert best >= 0
    from lrf_jax.registration import pose_errors
    assert pose_errors(got.coarse.transform, demo.transform, demo.mr)[0] < 1.0
  if best >= 0:  # the refit of that hypothesis is `verify`'s (the same arithmetic)
    only = hyps._replace(rotations=hyps.rotations[best:best + 1],
                         translations=hyps.translations[best:best + 1],
                         counts=hyps.counts[best:best + 1])
    ref = stages.verify(prepared, only, opts.hypotheses, opts.icp.icp_mr, matches.own)
    np.testing.assert_allclose(got.coarse.transform, ref.coarse.transform, atol=1e-9)


def test_an_init_icp_leaves_short_is_claimed_at_the_pose_the_hypotheses_near_it_give(demo):
  """One ICP iteration from the truth turned 20 deg leaves the pose 10 deg off, and that pose is
  "not sure" (the truth, among the graph's hypotheses, is its rival). Searched near it (the
  hypotheses not distinct from it, refitted and refined as `register`'s winner), the truth is
  found and claimed; held unmoved (`icp_iterations=0`) the init is judged as given only."""
  from lrf_jax.registration import pose_errors
  init = _turned(demo, 20.0)
  kw = dict(mr=demo.mr, init=init, icp_fine=False, effort="fast", **KW)
  ref = register(demo.model_points, demo.scene_points, icp_iterations=1, **kw)
  assert ref.success and ref.reason_code == "claimed", ref.reason
  assert ref.reason.startswith("refined from init and the hypotheses near it: "), ref.reason
  assert pose_errors(ref.transform, demo.transform, demo.mr)[0] < 1.0
  np.testing.assert_allclose(ref.coarse_transform, init, atol=1e-12)
  held = register(demo.model_points, demo.scene_points, icp_iterations=0, **kw)
  np.testing.assert_allclose(held.transform, init, atol=1e-12)
  assert not held.success, held.reason


@pytest.mark.parametrize("k", [1e-3, 1e3])
def test_the_search_near_an_init_has_no_length_of_its_own(demo, k):
  """The neighbourhood (10 deg, the support radius) is in mr: both clouds and the init's
  translation scaled by k give the same verdict and the pose with its translation scaled."""
  from lrf_jax.registration import rotation_error_deg
  init = _turned(demo, 20.0)
  kw = dict(icp_iterations=1, icp_fine=False, effort="fast", **KW)
  base = register(demo.model_points, demo.scene_points, init=init, **kw)
  scaled_init = init.copy()
  scaled_init[:3, 3] *= k
  scaled = register(k * demo.model_points, k * demo.scene_points, init=scaled_init, **kw)
  assert base.reason.startswith("refined from init and the hypotheses near it")
  assert scaled.success == base.success and scaled.reason_code == base.reason_code
  assert scaled.reason.split(":")[0] == base.reason.split(":")[0]
  assert rotation_error_deg(scaled.transform[:3, :3], base.transform[:3, :3]) < 1e-3
  np.testing.assert_allclose(scaled.transform[:3, 3] / k, base.transform[:3, 3],
                             atol=1e-4 * demo.mr)
