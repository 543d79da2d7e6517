"""What the viewer puts on its page (viser's scene and GUI panel): a multiway model
(`show_model`: every scan in its colour with a legend and a toggle each, the graph's edges as
lines between the scans' centroids, coloured by accepted / "not sure" / rejected), a pair
(`show_pair`: the target, the source before and after the transform, each toggled) or the pairs
of a batch folder (`show_batch`: a picker that loads the pair chosen).

Every cloud is shown centred (the model's or the target's bounding-box centre moved to the
origin) in float32, with flat colours (the legend's exactly).
"""

from __future__ import annotations

import html
import threading
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

import numpy as np

from lrf_jax.viz.scenes import (EDGE_COLOURS, EDGE_KINDS, MAX_POINTS, PAIR_COLOURS, ModelScene,
                                PairScene, thinning_note)

if TYPE_CHECKING:
  import viser

  from lrf_jax.viz.folders import BatchPair

__all__ = ["show_batch", "show_model", "show_pair"]

# A point's size on the page: the shown clouds' bounding-box diagonal over this (a slider
# scales it).
POINTS_PER_DIAGONAL = 400.0
# Edge lines, in pixels.
EDGE_PIXELS = 3.0
# The scene's up direction, picked in "View" (+z: viser's default, LiDAR's; +y: most meshes').
UP_AXES = {"+z": (0.0, 0.0, 1.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
           "+x": (1.0, 0.0, 0.0)}


def _extent(clouds: Sequence[np.ndarray]) -> tuple[np.ndarray, float]:
  """The clouds' bounding-box centre and diagonal (at least a tiny positive length)."""
  lo = np.min([c.min(axis=0) for c in clouds], axis=0)
  hi = np.max([c.max(axis=0) for c in clouds], axis=0)
  return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)), 1e-9)


def _hex(rgb: Sequence[int]) -> str:
  return "#" + "".join(f"{int(v):02x}" for v in rgb)


def _swatch(rgb: Sequence[int], text: str) -> str:
  """One legend line: a square of colour `rgb`, then `text` (escaped)."""
  return (f'<div style="display:flex;align-items:center;gap:0.5em;margin:0.1em 0">'
          f'<span style="display:inline-block;width:0.9em;height:0.9em;flex:none;'
          f'background:{_hex(rgb)};border-radius:2px"></span>'
          f'<span>{html.escape(text)}</span></div>')


def _legend(lines: Sequence[tuple[Sequence[int], str]]) -> str:
  return ('<div style="font-size:0.85em;padding:0 0.75em">'
          + "".join(_swatch(rgb, text) for rgb, text in lines) + "</div>")


def _toggle(server: viser.ViserServer, label: str, handles: Sequence[Any],
            initial: bool = True) -> Any:
  """A checkbox that shows or hides `handles`."""
  box = server.gui.add_checkbox(label, initial)

  def update(_: Any) -> None:
    for h in handles:
      h.visible = box.value

  box.on_update(update)
  return box


def _camera(target: Any, diagonal: float) -> None:
  """Point `target` (the server's initial camera, or a client's camera) at the origin from a
  distance that shows a scene of this diagonal."""
  target.look_at = (0.0, 0.0, 0.0)
  target.position = tuple(float(v) for v in diagonal * np.array([0.75, -0.75, 0.55]))


def _view_controls(server: viser.ViserServer, clouds: list[Any], size: float) -> None:
  """The "View" folder: the points' size (a factor of the default) and the up axis."""
  with server.gui.add_folder("View", expand_by_default=False):
    slider = server.gui.add_slider("point size", 0.1, 5.0, 0.1, 1.0)

    def resize(_: Any) -> None:
      for h in clouds:
        h.point_size = size * float(slider.value)

    slider.on_update(resize)
    up = server.gui.add_dropdown("up axis", tuple(UP_AXES), initial_value="+z")
    up.on_update(lambda _: server.scene.set_up_direction(UP_AXES[up.value]))


def _cloud(server: viser.ViserServer, name: str, points: np.ndarray, rgb: Sequence[int],
           size: float, visible: bool = True) -> Any:
  return server.scene.add_point_cloud(name, np.asarray(points, np.float32),
                                      np.asarray(rgb, np.uint8), point_size=size,
                                      point_shading="flat", precision="float32",
                                      visible=visible)


def _model_info(scene: ModelScene, max_points: int) -> str:
  n_in = sum(p is not None for p in scene.points)
  text = f"**{html.escape(scene.title)}**: {n_in}/{len(scene.names)} scans in the model"
  if scene.left_out:
    text += f"; left out: {html.escape(', '.join(scene.left_out))}"
  note = thinning_note(scene.thinned, max_points)
  return text + (f"\n\n{html.escape(note[len('note: '):])}" if note else "")


