"""The viewer's data and server (`lrf_jax.viz`, `lrf_jax.view`): the output folders read back as
written (a multiway model by `write_outputs` itself, a batch folder as `lrf-batch register`
lays it out), clouds thinned for display with one line saying so, and a server that serves the
page on 127.0.0.1 and stops. The page in a real browser: tests/test_viz_browser.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
import urllib.request
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
NAMES = ("alpha", "beta", "gamma")


def blob(centre, n: int = 3000, seed: int = 0) -> np.ndarray:
  """n points on a sphere of radius 0.8 around `centre`."""
  p = np.random.default_rng(seed).normal(size=(n, 3))
  return 0.8 * p / np.linalg.norm(p, axis=1, keepdims=True) + np.asarray(centre, float)


def shift(t) -> np.ndarray:
  out = np.eye(4)
  out[:3, 3] = t
  return out


def make_model(n: int = 3000, left_out: bool = False):
  """A MultiwayResult of three scans (the third left out with `left_out`) and their clouds,
  each in its own frame: scan k's pose moves it to its place."""
  from lrf_jax.multiway.result import MultiwayEdge, MultiwayResult
  places = [(0, 0, 0), (3, 0, 0), (0, 3, 0)]
  clouds = [blob((0, 0, 0), n, seed=k) for k in range(3)]
  poses = np.stack([shift(p) for p in places])
  in_model = np.array([True, True, not left_out])
  if left_out:
    poses[2] = np.nan
  edges = (MultiwayEdge(1, 0, np.eye(4), "success", "ok", 50, 0.5, 0.1, 0.2, True, "claimed"),
           MultiwayEdge(2, 0, np.eye(4), "not sure", "r", 20, 0.3, 0.1, 0.5, not left_out),
           MultiwayEdge(2, 1, np.eye(4), "not sure", "r", 10, 0.1, 0.1, 9.0, False))
  return MultiwayResult(NAMES, poses, in_model, 0, edges, 0.01, 1.0), clouds


def make_model_folder(d: Path, n: int = 3000, left_out: bool = False) -> Path:
  """A multiway output folder, written by `write_outputs` as `lrf-register --out-dir` does."""
  from lrf_jax.multiway.outputs import write_outputs
  result, clouds = make_model(n, left_out)
  write_outputs(result, clouds, d, figures=False)
  return d


def make_batch_folder(d: Path) -> Path:
  """An lrf-batch register folder: results.tsv (the job's columns) with a done pair, its
  transform, and a pair that failed; the scans as .npy beside it."""
  from lrf_jax.batch.jobs import REGISTER_COLUMNS
  from lrf_jax.batch.tables import tsv
  from lrf_jax.io.poses import format_matrix
  d.mkdir(parents=True)
  src, tgt = d / "src.npy", d / "tgt.npy"
  np.save(src, blob((0, 0, 0), 500))
  np.save(tgt, blob((1, 0, 0), 500, seed=1))
  (d / "0001.txt").write_text(format_matrix(shift((1, 0, 0))) + "\n")
  rows = [dict(name="0001", source=str(src), target=str(tgt), status="done", success="True",
               reason="claimed: 40 inliers"),
          dict(name="0002", source=str(src), target=str(d / "gone.npy"), status="error",
               error="gone.npy: no such file")]
  (d / "results.tsv").write_text(tsv(REGISTER_COLUMNS, rows))
  (d / ".lrf-batch").mkdir()
  return d


def test_a_model_folder_reads_back_every_scan_at_its_pose(tmp_path):
  from lrf_jax.multiway.figures import scan_colours
  from lrf_jax.viz.folders import folder_kind, read_model_folder
  d = make_model_folder(tmp_path / "m")
  assert folder_kind(d) == "model"
  scene = read_model_folder(d)
  assert scene.names == NAMES and scene.left_out == [] and scene.thinned == ()
  assert np.allclose(scene.centroids(), [(0, 0, 0), (3, 0, 0), (0, 3, 0)], atol=0.05)
  assert np.array_equal(scene.colours, scan_colours(3))
  assert sorted(scene.edges) == [(1, 0, "accepted"), (2, 0, "accepted, not sure"),
                                 (2, 1, "rejected")]
  assert scene.edge_counts == {"accepted": 1, "accepted, not sure": 1, "rejected": 1}


