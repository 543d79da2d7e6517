"""Figures of a multiway registration: the merged cloud coloured by scan, and the pose graph
with its accepted and rejected edges (PNG, matplotlib, written atomically)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING
from collections.abc import Sequence

import numpy as np

from lrf_jax.extras import pyplot
from lrf_jax.io.atomic import save_figure

if TYPE_CHECKING:
  from lrf_jax.multiway.result import MultiwayResult

# Points drawn in the merged cloud's figure at most (a seeded sample).
FIGURE_POINTS = 40000


# matplotlib's qualitative colormaps tab10 and tab20 as uint8 RGB (their values, rounded): the
# colours of merged.ply need no matplotlib (a base install writes it).
TAB10 = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
         (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207))
TAB20 = ((31, 119, 180), (174, 199, 232), (255, 127, 14), (255, 187, 120), (44, 160, 44),
         (152, 223, 138), (214, 39, 40), (255, 152, 150), (148, 103, 189), (197, 176, 213),
         (140, 86, 75), (196, 156, 148), (227, 119, 194), (247, 182, 210), (127, 127, 127),
         (199, 199, 199), (188, 189, 34), (219, 219, 141), (23, 190, 207), (158, 218, 229))


def scan_colours(n: int) -> np.ndarray:
  """(n, 3) uint8 distinct colours, one per scan (matplotlib's tab10, then tab20; no
  matplotlib import)."""
  table = np.array(TAB10 if n <= 10 else TAB20, np.uint8)
  return table[np.arange(n) % len(table)]


def _pyplot():
  plt = pyplot("plot", "register_all's figures")
  return plt


def merged_figure(points: np.ndarray, scan: np.ndarray, result: MultiwayResult,
                  path: str | os.PathLike, *, seed: int = 0) -> Path:
  """The merged cloud, each scan in its colour, from three sides (along the model's principal
  axes, largest spread in the picture plane), with the scans left out named in the title.

  Args:
    points: (m, 3) merged points (reference frame; `merged_cloud`).
    scan: (m,) the scan of each point.
    result: the registration (names, which scans are in).
    path: the PNG to write.
    seed: seed of the drawn sample.

  Returns:
    The path written.
  """
  plt = _pyplot()
  rng = np.random.default_rng(seed)
  if len(points) > FIGURE_POINTS:
    keep = np.sort(rng.choice(len(points), FIGURE_POINTS, replace=False))
    points, scan = points[keep], scan[keep]
  centred = points - points.mean(axis=0)
  _, _, axes = np.linalg.svd(centred[:: max(len(centred) // 5000, 1)], full_matrices=False)
  uvw = centred @ axes.T  # principal coordinates
  colours = scan_colours(len(result.names)) / 255.0
  views = (((0, 1), "front (axes 1-2)"), ((0, 2), "top (axes 1-3)"), ((2, 1), "side (axes 3-2)"))
  fig, ax = plt.subplots(1, 3, figsize=(15, 5.6), constrained_layout=True)
  order = rng.permutation(len(uvw))  # no scan systematically drawn over the others
  for a, ((u, v), title) in zip(ax, views):
    a.scatter(uvw[order, u], uvw[order, v], s=0.4, c=colours[scan[order]], linewidths=0,
              rasterized=True)
    a.set_aspect("equal")
    a.set_title(title)
    a.set_xticks([])
    a.set_yticks([])
  handles = [plt.Line2D([], [], ls="", marker="o", color=colours[k], label=name)
             for k, name in enumerate(result.names) if result.in_model[k]]
  fig.legend(handles=handles, loc="outside right center", title="scan", markerscale=1.5)
  left = result.left_out
  fig.suptitle(f"merged model: {int(result.in_model.sum())} scans in the frame of "
               f"{result.names[result.reference]}"
               + (f"; left out: {', '.join(left)}" if left else ""), fontsize=13)
  save_figure(fig, path, dpi=110)
  plt.close(fig)
  return Path(path)


def graph_figure(result: MultiwayResult, clouds: Sequence[np.ndarray] | None,
                 path: str | os.PathLike) -> Path:
  """The candidate graph: scans on a circle in the given order, accepted edges green (width
  by inliers, labelled a third of the way from the earlier scan with the residual in mr), trusted edges the graph rejected red,
  "not sure" edges it did not use as grey dots, pairs that could not be registered not drawn;
  scans left out grey.

  Args:
    result: the registration.
    clouds: unused (kept for a layout by scan position later); may be None.
    path: the PNG to write.

  Returns:
    The path written.
  """
  del clouds
  plt = _pyplot()
  n = len(result.names)
  angle = np.pi / 2 - 2 * np.pi * np.arange(n) / n
  xy = np.stack([np.cos(angle), np.sin(angle)], axis=1)
  fig, ax = plt.subplots(figsize=(8.5, 8.5), constrained_layout=True)
  counts = {"accepted": 0, "rejected (verdict success)": 0, "rejected (not sure)": 0}
  for e in sorted(result.edges, key=lambda e: (e.accepted, e.verdict == "success")):
    if e.verdict == "error":
      continue
    (x0, y0), (x1, y1) = xy[e.i], xy[e.j]
    if e.accepted:
      width = 1.0 + 1.5 * np.log10(max(e.n_inliers, 1))
      ax.plot([x0, x1], [y0, y1], color="tab:green", lw=width, zorder=3, solid_capstyle="round")
      if np.isfinite(e.residual_mr):
        # A third of the way from the earlier scan: diameters of the circle do not share it.
        ax.text(x0 + (x1 - x0) / 3, y0 + (y1 - y0) / 3, f"{e.residual_mr:.2f}", fontsize=7,
                zorder=5,
                ha="center", va="center", color="darkgreen",
                bbox={"fc": "white", "ec": "none", "alpha": 0.7, "pad": 0.5})
      counts["accepted"] += 1
    elif e.verdict == "success":
      ax.plot([x0, x1], [y0, y1], color="tab:red", lw=2.0, ls="--", zorder=4)
      counts["rejected (verdict success)"] += 1
    else:
      ax.plot([x0, x1], [y0, y1], color="0.75", lw=0.8, ls=":", zorder=1)
      counts["rejected (not sure)"] += 1
  colours = scan_colours(n) / 255.0
  for k, name in enumerate(result.names):
    inside = bool(result.in_model[k])
    ax.scatter(*xy[k], s=420, color=colours[k] if inside else "0.8", edgecolors="black",
               linewidths=2.5 if k == result.reference else 1.0, zorder=6)
    label = name + ("" if inside else "\n(left out)") + (" (ref.)" if k == result.reference
                                                         else "")
    ax.text(*(xy[k] * 1.17), label, ha="center", va="center", fontsize=10, zorder=7,
            color="black" if inside else "0.4")
  handles = [plt.Line2D([], [], color="tab:green", lw=3,
                        label=f"accepted ({counts['accepted']}; label: residual in mr)"),
             plt.Line2D([], [], color="tab:red", lw=2, ls="--",
                        label=f"rejected, verdict success ({counts['rejected (verdict success)']})"),
             plt.Line2D([], [], color="0.6", lw=1, ls=":",
                        label=f"rejected / unused, verdict not sure "
                              f"({counts['rejected (not sure)']})")]
  ax.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, -0.1), fontsize=9,
            frameon=False)
  ax.set_xlim(-1.45, 1.45)
  ax.set_ylim(-1.35, 1.35)
  ax.set_aspect("equal")
  ax.axis("off")
  fig.suptitle(f"pose graph: {n} scans, {len(result.edges)} candidate pairs"
               + (f", left out: {', '.join(result.left_out)}" if result.left_out else ""))
  save_figure(fig, path, dpi=110)
  plt.close(fig)
  return Path(path)
