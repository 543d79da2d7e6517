"""Multiway at scale: each scan described once, every pair registered from two scans' features
(`register`'s stages after "describe"), a state folder that makes a job resumable, any engine
giving the in-process result, and a candidate rule near-linear in the number of scans."""

from __future__ import annotations

import dataclasses
import json
import pickle

import numpy as np
import pytest

from lrf_jax import multiway
from lrf_jax.multiway import candidates as multiway_candidates
from lrf_jax.multiway import tasks as multiway_tasks
from lrf_jax.registration import pipeline, scan_features, stages
from lrf_jax.registration.options import RegisterOptions
from tests.test_multiway import _views

KW = dict(n_keypoints=400)


def test_register_scans_is_registers_later_stages_on_per_scan_keypoints():
  """`register_scans` on two `describe_scan`s equals `register`'s own stages run by hand with
  each side's keypoints drawn from a generator of the seed alone (bit for bit)."""
  clouds, _, mr = _views(2, step_deg=40.0)
  opts = RegisterOptions(mr=mr, seed=3, **KW)
  a, b = (scan_features.describe_scan(c, opts, mr=mr) for c in clouds)
  reg = scan_features.register_scans(a, b, opts)
  prepared = stages.prepare(clouds[0], clouds[1], opts)
  sides = tuple(s._replace(keypoints=stages.draw_keypoints(s.points, mr, opts.detection,
                                                           np.random.default_rng(3)))
                for s in prepared.sides)
  prepared = prepared._replace(sides=sides, rng=np.random.default_rng(3))
  timer = stages.StageTimer()
  features = stages.describe(prepared, opts.description, None, timer)
  ref = pipeline.conclude(prepared, features, stages.match(features, opts), opts, timer)
  assert np.array_equal(reg.transform, ref.transform)
  assert (reg.success, reg.reason, reg.n_inliers) == (ref.success, ref.reason, ref.n_inliers)
  assert np.array_equal(reg.correspondences, ref.correspondences)
  assert reg.success  # views 40 degrees apart: a claimed pose


def test_a_scans_features_do_not_depend_on_its_partner():
  clouds, _, mr = _views(3, step_deg=40.0)
  one = scan_features.describe_scan(clouds[1], mr=mr, **KW)
  two = scan_features.describe_scan(clouds[1], mr=mr, **KW)
  assert np.array_equal(one.runs[0].side.keypoints, two.runs[0].side.keypoints)
  assert np.array_equal(one.runs[0].descriptors[0], two.runs[0].descriptors[0])


def test_features_of_other_options_or_resolutions_are_refused():
  clouds, _, mr = _views(2)
  a = scan_features.describe_scan(clouds[0], mr=mr, **KW)
  b = scan_features.describe_scan(clouds[1], mr=mr, n_keypoints=300)
  with pytest.raises(ValueError, match="n_keypoints"):
    scan_features.register_scans(a, b, **KW)
  c = scan_features.describe_scan(clouds[1], mr=2 * mr, **KW)
  with pytest.raises(ValueError, match="mr: the source was described at"):
    scan_features.register_scans(a, c, **KW)
  with pytest.raises(ValueError, match="mr: expected a positive"):
    scan_features.describe_scan(clouds[0], mr=0.0)


def _count_describes(monkeypatch) -> list[int]:
  calls: list[int] = []
  real = scan_features.describe_scan

  def counted(*args, **kwargs):
    calls.append(1)
    return real(*args, **kwargs)
  monkeypatch.setattr(scan_features, "describe_scan", counted)
  return calls


def _same(a: multiway.MultiwayResult, b: multiway.MultiwayResult) -> None:
  assert np.array_equal(a.poses, b.poses, equal_nan=True)
  for x, y in zip(a.edges, b.edges):
    assert (x.i, x.j, x.verdict, x.reason, x.accepted) == (y.i, y.j, y.verdict, y.reason,
                                                            y.accepted)
    assert np.array_equal(x.transform, y.transform, equal_nan=True)