def test_a_scan_left_out_is_named_and_not_drawn(tmp_path):
  from lrf_jax.viz.folders import read_model_folder
  scene = read_model_folder(make_model_folder(tmp_path / "m", left_out=True))
  assert scene.left_out == ["gamma"] and scene.points[2] is None
  assert scene.edges == ((1, 0, "accepted"),)  # the two edges with gamma are not drawn
  assert scene.edge_counts == {"accepted": 1, "accepted, not sure": 0, "rejected": 2}


def test_a_large_scan_is_thinned_seeded_with_one_line(tmp_path):
  from lrf_jax.viz.folders import read_model_folder
  from lrf_jax.viz.scenes import thinning_note
  d = make_model_folder(tmp_path / "m")
  a = read_model_folder(d, max_points=1000, seed=3)
  b = read_model_folder(d, max_points=1000, seed=3)
  assert all(len(p) == 1000 for p in a.points)
  assert all(np.array_equal(p, q) for p, q in zip(a.points, b.points))
  note = thinning_note(a.thinned, 1000)
  assert note.count("\n") == 0 and "at most 1,000 points" in note and "alpha 3,000 -> 1,000" in note


def test_model_scene_of_a_result_and_its_scans_matches_the_folder(tmp_path):
  from lrf_jax.viz.folders import read_model_folder
  from lrf_jax.viz.scenes import model_scene
  result, clouds = make_model()
  scene = model_scene(result, clouds)
  folder = read_model_folder(make_model_folder(tmp_path / "m"))
  assert scene.names == folder.names and sorted(scene.edges) == sorted(folder.edges)
  for p, q in zip(scene.points, folder.points):
    assert np.allclose(p, q, atol=1e-5)  # merged.ply holds float32
  with pytest.raises(ValueError, match="the 3 scans given to register_all"):
    model_scene(result, clouds[:2])


def test_a_batch_folder_lists_its_pairs_and_reads_one_when_picked(tmp_path):
  from lrf_jax.viz.folders import folder_kind, read_batch_folder
  d = make_batch_folder(tmp_path / "b")
  assert folder_kind(d) == "batch"
  pairs = read_batch_folder(d)
  assert [p.label() for p in pairs] == ["0001 (success)", "0002 (error)"]
  scene = pairs[0].scene()
  assert np.allclose(scene.registered().mean(axis=0), scene.target.mean(axis=0), atol=0.1)
  assert pairs[1].transform is None
  with pytest.raises(FileNotFoundError, match="gone.npy"):
    pairs[1].scene()


def test_folders_of_neither_kind_are_refused_naming_both(tmp_path):
  from lrf_jax.viz.folders import folder_kind
  (tmp_path / "x.txt").write_text("hello")
  with pytest.raises(ValueError, match="neither a multiway output folder .* nor an lrf-batch"):
    folder_kind(tmp_path)
  with pytest.raises(ValueError, match="not a folder"):
    folder_kind(tmp_path / "x.txt")
  frames = tmp_path / "f"
  frames.mkdir()
  (frames / "results.tsv").write_text("name\tscan\tstatus\n")
  with pytest.raises(ValueError, match="frames folder"):
    folder_kind(frames)


