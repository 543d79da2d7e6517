"""`register_all`'s default escalation: the "not sure" pairs between two components of the
first pose graph are registered again as `effort="high"` registers them and the graph solved
again; `effort="fast"` never escalates, pairs within a component are not redone."""

from __future__ import annotations

import numpy as np

from lrf_jax import io
from lrf_jax.multiway import pipeline, register_all
from lrf_jax.registration.options import RegisterOptions


def _rec(i, j, verdict, code="rival"):
  return dict(i=i, j=j, verdict=verdict, reason=f"{verdict} {i}-{j}", reason_code=code)


def test_only_not_sure_pairs_between_components_are_registered_again(monkeypatch):
  """Scans {0, 1} and {2, 3} two components of the first graph: of the "not sure" pairs, (0, 2)
  and (1, 3) join them and run again with effort="high", and so does (0, 3), which found no
  hypothesis; (0, 1)'s second record within its component is not redone, nor (1, 2), an error
  (a scan that could not be read or described); an error of the second pass keeps the first
  record."""
  calls = []

  def fake_run_pairs(clouds, names, pairs, *, options, **kw):
    calls.append((list(pairs), options.verdict.effort))
    out = [_rec(i, j, "success" if (i, j) == (0, 2) else "error", "claimed")
           for i, j in pairs]
    return out, dict(scans_described=4, pairs_registered=len(pairs), pairs_resumed=0)

  monkeypatch.setattr(pipeline.tasks, "run_pairs", fake_run_pairs)
  monkeypatch.setattr(pipeline.tasks, "PairRecords", lambda *a, **k: None)
  recs = [_rec(0, 1, "success", "claimed"), _rec(2, 3, "success", "claimed"),
          _rec(0, 2, "not sure"), _rec(1, 3, "not sure", "chance"), _rec(0, 1, "not sure"),
          _rec(1, 2, "error", "error"), _rec(0, 3, "error", "no_hypothesis")]
  work = dict(scans_described=4, pairs_registered=7, pairs_resumed=0)
  out, more = pipeline._escalated(recs, work, [0, 0, 2, 2], [None] * 4, list("abcd"),
                                  opts=RegisterOptions(), mr=1.0, viewpoints=[None] * 4,
                                  hashes=["h"] * 4, params=None, engine=None, state_dir=None,
                                  progress=False)
  assert calls == [([(0, 2), (1, 3), (0, 3)], "high")]
  assert out[2]["verdict"] == "success" and out[2]["reason"].endswith(
      "(tried one pass (rival), then 2 seeds with 2x the keypoints pooled)")
  assert out[3] == recs[3]  # the pooled pass failed: the first record stands
  assert out[6] == recs[6]  # no hypothesis again
  assert out[:2] == recs[:2] and out[4:6] == recs[4:6]
  assert more == dict(scans_described=8, pairs_registered=10, pairs_resumed=0)
  # one component (the graph joined both scans, here through a weak edge): nothing runs again
  calls.clear()
  same = [_rec(0, 1, "not sure"), _rec(0, 1, "not sure")]
  assert pipeline._escalated(same, work, [0, 0], [None] * 2, list("ab"),
                             opts=RegisterOptions(), mr=1.0, viewpoints=[None] * 2,
                             hashes=["h"] * 2, params=None, engine=None, state_dir=None,
                             progress=False)[0] == same
  assert calls == []


def test_fast_never_escalates_and_normal_redoes_the_pairs_between_components(monkeypatch):
  """`register_all` itself: with every first-pass pair "not sure" and no edge the graph can
  use, each scan is its own component, so the default registers every pair again with
  effort="high" and "fast" registers each pair once."""
  calls = []

  def fake_run_pairs(clouds, names, pairs, *, options, **kw):
    calls.append((list(pairs), options.verdict.effort))
    out = [dict(_rec(i, j, "not sure"), transform=np.eye(4).tolist(), n_inliers=0, overlap=0.0,
                rmse=None, points=[]) for i, j in pairs]
    return out, dict(scans_described=3, pairs_registered=len(pairs), pairs_resumed=0)

  monkeypatch.setattr(pipeline.tasks, "run_pairs", fake_run_pairs)
  scans = [np.random.default_rng(k).normal(size=(200, 3)) for k in range(3)]
  every = [(0, 1), (0, 2), (1, 2)]
  fast = register_all(scans, seed=0, refine=False, effort="fast", mr=0.1)
  assert calls == [(every, "fast")] and fast.work["pairs_registered"] == 3
  calls.clear()
  res = register_all(scans, seed=0, refine=False, mr=0.1)
  assert calls == [(every, "normal"), (every, "high")] and res.work["pairs_registered"] == 6
  assert all("tried one pass (rival)" in e.reason for e in res.edges)


def test_two_rooms_of_two_fragments_each_are_claimed_by_the_default(data_root, tmp_path):
  """The four 3DMatch fragments: the first pass (one per pair, `effort="fast"`) claims neither
  room's pair; the default escalates the pairs between the first graph's components and claims
  both, and no pair across the two rooms. Run again on its state folder, it registers nothing and
  gives the same edges and poses."""
  folder = data_root / "threedmatch_scenes"
  names = ["hotel3_8", "hotel3_15", "home_at_38", "home_at_41"]
  scans = [io.read_cloud(folder / f"{n}.ply").points for n in names]
  res = register_all(scans, names=names, seed=1, refine=False, state_dir=tmp_path)
  assert res.work["pairs_registered"] > 6  # the first pass's 6, then the escalated ones
  by = {(e.i, e.j): e for e in res.edges}
  assert {k for k, e in by.items() if e.verdict == "success"} == {(0, 1), (2, 3)}
  # both claims came from the escalation: the first pass left each pair "not sure"
  assert all("tried one pass" in by[k].reason for k in ((0, 1), (2, 3)))
  assert np.asarray(res.in_model).tolist() == [True, True, False, False]
  again = register_all(scans, names=names, seed=1, refine=False, state_dir=tmp_path)
  assert again.work["pairs_registered"] == 0 and again.work["pairs_resumed"] == res.work[
      "pairs_registered"]
  assert [(e.i, e.j, e.verdict, e.reason) for e in again.edges] == [
      (e.i, e.j, e.verdict, e.reason) for e in res.edges]
  np.testing.assert_array_equal(again.poses, res.poses)
