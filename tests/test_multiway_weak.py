"""Multiway's "not sure" edges (issue 41): two wrong weak edges that agree with each other never
place a scan; independent routes through scans placed with confidence do, and say so."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from lrf_jax.registration import multiway
from lrf_jax.registration import pose_graph


def _pose(seed: int) -> np.ndarray:
  x = np.eye(4)
  x[:3, :3] = Rotation.random(random_state=seed).as_matrix()
  x[:3, 3] = np.random.default_rng(seed).normal(size=3)
  return x


def _edge(x, i, j, seed, wrong=None):
  """Edge i -> j from poses x (or from the wrong pose `wrong` of scan i)."""
  xi = x[i] if wrong is None else wrong
  pts = np.random.default_rng(seed).normal(size=(16, 3))
  return pose_graph.PoseEdge(i, j, np.linalg.inv(x[j]) @ xi, pts, 1.0)


def _world(n):
  return np.stack([np.eye(4)] + [_pose(k) for k in range(1, n)])


def test_two_agreeing_wrong_weak_edges_from_one_scan_never_place_it():
  """Scans 0-1-2 linked by trusted edges; scan 3 (foreign) has two "not sure" edges, to 1 and
  to 2, that agree on one wrong pose (a foreign scan matched twice to one surface that 1 and 2
  both see). They confirm each other only: scan 3 stays out. (The rule before issue 41 took
  any two agreeing weak edges and placed it.)"""
  x = _world(4)
  wrong = _pose(99)
  edges = [_edge(x, 0, 1, 0), _edge(x, 1, 2, 1), _edge(x, 0, 2, 2),
           _edge(x, 3, 1, 3, wrong), _edge(x, 3, 2, 4, wrong)]
  res = pose_graph.solve(4, edges, trusted=[True, True, True, False, False], seed=0)
  assert list(res.component) == [0, 0, 0, 3]
  assert not res.accepted[3:].any()
  assert res.confident[:3].all()


def test_independent_routes_join_two_confident_groups_flagged_not_sure():
  """Groups {0, 1, 2} and {3, 4} (trusted edges inside each) joined by two agreeing weak edges
  with distinct scans at both ends (2-3 and 1-4): a cycle with two trusted legs; they join,
  and the scans placed through them are not confident. Two weak edges from one scan of the
  group (2-3 and 2-4) do not join it."""
  x = _world(5)
  inside = [_edge(x, 0, 1, 0), _edge(x, 1, 2, 1), _edge(x, 3, 4, 2)]
  res = pose_graph.solve(5, inside + [_edge(x, 2, 3, 3), _edge(x, 1, 4, 4)],
                         trusted=[True] * 3 + [False] * 2, seed=0)
  assert (res.component == 0).all() and res.accepted.all()
  assert list(res.confident) == [True, True, True, False, False]
  np.testing.assert_allclose(res.poses, x, atol=1e-6)
  res = pose_graph.solve(5, inside + [_edge(x, 2, 3, 3), _edge(x, 2, 4, 4)],
                         trusted=[True] * 3 + [False] * 2, seed=0)
  assert list(res.component) == [0, 0, 0, 3, 3]


def test_weak_edges_between_unconfirmed_scans_do_not_chain():
  """Scan 3 has agreeing weak edges to 1 and 2 and scan 4 to 2 and 3: neither group of routes
  runs through two scans placed with confidence on both sides."""
  x = _world(5)
  edges = [_edge(x, 0, 1, 0), _edge(x, 1, 2, 1), _edge(x, 3, 1, 2), _edge(x, 3, 2, 3),
           _edge(x, 4, 2, 4), _edge(x, 4, 3, 5)]
  res = pose_graph.solve(5, edges, trusted=[True, True, False, False, False, False], seed=0)
  assert list(res.component) == [0, 0, 0, 3, 4]


def _views(n):
  rng = np.random.default_rng(0)
  base = rng.normal(size=(400, 3))
  world = _world(n)
  return [(base[k * 30:k * 30 + 200] - world[k][:3, 3]) @ world[k][:3, :3] for k in range(n)], \
      world


def _oracle(clouds, world, intruder, wrong, sure):
  """Exact transforms between the views ("success" for the pairs in `sure`, else "not sure");
  the intruder "not sure" everywhere, at one wrong pose that its edges agree on."""
  def run(src, dst, **_):
    def index(c):
      if c.points.shape == intruder.shape:
        return -1
      return next(k for k, v in enumerate(clouds) if np.array_equal(v, c.points))
    i, j = index(src), index(dst)
    xi = wrong if i < 0 else world[i]
    xj = wrong if j < 0 else world[j]
    ok = i >= 0 and j >= 0 and ((i, j) in sure or (j, i) in sure)
    return SimpleNamespace(transform=np.linalg.inv(xj) @ xi, success=ok,
                           reason="oracle" if ok else "not sure", n_inliers=50 if ok else 12,
                           overlap=0.5, rmse=0.0, reason_code="claimed" if ok else "rival")
  return run


def test_register_all_leaves_out_an_intruder_whose_weak_edges_agree():
  """The issue-41 case in small: a foreign scan whose "not sure" edges to every scan agree on
  one wrong pose. Before, it was placed (two agreeing weak edges); now it is left out."""
  clouds, world = _views(4)
  intruder = np.random.default_rng(5).normal(size=(333, 3))
  run = _oracle(clouds, world, intruder, _pose(77), {(0, 1), (1, 2), (2, 3), (0, 2)})
  res = multiway.register_all([*clouds, intruder], names=list("abcdx"), mr=0.05, pairwise=run,
                              refine=False)
  assert res.left_out == ["x"] and res.placed_not_sure == []
  assert not any(e.accepted for e in res.edges if 4 in (e.i, e.j))


def test_a_group_joined_by_not_sure_edges_is_flagged_in_edges_tsv():
  """Views {a, b} and {c, d} ("success" inside each), joined by "not sure" edges only: placed,
  and said so (`placed_not_sure`, edges.tsv's placement column)."""
  clouds, world = _views(4)
  intruder = np.random.default_rng(5).normal(size=(333, 3))
  run = _oracle(clouds, world, intruder, _pose(77), {(0, 1), (2, 3)})
  res = multiway.register_all(clouds, names=list("abcd"), mr=0.05, pairwise=run, refine=False)
  assert res.in_model.all() and res.placed_not_sure == ["c", "d"]
  rows = [line.split("\t") for line in multiway.edges_table(res).splitlines()]
  col = rows[0].index("placement")
  table = {(r[0], r[1]): r[col] for r in rows[1:]}
  assert table[("a", "b")] == "confident" and table[("c", "d")] == "both_not_sure"
  assert table[("a", "c")] == "target_not_sure"


def test_cli_names_the_scans_placed_only_through_not_sure_edges(tmp_path, monkeypatch, capsys):
  from lrf_jax.cli.register import main
  paths = []
  for k in range(3):
    paths.append(str(tmp_path / f"s{k}.npy"))
    np.save(paths[-1], np.random.default_rng(k).normal(size=(30, 3)))

  def run(clouds, *, names, **kw):
    return multiway.MultiwayResult(names=tuple(names), poses=np.tile(np.eye(4), (3, 1, 1)),
                                   in_model=np.ones(3, bool), reference=0, edges=(), mr=1.0,
                                   seconds=0.0, confident=np.array([True, False, True]))
  monkeypatch.setattr(multiway, "register_all", run)
  assert main([*paths, "--quiet"]) == 0
  assert 'edges (check them; edges.tsv\'s placement): s1\n' in capsys.readouterr().err