def test_view_takes_each_of_its_forms_and_refuses_others(tmp_path):
  from lrf_jax.viz.api import content_of
  result, clouds = make_model()
  assert content_of(result, (clouds,)).model.names == NAMES
  reg = types.SimpleNamespace(transform=shift((1, 0, 0)), success=False, reason="few inliers",
                              estimated=True)
  pair = content_of(reg, (clouds[0], clouds[1])).pair
  assert pair.verdict == "not sure: few inliers" and np.allclose(pair.transform, shift((1, 0, 0)))
  t = tmp_path / "T.txt"
  t.write_text("1 0 0 2\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
  assert content_of(clouds[0], (clouds[1],), str(t)).pair.transform[0, 3] == 2
  assert content_of(clouds[0], (clouds[1],)).pair.registered() is None
  with pytest.raises(ValueError, match="holds poses, not points"):
    content_of(result)
  with pytest.raises(ValueError, match="pass the source and the target"):
    content_of(reg, (clouds[0],))
  with pytest.raises(ValueError, match="max_points"):
    content_of(result, (clouds,), max_points=0)


def test_view_serves_the_page_on_127_0_0_1_and_stops(tmp_path):
  """The Python API as a notebook uses it: it returns at once with a running viewer whose page
  answers, bound to 127.0.0.1 only; stop() ends it."""
  pytest.importorskip("viser", reason="viser is not installed (the viz extra)")
  import psutil

  import lrf_jax
  viewer = lrf_jax.view(make_model_folder(tmp_path / "m"))
  try:
    assert viewer.url.startswith("http://127.0.0.1:")
    with urllib.request.urlopen(viewer.url, timeout=10) as r:
      assert r.status == 200 and b"<html" in r.read().lower()
    port = viewer.server.get_port()
    proc = psutil.Process()
    listing = getattr(proc, "net_connections", None) or proc.connections  # psutil < 6
    mine = [c for c in listing("inet")
            if c.status == psutil.CONN_LISTEN and c.laddr.port == port]
    assert mine and {c.laddr.ip for c in mine} == {"127.0.0.1"}
    assert "<iframe" in viewer._repr_html_()
    assert viewer.server.scene is not None and viewer.server.gui is not None
  finally:
    viewer.stop()
  viewer.stop()  # idempotent
  with pytest.raises(OSError):
    urllib.request.urlopen(viewer.url, timeout=2)


def test_view_of_a_batch_folder_shows_the_first_pair(tmp_path, capsys):
  pytest.importorskip("viser", reason="viser is not installed (the viz extra)")
  from lrf_jax.viz.api import folder_content, serve
  viewer = serve(folder_content(make_batch_folder(tmp_path / "b")), max_points=100)
  try:
    assert "thinned for display" in capsys.readouterr().err  # 500 points shown as 100
  finally:
    viewer.stop()


def test_the_pair_picker_loads_each_pair_and_says_why_one_cannot_be_shown(tmp_path):
  pytest.importorskip("viser", reason="viser is not installed (the viz extra)")
  from lrf_jax.viz.draw import show_batch
  from lrf_jax.viz.folders import read_batch_folder
  from lrf_jax.viz.server import Viewer, start_server
  viewer = Viewer(start_server(), "127.0.0.1")
  notes: list[str] = []
  try:
    picker = show_batch(viewer.server, read_batch_folder(make_batch_folder(tmp_path / "b")),
                        max_points=100, notify=notes.append)
    assert picker.value == "0001 (success)" and len(notes) == 1
    picker.value = "0002 (error)"  # runs the picker's callback, as a click in the page does
    picker.value = "0001 (success)"
    assert len(notes) == 2 and "0001: source 500 -> 100" in notes[-1]
  finally:
    viewer.stop()


def test_a_missing_viser_names_the_extra(tmp_path):
  d = make_model_folder(tmp_path / "m")
  code = ("import sys\nsys.modules['viser'] = None\nimport lrf_jax\n"
          f"lrf_jax.view({str(d)!r})\n")
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=120)
  last = out.stderr.strip().splitlines()[-1]
  assert "MissingExtraError" in last and "pip install 'lrf_jax[viz]'" in last, out.stderr


def test_the_manifest_of_a_model_folder_is_what_write_outputs_writes(tmp_path):
  """The viewer reads the folder by its manifest's kind: the writer's constant."""
  from lrf_jax.multiway.outputs import MANIFEST_KIND
  d = make_model_folder(tmp_path / "m")
  assert json.loads((d / "manifest.json").read_text())["kind"] == MANIFEST_KIND
