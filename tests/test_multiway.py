"""Multiway registration (`lrf_jax.multiway`): `register_all` rejecting a wrong edge, the joint
ICP, determinism, the outputs and the `lrf-register a b c --out-dir D` command. (The pose graph
against brute-force references on synthetic poses: tests/test_pose_graph.py.)"""

from __future__ import annotations

import functools
import json
import os
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax import multiway
from lrf_jax.multiway import pipeline as multiway_pipeline
from lrf_jax.multiway import outputs as multiway_outputs
from lrf_jax.multiway import pose_graph
from lrf_jax.datasets.synthetic import hidden_point_removal, make_demo_mesh, vertex_normals
from tests.lrf_testing import random_poses, wrong_edge


def _gauge(p: np.ndarray) -> np.ndarray:
  return np.linalg.inv(p[0]) @ p


@functools.cache
def _views(n: int, seed: int = 0, step_deg: float = 60.0):
  """n partial views of the demo blob from viewpoints `step_deg` apart around z, each moved by
  a random rigid motion; (clouds, world-from-view poses, mr)."""
  points, faces = make_demo_mesh("blob", seed)
  normals = vertex_normals(points, faces)
  from lrf_jax.geometry.resolution import mesh_resolution
  mr = mesh_resolution(points, faces)[0]
  poses = random_poses(n, seed + 100)
  clouds = []
  for k in range(n):
    a = np.radians(step_deg * k)
    vp = 4.0 * np.array([np.cos(a), np.sin(a), 0.3])
    vis = hidden_point_removal(points, vp) & (np.einsum("ij,ij->i", normals, vp - points) > 0)
    view = points[vis]
    inv = np.linalg.inv(poses[k])
    clouds.append(view @ inv[:3, :3].T + inv[:3, 3])  # view k in its own frame
  return tuple(clouds), poses, mr


def _oracle(clouds, poses):
  """A pairwise registration that knows the truth except for the pair (0, 2) it gets wrong,
  while claiming success: a wrong loop closure the verdict let through."""
  def run(src, dst, **_):
    i = next(k for k, c in enumerate(clouds) if c.shape == src.points.shape)
    j = next(k for k, c in enumerate(clouds) if c.shape == dst.points.shape)
    t = np.linalg.inv(poses[j]) @ poses[i]
    if (i, j) == (0, 2):
      t = wrong_edge(pose_graph.PoseEdge(0, 2, t, np.zeros((1, 3)))).transform
    return SimpleNamespace(transform=t, success=True, reason="oracle", n_inliers=100,
                           overlap=0.5, rmse=0.0)
  return run


def test_register_all_rejects_a_wrong_edge_and_refines():
  """Exact pairwise transforms but one wrong loop closure claimed as success: it is rejected,
  the pose graph recovers the poses exactly, and the joint ICP keeps them (it pairs nearest
  points, so boundary pairs move them by a fraction of a mesh resolution)."""
  clouds, poses, mr = _views(4)
  gt = np.linalg.inv(poses[0]) @ poses
  for refine, tol_deg, tol_mr in ((False, 1e-6, 1e-6), (True, 0.5, 0.5)):
    res = multiway.register_all(clouds, mr=mr, pairwise=_oracle(clouds, poses), seed=0,
                                refine=refine)
    wrong = [e for e in res.edges if (e.i, e.j) == (0, 2)][0]
    assert not wrong.accepted and all(e.accepted for e in res.edges if (e.i, e.j) != (0, 2))
    assert res.in_model.all() and res.reference == 0
    for k in range(4):
      err_r = np.degrees(Rotation.from_matrix(res.poses[k, :3, :3] @ gt[k, :3, :3].T)
                         .magnitude())
      assert err_r < tol_deg and np.linalg.norm(res.poses[k, :3, 3] - gt[k, :3, 3]) < tol_mr * mr
  assert set(res.timings) == {"load", "pairwise", "graph", "refine"}


