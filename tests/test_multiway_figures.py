"""merged.png and graph.png (`lrf_jax.multiway.figures`): each scan its own colour and marker,
a section and a distance panel that show a misplaced scan, and a graph whose labels do not
overlap at 50 scans."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lrf_jax.multiway import figures
from lrf_jax.multiway.result import MultiwayEdge, MultiwayResult

pytest.importorskip("matplotlib")


def _edge(i, j, verdict, accepted, residual=0.2, inliers=100):
  return MultiwayEdge(i=i, j=j, transform=np.eye(4), verdict=verdict, reason="", n_inliers=inliers,
                      overlap=0.5, rmse=0.1, residual_mr=residual, accepted=accepted)


def _result(n, edges, left=(), names=None, mr=1.0, confident=None) -> MultiwayResult:
  in_model = np.array([k not in left for k in range(n)])
  poses = np.where(in_model[:, None, None], np.tile(np.eye(4), (n, 1, 1)), np.nan)
  return MultiwayResult(names=tuple(names or [f"scan_{k:04d}" for k in range(n)]), poses=poses,
                        in_model=in_model, reference=0, edges=tuple(edges), mr=mr, seconds=1.0,
                        confident=confident)


def _chain_with_loops(n, left=()):
  """Neighbours in order plus a few loop closures, of every outcome."""
  edges = []
  for i in range(n - 1):
    ok = i not in left and i + 1 not in left
    edges.append(_edge(i, i + 1, "success" if ok else "not sure", ok))
  for i in range(0, n - 7, 3):
    edges.append(_edge(i, i + 7, ("success", "not sure", "error")[i % 3], i % 3 == 0))
  edges.append(_edge(1, n // 2, "success", False, residual=40.0))  # rejected
  edges.append(_edge(2, n // 2 + 1, "not sure", True))  # accepted on the graph's backing
  return edges


def _capture(monkeypatch):
  """Keep the figures `save_figure` is given (and write them as it would)."""
  kept = []
  save = figures.save_figure

  def keep(fig, path, **kw):
    fig.canvas.draw()
    kept.append(fig)
    return save(fig, path, **kw)
  monkeypatch.setattr(figures, "save_figure", keep)
  monkeypatch.setattr(figures._pyplot(), "close", lambda fig: None)
  return kept


def _overlaps(boxes):
  return [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2) if ba.overlaps(bb)]


def test_scan_styles_cycle_colours_and_change_markers_beyond_twenty():
  colours, markers = figures.scan_styles(45)
  np.testing.assert_array_equal(colours, figures.scan_colours(45) / 255.0)  # merged.ply's
  assert markers[:20] == ["o"] * 20 and markers[20:40] == ["s"] * 20 and markers[40] == "D"
  pairs = {(tuple(c), m) for c, m in zip(colours, markers)}
  assert len(pairs) == 45  # colour and marker together tell every scan apart
  assert figures.scan_styles(10)[1] == ["o"] * 10


@pytest.mark.parametrize("n", [6, 12, 50])
def test_graph_labels_do_not_overlap(tmp_path, monkeypatch, n):
  """The node labels (names beside the nodes up to NAMED_NODES_MAX scans, numbers inside them
  beyond) overlap neither each other nor, beyond, the list of names, which holds every name."""
  kept = _capture(monkeypatch)
  res = _result(n, _chain_with_loops(n, left=(n - 2,)), left=(n - 2,))
  path = figures.graph_figure(res, None, tmp_path / "graph.png")
  assert path.stat().st_size > 10_000
  fig = kept[0]
  ax = fig.axes[0]
  renderer = fig.canvas.get_renderer()
  nodes = [(t.get_text(), t.get_window_extent(renderer)) for t in ax.texts
           if t.get_zorder() == 9]  # the node labels (residual labels: 7)
  assert len(nodes) == n
  assert not _overlaps(nodes)
  legend = ax.get_legend().get_window_extent(renderer)
  assert not any(box.overlaps(legend) for _, box in nodes)
  listed = [t.get_text() for t in fig.texts]
  if n > figures.NAMED_NODES_MAX:
    assert all(any(name in line for line in listed) for name in res.names)
    numbers = {text for text, _ in nodes}
    assert numbers == {str(k) for k in range(n)}
    graph_box = ax.get_window_extent(renderer)
    assert all(not box.overlaps(graph_box) for box in (t.get_window_extent(renderer)
                                                      for t in fig.texts if "scan_" in t.get_text()))
  else:
    assert [text for text, _ in nodes] == list(res.names)
    grey = [t.get_text() for t in ax.texts if t.get_zorder() == 9 and t.get_color() != "black"]
    assert grey == res.left_out


def test_graph_numbers_the_nodes_of_long_names(tmp_path, monkeypatch):
  """Twelve long names would stand along the radius, far out: numbered nodes and a list
  instead, its names cut in the middle (they differ at the end)."""
  kept = _capture(monkeypatch)
  names = [f"a_long_scan_name_of_the_survey_{k:02d}" for k in range(12)]
  figures.graph_figure(_result(12, _chain_with_loops(12), names=names), None, tmp_path / "g.png")
  fig = kept[0]
  nodes = [t.get_text() for t in fig.axes[0].texts if t.get_zorder() == 9]
  assert nodes == [str(k) for k in range(12)]
  listed = " ".join(t.get_text() for t in fig.texts)
  assert all(f"{k:>3}  " in listed and f"survey_{k:02d}" in listed for k in range(12))


def test_graph_edges_by_outcome_with_counts_in_the_legend(tmp_path, monkeypatch):
  kept = _capture(monkeypatch)
  n = 20
  res = _result(n, _chain_with_loops(n))
  figures.graph_figure(res, None, tmp_path / "graph.png")
  ax = kept[0].axes[0]
  legend = [t.get_text() for t in ax.get_legend().get_texts()]
  outcomes = [e.outcome for e in res.edges]
  for kind, (text, colour, _) in figures.EDGE_STYLES.items():
    assert any(line.startswith(f"{text} ({outcomes.count(kind)})") for line in legend), (kind, legend)
    drawn = [line for line in ax.lines if line.get_color() == colour]
    assert len(drawn) == outcomes.count(kind), kind
  assert any(f"not drawn ({outcomes.count('error')})" in line for line in legend)
  assert sum(len(line.get_xdata()) == 2 for line in ax.lines) == len(outcomes) - outcomes.count(
      "error")


def _plane(rng, centre, size=20.0, n=4000):
  pts = np.column_stack([rng.uniform(-size / 2, size / 2, (n, 2)), np.zeros(n)])
  return pts + centre


def test_distance_to_other_scans_is_to_their_surface():
  """A scan 2 units above another is 2 off its surface; a scan beside another on the same plane
  (no overlap, within the limit) is near the point distance away but on the surface; a scan
  farther than the limit from every other has no distance."""
  rng = np.random.default_rng(0)
  a = _plane(rng, [0, 0, 0])
  above = _plane(rng, [0, 0, 2.0])
  beside = _plane(rng, [22.0, 0, 0])  # from 2 units past a's border
  far = _plane(rng, [0, 200.0, 0])
  points = np.concatenate([a, above, beside, far])
  scan = np.repeat(np.arange(4), 4000)
  query = np.concatenate([above[:200], beside[beside[:, 0] < 14.0][:50], far[:20]])
  qs = np.concatenate([np.full(200, 1), np.full(50, 2), np.full(20, 3)])
  point, surface = figures.distance_to_other_scans(points, scan, query, qs, limit=5.0)
  np.testing.assert_allclose(surface[:200], 2.0, atol=1e-6)  # above a: on neither plane
  assert np.all(point[:200] >= 2.0 - 1e-9)
  assert np.all(point[200:250] > 1.0) and np.all(surface[200:250] < 0.05)  # a's continuation
  assert np.all(np.isinf(point[250:])) and np.all(np.isinf(surface[250:]))


def test_principal_frame_is_right_handed_with_the_tail_up():
  rng = np.random.default_rng(1)
  ground = np.column_stack([rng.uniform(-50, 50, 20000), rng.uniform(-20, 20, 20000),
                            rng.normal(0, 0.05, 20000)])
  poles = np.column_stack([rng.uniform(-50, 50, 400), rng.uniform(-20, 20, 400),
                           rng.uniform(0, 6, 400)])
  rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
  rot *= np.linalg.det(rot)
  _, axes = figures.principal_frame(np.concatenate([ground, poles]) @ rot.T)
  np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-9)
  assert np.linalg.det(axes) > 0
  np.testing.assert_allclose(axes[2], rot[:, 2], atol=0.02)  # "up": the poles' side
  assert abs(axes[0] @ rot[:, 0]) > 0.99  # the longest spread first


def test_merged_figure_shows_a_misplaced_scan(tmp_path, monkeypatch):
  """Three views of one box, one of them moved 4 mr off: the legend names every scan (the scan
  left out greyed), the distance panel's summary reads the offset, the title names the scan
  left out."""
  kept = _capture(monkeypatch)
  rng = np.random.default_rng(2)
  box = rng.uniform(-1, 1, (30000, 3))
  box[np.arange(30000), rng.integers(0, 3, 30000)] = rng.choice([-1.0, 1.0], 30000)
  parts = [box[box[:, 0] < 0.3], box[box[:, 0] > -0.3], box[box[:, 1] > 0]]
  mr = 0.02
  parts[2] = parts[2] + [0, 0, 4 * mr]  # misplaced
  points = np.concatenate(parts)
  scan = np.concatenate([np.full(len(p), k) for k, p in enumerate(parts)])
  res = _result(4, [], left=(3,), names=["left", "right", "top", "foreign"], mr=mr)
  figures.merged_figure(points, scan, res, tmp_path / "merged.png")
  fig = kept[0]
  assert "left out: foreign" in fig._suptitle.get_text()
  legends = [a.get_legend() for a in fig.axes if a.get_legend() is not None]
  labels = [t.get_text() for t in legends[0].get_texts()]
  assert labels == ["left", "right", "top", "foreign (left out)"]
  stats = " ".join(t.get_text() for t in fig.axes[2].texts)
  assert "90% of points under" in stats
  ninety = float(stats.split("under ")[1].split(" mr")[0])
  assert 3.0 < ninety < 5.0, stats  # the top view's 4 mr, measured across its faces
  aligned = _result(3, [], names=["left", "right", "top"], mr=mr)
  parts[2] = parts[2] - [0, 0, 4 * mr]
  figures.merged_figure(np.concatenate(parts), scan, aligned, tmp_path / "aligned.png")
  stats = " ".join(t.get_text() for t in kept[1].axes[2].texts)
  assert float(stats.split("under ")[1].split(" mr")[0]) < 0.5, stats


def test_figures_of_tiny_and_degenerate_models(tmp_path):
  """Two scans of three points each, one of them a single repeated point: both figures are
  written."""
  res = _result(2, [_edge(0, 1, "success", True)], mr=1.0)
  points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [5, 5, 5], [5, 5, 5]], float)
  scan = np.array([0, 0, 0, 1, 1, 1])
  assert figures.merged_figure(points, scan, res, tmp_path / "m.png").stat().st_size > 1000
  assert figures.graph_figure(res, None, tmp_path / "g.png").stat().st_size > 1000
  one = _result(2, [], left=(1,))
  assert figures.merged_figure(points[:3], scan[:3], one, tmp_path / "m1.png").exists()
  assert figures.graph_figure(one, None, tmp_path / "g1.png").exists()