@pytest.fixture(scope="module")
def five():
  return _views(5, step_deg=35.0)


@pytest.fixture(scope="module")
def reference(five):
  clouds, _, mr = five
  return multiway.register_all(clouds, mr=mr, refine=False, **KW)


def test_each_scan_is_described_once_and_a_rerun_redoes_nothing(five, reference, tmp_path,
                                                                monkeypatch):
  clouds, poses, mr = five
  calls = _count_describes(monkeypatch)
  state = tmp_path / "state"
  res = multiway.register_all(clouds, mr=mr, refine=False, state_dir=state, **KW)
  assert len(calls) == 5 and res.work == dict(scans_described=5, pairs_registered=10,
                                              pairs_resumed=0)
  _same(res, reference)
  assert len(list((state / "pairs").glob("*.json"))) == 10
  assert res.in_model.all() and sum(e.verdict == "success" for e in res.edges) >= 4
  again = multiway.register_all(clouds, mr=mr, refine=False, state_dir=state, **KW)
  assert len(calls) == 5 and again.work == dict(scans_described=0, pairs_registered=0,
                                                pairs_resumed=10)
  _same(again, res)


def test_a_job_killed_midway_keeps_its_finished_pairs(five, reference, tmp_path, monkeypatch):
  clouds, _, mr = five
  state = tmp_path / "state"
  real = multiway_tasks.pair_task
  done: list[int] = []

  def dies_at_the_fourth(payload):
    if len(done) == 3:
      raise KeyboardInterrupt
    done.append(1)
    return real(payload)
  monkeypatch.setattr(multiway_tasks, "pair_task", dies_at_the_fourth)
  with pytest.raises(KeyboardInterrupt):
    multiway.register_all(clouds, mr=mr, refine=False, state_dir=state, **KW)
  assert len(list((state / "pairs").glob("*.json"))) == 3
  monkeypatch.setattr(multiway_tasks, "pair_task", real)
  calls = _count_describes(monkeypatch)
  res = multiway.register_all(clouds, mr=mr, refine=False, state_dir=state, **KW)
  assert res.work == dict(scans_described=len(calls), pairs_registered=7, pairs_resumed=3)
  _same(res, reference)


def test_a_changed_scan_redoes_its_pairs_only(five, tmp_path):
  clouds, _, mr = five
  state = tmp_path / "state"
  multiway.register_all(clouds, mr=mr, refine=False, state_dir=state, **KW)
  moved = list(clouds)
  moved[2] = moved[2] + 1e-3 * mr
  res = multiway.register_all(moved, mr=mr, refine=False, state_dir=state, **KW)
  assert res.work == dict(scans_described=5, pairs_registered=4, pairs_resumed=6)
  other = multiway.register_all(clouds[:2], mr=mr, refine=False, state_dir=state,
                                n_keypoints=300)
  assert other.work["pairs_resumed"] == 0  # another option: the pair (0, 1) again


@dataclasses.dataclass
class _Outcome:
  index: int
  value: object
  error: str | None = None


class _FarEngine:
  """An engine that ships every payload and result through pickle and finishes them in
  reverse order (as a cluster may), optionally losing the payloads `lose` names."""

  def __init__(self, lose=()):
    self.lose, self.puts = set(lose), 0

  def put(self, value):
    self.puts += 1
    return pickle.loads(pickle.dumps(value))

  def run(self, fn, payloads):
    for k in reversed(range(len(payloads))):
      payload = pickle.loads(pickle.dumps(payloads[k]))
      if isinstance(payload, dict) and (payload.get("i"), payload.get("j")) in self.lose:
        yield _Outcome(k, None, "lost after 4 attempts: NodeDiedError")
        continue
      yield _Outcome(k, pickle.loads(pickle.dumps(fn(payload))))