def test_unconnected_scan_is_left_out_and_the_reference_moves_if_it_is_first():
  clouds, poses, mr = _views(3)
  intruder = np.random.default_rng(0).normal(size=(3000, 3))

  def run(src, dst, **kw):
    if src.points.shape == intruder.shape or dst.points.shape == intruder.shape:
      return SimpleNamespace(transform=np.eye(4), success=False, reason="not sure",
                             n_inliers=3, overlap=0.01, rmse=1.0)
    return _oracle([c for c in clouds], poses)(src, dst)

  res = multiway.register_all([intruder, *clouds], mr=mr, pairwise=run, names=list("xabc"))
  assert res.left_out == ["x"] and res.reference == 1
  assert np.isnan(res.poses[0]).all()
  points, scan = multiway_outputs.merged_cloud([intruder, *clouds], res)
  assert len(points) == sum(len(c) for c in clouds) and 0 not in scan
  down, scan_down = multiway_outputs.merged_cloud([intruder, *clouds], res, voxel=4 * mr)
  assert len(down) < len(points) and set(np.unique(scan_down)) <= {1, 2, 3}


def test_candidate_rule_for_large_sets():
  rng = np.random.default_rng(0)
  clouds = [rng.normal(size=(500, 3)) * (1 + 0.1 * k) for k in range(15)]
  pairs = multiway.candidate_pairs(clouds, loop_candidates=2)
  assert all((k, k + 1) in pairs for k in range(14))
  assert len(pairs) < 15 * 14 // 2 and pairs == sorted(set(pairs))
  assert len(multiway.candidate_pairs(clouds[:5])) == 10


def test_scan_names_and_bad_input_names_the_file(tmp_path):
  assert multiway_outputs.scan_names(["a/x.txt.gz", "b/x.ply", "c.ply", np.zeros((3, 3))]) == [
      "x", "x_2", "c", "scan3"]
  bad = tmp_path / "broken.ply"
  bad.write_text("not a ply\n")
  with pytest.raises(ValueError, match="broken.ply"):
    multiway.register_all([np.zeros((20, 3)), str(bad)])
  with pytest.raises(ValueError, match="at least 2 scans"):
    multiway.register_all([np.zeros((20, 3))])


def test_scan_names_are_distinct_and_keep_every_natural_name():
  """`d/a.ply d/a_2.ply e/a.ply` were named a, a_2, a_2: two scans, one pose file. A repeated
  name now takes the first "_k" that is no scan's natural name and not given yet; equal
  ignoring case counts as repeated (one file on a case-insensitive file system)."""
  assert multiway_outputs.scan_names(["d/a.ply", "d/a_2.ply", "e/a.ply"]) == ["a", "a_2", "a_3"]
  assert multiway_outputs.scan_names(["d/a.ply", "e/a.ply", "d/a_2.ply"]) == ["a", "a_3", "a_2"]
  assert multiway_outputs.scan_names(["A.ply", "a.ply", "x/a.ply"]) == ["A", "a_2", "a_3"]
  assert multiway_outputs.scan_names(["scan1.ply", np.zeros((3, 3))]) == ["scan1", "scan1_2"]
  assert multiway_outputs.scan_names(["d/..", "a\tb.ply", "c\n.npy"]) == ["scan0", "a_b", "c_"]
  long = ["x" * 253 + ".gz", "d/" + "x" * 251 + ".ply", "é" * 127 + ".ply"]
  names = multiway_outputs.scan_names(long)
  assert names[0] == "x" * 251 and names[1] == "x" * 249 + "_2" and names[2] == "é" * 125
  rng = np.random.default_rng(0)
  for _ in range(300):  # any mix of repeated, suffixed and case-varied names
    scans = [f"{rng.choice(['d', 'e'])}/{rng.choice(['a', 'A', 'a_2', 'a_3', 'b'])}"
             f"{rng.choice(['', '_2'])}.ply" for _ in range(rng.integers(2, 9))]
    names = multiway_outputs.scan_names(scans)
    assert len({n.casefold() for n in names}) == len(names), (scans, names)
    assert multiway_outputs.check_names(names) == names
    first = {}
    for scan, name in zip(scans, names):
      natural = Path(scan).stem
      first.setdefault(natural.casefold(), name)
      assert first[natural.casefold()] == natural or name != natural  # first keeps it