def show_model(server: viser.ViserServer, scene: ModelScene, *,
               max_points: int = MAX_POINTS) -> dict[str, Any]:
  """Put a multiway model on the page: the scans (folder "Scans": the legend, a toggle per
  scan, all / none), the edges (folder "Edges": a toggle per kind) and "View".

  Returns:
    The scene handles: {"scans": [per scan, None when left out], "edges": {kind: handle}}.
  """
  shown = [p for p in scene.points if p is not None]
  centre, diagonal = _extent(shown)
  size = diagonal / POINTS_PER_DIAGONAL
  server.gui.add_markdown(_model_info(scene, max_points))
  clouds: list[Any] = [None if p is None else
                       _cloud(server, f"/scans/{k}", p - centre, scene.colours[k], size)
                       for k, p in enumerate(scene.points)]
  with server.gui.add_folder("Scans"):
    server.gui.add_html(_legend([(scene.colours[k], f"{n} ({len(p):,} points)")
                                 for k, (n, p) in enumerate(zip(scene.names, scene.points))
                                 if p is not None]))
    boxes = [_toggle(server, name, [h]) for name, h in zip(scene.names, clouds)
             if h is not None]
    both = server.gui.add_button_group("show", ("all", "none"))

    def show_all(event: Any) -> None:
      for box in boxes:  # its callback shows or hides its scan
        box.value = event.target.value == "all"

    both.on_click(show_all)
  edges = _show_edges(server, scene, centre)
  _view_controls(server, [h for h in clouds if h is not None], size)
  _camera(server.initial_camera, diagonal)
  return {"scans": clouds, "edges": edges}


def _show_edges(server: viser.ViserServer, scene: ModelScene, centre: np.ndarray
                ) -> dict[str, Any]:
  """The edges between the scans' centroids, one line set per kind, and their folder."""
  centroids = scene.centroids() - centre
  handles = {}
  for kind in EDGE_KINDS:
    ends = [(i, j) for i, j, k in scene.edges if k == kind]
    if ends:
      segments = np.array([[centroids[i], centroids[j]] for i, j in ends], np.float32)
      handles[kind] = server.scene.add_line_segments(
          f"/edges/{EDGE_KINDS.index(kind)}", segments, np.asarray(EDGE_COLOURS[kind], np.uint8),
          thickness=EDGE_PIXELS, thickness_units="screen")
  total = sum(scene.edge_counts.values())
  with server.gui.add_folder("Edges"):
    lines = [(EDGE_COLOURS[k], f"{k}: {scene.edge_counts[k]}") for k in EDGE_KINDS]
    server.gui.add_html(_legend(lines))
    hidden = total - len(scene.edges)
    if hidden:
      server.gui.add_markdown(f"{hidden} of {total} edges not drawn (a scan left out)")
    for kind, h in handles.items():
      _toggle(server, f"{kind} edges", [h])
  return handles


def show_pair(server: viser.ViserServer, scene: PairScene, *, root: str = "/pair",
              max_points: int = MAX_POINTS, camera: bool = True) -> list[Any]:
  """Put a pair on the page: the target, the source moved by the transform ("registered",
  shown) and where it was ("before", shown only when there is no transform), each toggled, and
  the verdict.

  Returns:
    The clouds' scene handles (target, registered source if any, source before).
  """
  centre, diagonal = _extent([scene.target])
  size = diagonal / POINTS_PER_DIAGONAL
  moved = scene.registered()
  text = f"**{html.escape(scene.name)}**"
  text += f": {html.escape(scene.verdict)}" if scene.verdict else ""
  if moved is None:
    text += "\n\nno transform: the source is shown where it is"
  note = thinning_note(scene.thinned, max_points)
  text += f"\n\n{html.escape(note[len('note: '):])}" if note else ""
  server.gui.add_markdown(text)
  clouds = [("target", scene.target, True)]
  if moved is not None:
    clouds.append(("source (registered)", moved, True))
  clouds.append(("source (before)", scene.source, moved is None))
  server.gui.add_html(_legend([(PAIR_COLOURS[n], n) for n, _, _ in clouds]))
  handles = []
  for k, (label, points, visible) in enumerate(clouds):
    h = _cloud(server, f"{root}/{k}", points - centre, PAIR_COLOURS[label], size, visible)
    handles.append(h)
    _toggle(server, label, [h], visible)
  if camera:
    _camera(server.initial_camera, diagonal)
    for client in server.get_clients().values():
      _camera(client.camera, diagonal)
  return handles


def show_batch(server: viser.ViserServer, pairs: Sequence[BatchPair], *,
               max_points: int = MAX_POINTS, seed: int = 0, title: str = "",
               notify: Callable[[str], None] | None = None) -> Any:
  """Put the pairs of a batch folder on the page: a picker ("pair": each name and verdict)
  and the pair picked (`show_pair`), read from its files when picked; a pair that cannot be
  read says why instead. `notify` is called with the line of a pair thinned for display.

  Returns:
    The picker (its `.value` is the label of the pair shown).
  """
  labels = [p.label() for p in pairs]
  by_label = dict(zip(labels, pairs))
  server.gui.add_markdown(f"**{html.escape(title)}**: {len(pairs)} pairs (lrf-batch register)")
  picker = server.gui.add_dropdown("pair", labels, initial_value=labels[0])
  lock = threading.Lock()
  shown: list[Any] = []

  def load(_: Any = None) -> None:
    with lock:
      for h in shown:  # the folder (and the GUI in it) and the clouds
        h.remove()
      shown.clear()
      pair = by_label[picker.value]
      with server.gui.add_folder("Pair") as folder:
        shown.append(folder)
        try:
          scene = pair.scene(max_points=max_points, seed=seed)
        except (ValueError, OSError) as e:
          server.gui.add_markdown(f"**{html.escape(pair.name)}** cannot be shown: "
                                  f"{html.escape(str(e))}")
          return
        shown.extend(show_pair(server, scene, max_points=max_points))
      note = thinning_note(scene.thinned, max_points)
      if note and notify is not None:
        notify(note)

  picker.on_update(load)
  load()
  return picker