def test_an_engine_gives_the_in_process_result(five, reference):
  clouds, _, mr = five
  far = _FarEngine()
  res = multiway.register_all(clouds, mr=mr, refine=False, engine=far, **KW)
  _same(res, reference)
  assert far.puts == 5  # each scan's features handed over once


def test_a_pair_the_engine_lost_is_no_edge_and_the_next_run_redoes_it(five, reference,
                                                                       tmp_path):
  clouds, _, mr = five
  state = tmp_path / "state"
  res = multiway.register_all(clouds, mr=mr, refine=False, engine=_FarEngine(lose={(1, 3)}),
                              state_dir=state, **KW)
  lost = next(e for e in res.edges if (e.i, e.j) == (1, 3))
  assert lost.verdict == "error" and "the engine lost this pair" in lost.reason
  assert len(list((state / "pairs").glob("*.json"))) == 9
  again = multiway.register_all(clouds, mr=mr, refine=False, state_dir=state, **KW)
  assert again.work["pairs_registered"] == 1
  _same(again, reference)


def test_records_are_plain_json_of_the_edge(five, tmp_path):
  """A record names its scans by content (source, target hashes) and its lrf_jax version, never
  by their positions in the run that wrote it."""
  from lrf_jax import records
  clouds, _, mr = five
  multiway.register_all(clouds[:2], mr=mr, refine=False, state_dir=tmp_path, **KW)
  rec = json.loads(next((tmp_path / "pairs").glob("*.json")).read_text())
  assert {"source", "target", "transform", "verdict", "reason", "points", "version"} <= set(rec)
  assert not {"i", "j"} & set(rec)
  assert rec["version"] == records.version()
  assert np.asarray(rec["points"]).shape == (multiway_tasks.EDGE_POINTS, 3)


def _edges(res):
  return [(res.names[e.i], res.names[e.j], e.verdict, e.transform.round(12).tolist(),
           e.accepted, round(e.residual_mr, 9)) for e in res.edges]


@pytest.mark.parametrize("order", ["reordered", "grown", "repeated"])
def test_records_read_back_in_another_run_give_a_fresh_runs_result(five, tmp_path, order):
  """Records written by a run over 3 scans, read by a run over the same scans in another order,
  among a 4th, or with one scan twice: the poses and edges of a fresh run into an empty folder
  (a record gives the edge between the scans it was computed for, wherever they sit now)."""
  clouds, _, mr = five
  names = ["a", "b", "c", "d"]
  kw = dict(mr=mr, refine=False, **KW)
  state = tmp_path / "state"
  multiway.register_all(clouds[:3], names=names[:3], state_dir=state, **kw)
  pick = {"reordered": [2, 0, 1], "grown": [0, 1, 3, 2], "repeated": [1, 0, 1]}[order]
  scans = [clouds[k] for k in pick]
  labels = [names[k] + ("_2" if pick[:n].count(k) else "") for n, k in enumerate(pick)]
  resumed = multiway.register_all(scans, names=labels, state_dir=state, **kw)
  fresh = multiway.register_all(scans, names=labels, state_dir=tmp_path / "empty", **kw)
  assert _edges(resumed) == _edges(fresh)
  np.testing.assert_array_equal(resumed.poses, fresh.poses)
  read = {"reordered": 1, "grown": 3, "repeated": 1}[order]  # pairs whose direction was seen
  assert resumed.work["pairs_resumed"] == read
  assert resumed.work["pairs_registered"] == len(resumed.edges) - read


def test_a_record_of_another_version_is_redone(five, tmp_path, monkeypatch):
  from lrf_jax import records
  clouds, _, mr = five
  kw = dict(mr=mr, refine=False, state_dir=tmp_path, **KW)
  multiway.register_all(clouds[:2], **kw)
  assert multiway.register_all(clouds[:2], **kw).work["pairs_resumed"] == 1
  monkeypatch.setattr(records, "version", lambda: "0.0.1")
  assert multiway.register_all(clouds[:2], **kw).work["pairs_registered"] == 1