@pytest.mark.parametrize("name,fragment", [
    ("../../victim", "path separator"), ("a/b", "path separator"), ("..", "'.' or '..'"),
    (".", "'.' or '..'"), ("", "non-empty"), (3, "non-empty string"), ("a\tb", "control"),
    ("a\nb", "control"), ("x" * 252, "252 bytes"), ("é" * 126, "252 bytes"),
    ("B", "scan 0 too"),
])
def test_names_that_are_not_file_names_are_refused(tmp_path, name, fragment):
  """`register_all(names=['../../victim', ...])` then `write_outputs` wrote ../../victim.txt,
  outside the folder; a 252-byte name failed on its 256-byte file name. Refused as ValueError
  naming the argument and the name, before any work and before anything is written."""
  names = ["b", name]
  with pytest.raises(ValueError, match=r"names\[1\]: .*" + re.escape(fragment)):
    multiway.register_all([np.zeros((20, 3)), np.zeros((20, 3))], names=names,
                          pairwise=lambda *a, **k: pytest.fail("registered"))
  res = _result(names, [True, True])
  out = tmp_path / "a" / "b"
  with pytest.raises(ValueError, match=r"result.names\[1\]: .*" + re.escape(fragment)):
    multiway_outputs.write_outputs(res, [np.zeros((3, 3))] * 2, out, figures=False)
  with pytest.raises(ValueError, match=re.escape(fragment)):
    multiway_outputs.output_paths(names, out)
  assert list(tmp_path.iterdir()) == []


def _result(names, in_model, mr=1.0) -> multiway.MultiwayResult:
  """A result of `register_all` with identity poses for the scans in the model."""
  n = len(names)
  poses = np.where(np.asarray(in_model)[:, None, None], np.tile(np.eye(4), (n, 1, 1)), np.nan)
  return multiway.MultiwayResult(names=tuple(names), poses=poses, in_model=np.asarray(in_model),
                                 reference=0, edges=(), mr=mr, seconds=0.0)


def _clouds(n):
  return [np.random.default_rng(k).normal(size=(50, 3)) for k in range(n)]


def _files(folder):
  return sorted(p.name for p in folder.iterdir())


def test_a_rerun_leaves_only_its_own_files(tmp_path):
  """A rerun into an --out-dir kept the pose file of a scan it left out, and the figures of the
  earlier run: the folder showed a model that no run made. The run lists its files in
  manifest.json; a rerun removes the earlier run's files it does not write, and replaces the
  others; files no manifest lists are never touched."""
  out = tmp_path / "model"
  written = multiway_outputs.write_outputs(_result(["a", "b", "c"], [True] * 3), _clouds(3), out)
  assert _files(out) == ["a.txt", "b.txt", "c.txt", "edges.tsv", "graph.png", "manifest.json",
                         "merged.ply", "merged.png", "poses.txt"]
  manifest = json.loads((out / "manifest.json").read_text())
  assert sorted(manifest["files"]) == sorted(p.name for p in written)
  (out / "notes.md").write_text("mine")  # the user's, in an earlier run's folder: kept
  multiway_outputs.write_outputs(_result(["a", "b", "c"], [True, False, True]), _clouds(3), out,
                         figures=False)
  assert _files(out) == ["a.txt", "c.txt", "edges.tsv", "manifest.json", "merged.ply",
                         "notes.md", "poses.txt"]
  assert sorted(json.loads((out / "manifest.json").read_text())["files"]) == [
      "a.txt", "c.txt", "edges.tsv", "merged.ply", "poses.txt"]
  multiway_outputs.write_outputs(_result(["x", "y"], [True, True]), _clouds(2), out, figures=False)
  assert _files(out) == ["edges.tsv", "manifest.json", "merged.ply", "notes.md", "poses.txt",
                         "x.txt", "y.txt"]
  assert (out / "notes.md").read_text() == "mine"


