"""Multiway's "not sure" edges (issue 41) through `register_all` and the command line: two wrong
weak edges that agree with each other never place a scan; independent routes through scans placed
with confidence do, and say so. (The pose graph's rule itself: tests/test_pose_graph.py.)"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from lrf_jax import multiway
from lrf_jax.multiway import pipeline as multiway_pipeline
from lrf_jax.multiway import outputs as multiway_outputs
from tests.lrf_testing import random_pose, world_poses


def _views(n):
  rng = np.random.default_rng(0)
  base = rng.normal(size=(400, 3))
  world = world_poses(n)
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
  run = _oracle(clouds, world, intruder, random_pose(77), {(0, 1), (1, 2), (2, 3), (0, 2)})
  res = multiway.register_all([*clouds, intruder], names=list("abcdx"), mr=0.05, pairwise=run,
                              refine=False)
  assert res.left_out == ["x"] and res.placed_not_sure == []
  assert not any(e.accepted for e in res.edges if 4 in (e.i, e.j))


def test_a_group_joined_by_not_sure_edges_is_flagged_in_edges_tsv():
  """Views {a, b} and {c, d} ("success" inside each), joined by "not sure" edges only: placed,
  and said so (`placed_not_sure`, edges.tsv's placement column)."""
  clouds, world = _views(4)
  intruder = np.random.default_rng(5).normal(size=(333, 3))
  run = _oracle(clouds, world, intruder, random_pose(77), {(0, 1), (2, 3)})
  res = multiway.register_all(clouds, names=list("abcd"), mr=0.05, pairwise=run, refine=False)
  assert res.in_model.all() and res.placed_not_sure == ["c", "d"]
  rows = [line.split("\t") for line in multiway_outputs.edges_table(res).splitlines()]
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
  monkeypatch.setattr(multiway_pipeline, "register_all", run)
  assert main([*paths, "--quiet"]) == 0
  assert 'edges (check them; edges.tsv\'s placement): s1\n' in capsys.readouterr().err