def _brute_force_candidates(clouds, loop_candidates, seed=0):
  """The candidate rule with the n x n signature distances (the rule's definition)."""
  n = len(clouds)
  pairs = {(i, i + 1) for i in range(n - 1)}
  extent = max(float(np.linalg.norm(np.ptp(c, axis=0))) for c in clouds)
  sig = np.stack([multiway_candidates.shape_signature(c, max_distance=extent, seed=seed)
                  for c in clouds])
  dist = np.abs(sig[:, None, :] - sig[None, :, :]).sum(axis=2)
  np.fill_diagonal(dist, np.inf)
  for i in range(n):
    for j in np.argsort(dist[i], kind="stable")[:loop_candidates]:
      pairs.add((min(i, int(j)), max(i, int(j))))
  return sorted(pairs)


def test_candidate_pairs_equal_the_brute_force_rule_and_grow_linearly():
  rng = np.random.default_rng(1)
  clouds = [rng.normal(size=(300, 3)) * (1 + rng.random(3) * 2) for _ in range(60)]
  pairs = multiway.candidate_pairs(clouds)
  assert pairs == _brute_force_candidates(clouds, 3)
  assert len(pairs) <= (1 + 3) * len(clouds)
  assert all(i < j for i, j in pairs)


def test_the_command_line_resumes_from_its_output_folder(five, tmp_path, capsys):
  from lrf_jax import io
  from lrf_jax.cli.register import main
  clouds, _, mr = five
  paths = []
  for k, c in enumerate(clouds[:3]):
    paths.append(tmp_path / f"view{k}.ply")
    io.write_ply(paths[-1], c, dtype="float64")
  out = tmp_path / "model"
  argv = [*map(str, paths), "--out-dir", str(out), "--keypoints", "400", "--quiet",
          "--no-figures", "--mr", repr(mr)]
  assert main(argv) == 0
  first = capsys.readouterr()
  assert "3 pairs registered, 0 read from" in first.err
  poses = (out / "poses.txt").read_text()
  assert main(argv) == 0
  assert "0 pairs registered, 3 read from" in capsys.readouterr().err
  assert (out / "poses.txt").read_text() == poses
  assert main([*argv, "--address", "127.0.0.1:1"]) == 2
  assert "--address" in capsys.readouterr().err
  # Nothing to do: the cluster is never joined (nothing answers at 127.0.0.1:1) ...
  assert main([*argv, "--engine", "ray", "--address", "127.0.0.1:1"]) == 0
  capsys.readouterr()
  # ... work to do: refused at once, naming the address, not after Ray's minutes of retries
  argv[argv.index(str(out))] = str(tmp_path / "other")
  assert main([*argv, "--engine", "ray", "--address", "127.0.0.1:1"]) == 2
  assert "no Ray cluster answers at 127.0.0.1:1" in capsys.readouterr().err


def test_a_custom_pairwise_takes_no_engine_or_state(tmp_path):
  clouds, _, mr = _views(2)
  for kw in (dict(engine=_FarEngine()), dict(state_dir=tmp_path)):
    with pytest.raises(ValueError, match="custom pairwise"):
      multiway.register_all(clouds, mr=mr, pairwise=lambda *a, **k: pytest.fail("ran"), **kw)


def test_a_scan_that_cannot_be_described_gives_error_edges_naming_it():
  clouds, _, mr = _views(3, step_deg=35.0)
  tiny = np.random.default_rng(0).normal(size=(30, 3)) * mr * 0.01
  res = multiway.register_all([*clouds, tiny], names=["a", "b", "c", "tiny"], mr=mr,
                              refine=False, n_keypoints=300, voxel_size=mr * 0.5)
  bad = [e for e in res.edges if 3 in (e.i, e.j)]
  assert len(bad) == 3 and all(e.verdict == "error" and e.reason.startswith("scan tiny: ")
                               for e in bad)
  assert res.left_out == ["tiny"] and res.in_model[:3].all()