def test_an_interrupted_rerun_is_cleaned_up_by_the_next(tmp_path, monkeypatch):
  """Until a run ends, its manifest lists both runs' files: whatever an interrupted run leaves,
  the next run removes."""
  out = tmp_path / "model"
  multiway_outputs.write_outputs(_result(["a", "b"], [True, True]), _clouds(2), out, figures=False)

  def broken(*a, **k):
    raise KeyboardInterrupt
  with monkeypatch.context() as m:
    m.setattr(multiway_outputs, "write_merged_ply", broken)
    with pytest.raises(KeyboardInterrupt):
      multiway_outputs.write_outputs(_result(["c", "d"], [True, True]), _clouds(2), out, figures=False)
  listed = json.loads((out / "manifest.json").read_text())["files"]
  assert set(_files(out)) - {"manifest.json"} <= set(listed)
  multiway_outputs.write_outputs(_result(["e", "f"], [True, True]), _clouds(2), out, figures=False)
  assert _files(out) == ["e.txt", "edges.tsv", "f.txt", "manifest.json", "merged.ply",
                         "poses.txt"]


def test_a_folder_no_run_wrote_is_refused(tmp_path):
  """A non-empty folder without an earlier run's manifest, or with a manifest that is not one
  (unreadable, or listing a path outside the folder), is refused before anything is written;
  an output path that is a FIFO too."""
  res, clouds = _result(["a", "b"], [True, True]), _clouds(2)
  out = tmp_path / "photos"
  out.mkdir()
  (out / "holiday.jpg").write_bytes(b"jpeg")
  with pytest.raises(ValueError, match="out_dir: .*photos is not empty and holds no "
                                       "manifest.json"):
    multiway_outputs.write_outputs(res, clouds, out, figures=False)
  assert _files(out) == ["holiday.jpg"]
  victim = tmp_path / "victim.txt"
  victim.write_text("keep me")
  for text in ("{not json", json.dumps({"files": ["holiday.jpg"]}),
               json.dumps({"kind": multiway_outputs.MANIFEST_KIND, "files": ["../victim.txt"]})):
    (out / "manifest.json").write_text(text)
    with pytest.raises(ValueError, match="is not a manifest of an earlier run"):
      multiway_outputs.write_outputs(res, clouds, out, figures=False)
  assert victim.read_text() == "keep me" and _files(out) == ["holiday.jpg", "manifest.json"]
  earlier = tmp_path / "earlier"
  multiway_outputs.write_outputs(res, clouds, earlier, figures=False)
  (earlier / "b.txt").unlink()
  os.mkfifo(earlier / "b.txt")
  before = (earlier / "manifest.json").read_bytes()
  with pytest.raises(ValueError, match="out_dir: .*b.txt is a FIFO"):
    multiway_outputs.write_outputs(res, clouds, earlier, figures=False)
  assert (earlier / "b.txt").is_fifo() and (earlier / "manifest.json").read_bytes() == before
  with pytest.raises(ValueError, match="out_dir: .*is not a folder"):
    multiway_outputs.write_outputs(res, clouds, victim, figures=False)


def _fake_register_all(monkeypatch, in_model=None):
  """`lrf-register a b c --out-dir D` with `register_all` replaced by identity poses (the
  scans in `in_model`, default all): these tests are about the outputs."""
  def run(clouds, *, names, **kw):
    return _result(names, in_model or [True] * len(names))
  monkeypatch.setattr(multiway_pipeline, "register_all", run)


def _npy_scans(folder, *rel):
  paths = []
  for k, r in enumerate(rel):
    path = folder / r
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, np.random.default_rng(k).normal(size=(30, 3)))
    paths.append(str(path))
  return paths


def test_cli_names_collide_no_more_and_reruns_are_clean(tmp_path, capsys, monkeypatch):
  from lrf_jax.cli.register import main
  scans = _npy_scans(tmp_path / "in", "d/a.npy", "d/a_2.npy", "e/a.npy")
  out = tmp_path / "model"
  _fake_register_all(monkeypatch)
  assert main([*scans, "--out-dir", str(out), "--quiet", "--no-figures"]) == 0
  assert _files(out) == ["a.txt", "a_2.txt", "a_3.txt", "edges.tsv", "manifest.json",
                         "merged.ply", "poses.txt"]
  _fake_register_all(monkeypatch, [True, False, True])  # scan a_2 left out this time
  assert main([*scans, "--out-dir", str(out), "--quiet", "--no-figures"]) == 3
  assert _files(out) == ["a.txt", "a_3.txt", "edges.tsv", "manifest.json", "merged.ply",
                         "poses.txt"]
  capsys.readouterr()
  other = tmp_path / "other"
  other.mkdir()
  (other / "mine.txt").write_text("x")
  os.mkfifo(out / "a_2.txt")
  for folder, fragment in ((other, "is not empty and holds no manifest.json"),
                           (out, "a_2.txt is a FIFO (named pipe); expected a regular file")):
    monkeypatch.setattr(multiway_pipeline, "register_all", lambda *a, **k: pytest.fail("registered"))
    assert main([*scans, "--out-dir", str(folder), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --out-dir: ") and fragment in err, err
  assert _files(other) == ["mine.txt"]


def test_pairs_without_a_hypothesis_are_no_edges_and_the_run_goes_on():
  """`register` raised IndexError when its graph built no hypothesis (here: one correspondence
  per pair), which ended the multiway run. Such a pair now gives a not-estimated registration
  (the identity): an "error" edge with its reason, no edge in the graph; the other pairs make
  the model."""
  clouds, poses, mr = _views(3)
  res = multiway.register_all(clouds, mr=mr, refine=False, n_keypoints=10, n_correspondences=1)
  assert [e.verdict for e in res.edges] == ["error"] * 3
  assert all(e.reason.startswith("no pose hypothesis") and not e.accepted for e in res.edges)
  assert res.in_model.tolist() == [True, False, False] and res.left_out == ["scan1", "scan2"]
  oracle = _oracle(clouds, poses)

  def some_without(src, dst, **kw):  # the pair (0, 1) builds no hypothesis
    if src.points.shape == clouds[0].shape and dst.points.shape == clouds[1].shape:
      return SimpleNamespace(transform=np.eye(4), success=False, reason="no pose hypothesis",
                             n_inliers=0, overlap=0.1, rmse=1.0, estimated=False)
    return oracle(src, dst, **kw)
  res = multiway.register_all(clouds, mr=mr, pairwise=some_without, refine=False)
  assert [e.verdict for e in res.edges] == ["error", "success", "success"]
  assert np.isnan(res.edges[0].transform).all() and res.edges[0].reason == "no pose hypothesis"


def test_cli_end_to_end_into_a_tmp_dir(tmp_path, capsys):
  """`lrf-register a b c --out-dir D` with the real pairwise registration on three small views
  of the demo blob: poses right, every output written, refusing an input as an output."""
  from lrf_jax import io
  from lrf_jax.cli.register import main
  clouds, poses, mr = _views(3, step_deg=50.0)
  paths = []
  for k, c in enumerate(clouds):
    sub = c[np.random.default_rng(k).choice(len(c), min(len(c), 6000), replace=False)]
    paths.append(tmp_path / f"view{k}.ply")
    io.write_ply(paths[-1], sub, dtype="float64")
  out = tmp_path / "model"
  rc = main([*map(str, paths), "--out-dir", str(out), "--keypoints", "600", "--quiet",
             "--no-figures"])
  captured = capsys.readouterr()
  assert rc == 0, captured.err
  assert captured.out.startswith("source\ttarget\tverdict")
  for k in range(3):
    est = np.loadtxt(out / f"view{k}.txt")
    gt = np.linalg.inv(poses[0]) @ poses[k]
    err_r = np.degrees(Rotation.from_matrix(est[:3, :3] @ gt[:3, :3].T).magnitude())
    assert err_r < 2.0 and np.linalg.norm(est[:3, 3] - gt[:3, 3]) < 5 * mr, (k, est, gt)
  assert (out / "merged.ply").is_file() and (out / "edges.tsv").read_text().count("\n") == 4
  assert io.read_cloud(out / "merged.ply").points.shape[1] == 3
  # An input inside the output folder, named as an output: refused before any work.
  clash = out / "view0.txt"
  np.savetxt(clash, clouds[0][:100])
  assert main([str(clash), *map(str, paths[1:]), "--out-dir", str(out)]) == 2
  assert "refusing to overwrite" in capsys.readouterr().err


def test_cli_hand_over_rule():
  from lrf_jax.cli.multiway import wanted
  from lrf_jax.cli.register import build_parser
  ap = build_parser()
  assert wanted(ap, ["a.ply", "b.ply", "c.ply"])
  assert wanted(ap, ["a.ply", "b.ply", "--out-dir", "D"])
  assert not wanted(ap, ["a.ply", "b.ply", "--mr", "0.5", "--out", "T.txt"])
  assert not wanted(ap, ["a.ply", "b.ply", "--init", "T.txt"])


def test_figures_are_written(tmp_path):
  clouds, poses, mr = _views(3)
  res = multiway.register_all(clouds, mr=mr, pairwise=_oracle(clouds, poses), refine=False)
  written = multiway_outputs.write_outputs(res, clouds, tmp_path / "d", voxel=3 * mr)
  names = {p.name for p in written}
  assert {"merged.png", "graph.png", "merged.ply", "edges.tsv", "scan0.txt"} <= names
  assert (tmp_path / "d" / "graph.png").stat().st_size > 10_000


@pytest.mark.data
def test_bunny_scans_within_a_degree_and_two_mm(data_root):
  """The 10 real bunny scans (all 45 pairs): every pose within 1 deg and 2 mm of bun.conf."""
  from lrf_jax.datasets.stanford import bunny_poses
  from lrf_jax.registration import pose_errors
  folder = data_root / "stanford_bunny_scans"
  names = ["bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "chin", "ear_back",
           "top2", "top3"]
  res = multiway.register_all([str(folder / f"{n}.ply") for n in names], refine=False)
  world = bunny_poses(data_root)
  assert res.in_model.all()
  for k, n in enumerate(names):
    err_r, err_t = pose_errors(res.poses[k], np.linalg.inv(world["bun000"]) @ world[n], 1e-3)
    assert err_r < 1.0 and err_t < 2.0, (n, err_r, err_t)
@pytest.mark.data
@pytest.mark.parametrize("seed", [0, 1])
def test_a_foreign_scan_among_real_bunny_scans_is_never_placed(data_root, seed):
  """Four real bunny scans and a UWA3M T-rex view (mm -> m): the T-rex view is left out with no
  pose, whatever its "not sure" edges say, and the bunny scans are all placed."""
  import gzip
  from lrf_jax import io
  folder = data_root / "stanford_bunny_scans"
  scans = [io.read_cloud(folder / f"{n}.ply").points
           for n in ("bun000", "bun045", "bun315", "chin")]
  with gzip.open(data_root / "uwa_3d_modeling_views" / "T-rex_view001.txt.gz") as f:
    trex = np.loadtxt(f) / 1000.0
  res = multiway.register_all([*scans, trex], names=["bun000", "bun045", "bun315", "chin",
                                                     "trex"], seed=seed, refine=False)
  assert res.left_out == ["trex"] and np.isnan(res.poses[4]).all()
  assert not any(e.accepted for e in res.edges if 4 in (e.i, e.j))


@pytest.mark.parametrize("all_pairs_max", [0, 1, 2])
def test_candidate_pairs_never_pair_a_scan_with_itself(all_pairs_max):
  """Fewer scans than loop candidates + 1 (3 scans, 3 candidates): every pair (i, j), i < j,
  once; a scan's own distance (inf) was taken as its third candidate, (0, 0) an edge that
  `register_all` refused after the pairwise work."""
  clouds = [np.random.default_rng(k).random((200, 3)) * (1 + k) for k in range(3)]
  pairs = multiway.candidate_pairs(clouds, all_pairs_max=all_pairs_max)
  assert pairs == [(0, 1), (0, 2), (1, 2)]


@pytest.mark.parametrize("flag", ["--merge-voxel-mr", "--voxel"])  # --voxel: before 0.9
def test_voxel_too_small_for_the_extent_is_refused(tmp_path, capsys, monkeypatch, flag):
  """`--voxel 1e-20`: the int64 voxel keys overflowed and merged.ply collapsed to a few points;
  now one error: line naming the flag as typed before any registration, nothing written."""
  from lrf_jax.cli.register import main
  clouds = [np.random.default_rng(k).normal(size=(30, 3)) for k in range(3)]
  res = _result(["a", "b", "c"], [True] * 3)
  with pytest.raises(ValueError, match="voxel: 1e-20 is too small for the merged cloud's extent"):
    multiway_outputs.merged_cloud(clouds, res, voxel=1e-20)
  down, _ = multiway_outputs.merged_cloud(clouds, res, voxel=1e-9)  # small, still exact: every point
  assert len(down) == 90
  with pytest.raises(ValueError, match="voxel: 1e-20 is too small for the scans' extent"):
    multiway_outputs.check_voxel(clouds, 1e-20)  # whatever the poses: before the work
  multiway_outputs.check_voxel(clouds, 1e-9)
  scans = _npy_scans(tmp_path / "in", "a.npy", "b.npy", "c.npy")
  monkeypatch.setattr(multiway_pipeline, "register_all", lambda *a, **k: pytest.fail("registered"))
  out = tmp_path / "model"
  assert main([*scans, "--out-dir", str(out), "--quiet", "--no-figures", flag, "1e-20"]) == 2
  err = capsys.readouterr().err
  errors = [line for line in err.splitlines() if line.startswith("error: ")]
  assert len(errors) == 1 and errors[0].startswith(f"error: {flag}: 1e-20 mr = "), err
  assert "too small" in err and "Traceback" not in err and not out.exists()


@pytest.mark.parametrize("n", [1, 3, 10, 11, 25])
def test_scan_colours_are_matplotlibs_without_importing_it(n):
  """merged.ply's colours: matplotlib's tab10 / tab20 as tables (a base install writes it)."""
  from matplotlib import colormaps

  from lrf_jax.multiway.figures import scan_colours
  cmap = colormaps["tab10" if n <= 10 else "tab20"]
  expected = (np.array([cmap(k % cmap.N)[:3] for k in range(n)]) * 255).round().astype(np.uint8)
  np.testing.assert_array_equal(scan_colours(n), expected)


def test_cli_out_dir_in_use_by_another_job_is_refused(tmp_path, monkeypatch, capsys):
  """A second `lrf-register SCANS --out-dir D` while a live job holds D: exit 2 before any
  work, naming the holder; the holder's lock is untouched."""
  import socket
  import subprocess
  import sys
  from lrf_jax.cli.register import main
  from lrf_jax.multiway.outputs import STATE
  scans = _npy_scans(tmp_path / "in", "a.npy", "b.npy")
  out = tmp_path / "model"
  (out / STATE).mkdir(parents=True)
  holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
  try:
    lock = out / STATE / "lock"
    lock.write_text(json.dumps({"host": socket.gethostname(), "pid": holder.pid, "start": None,
                                "command": "lrf-register x y z --out-dir model"}))
    monkeypatch.setattr(multiway_pipeline, "register_all",
                        lambda *a, **k: pytest.fail("registered"))
    assert main([*scans, "--out-dir", str(out), "--quiet", "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --out-dir") and f"pid {holder.pid}" in err
    assert lock.exists()
  finally:
    holder.kill()
    holder.wait()


def test_a_hidden_files_scan_name_has_no_leading_dot():
  """Before: `.hidden.npy` was named `.hidden`: lrf-batch refused the whole job (a name may not
  start with a dot) and lrf-register --out-dir wrote a hidden `.hidden.txt`."""
  from lrf_jax.multiway.outputs import scan_names
  assert scan_names(["/d/.hidden.npy", "/d/a.npy", "/d/...npy"]) == ["hidden", "a", "scan2"]

