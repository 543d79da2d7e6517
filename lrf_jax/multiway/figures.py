"""Figures of a multiway registration (PNG, matplotlib, written atomically).

`merged.png` (`merged_figure`) shows whether the scans line up: the model from above and a
section through its middle, each scan in its own colour (`scan_styles`), and the model from above
coloured by each point's distance to the other scans' surface (`distance_to_other_scans`), where
a misplaced scan stands out. `graph.png` (`graph_figure`) is the candidate graph: the scans on a circle (named, or
numbered with a list of names beside it when there are many), each pair's edge drawn by what
became of it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Sequence

import numpy as np

from lrf_jax.extras import pyplot
from lrf_jax.io.atomic import save_figure

if TYPE_CHECKING:
  from lrf_jax.multiway.result import MultiwayResult

# Points drawn per panel of the merged cloud's figure at most (seeded samples).
FIGURE_POINTS = 40000
# Resolution of both figures (dots per inch).
FIGURE_DPI = 100
# The section: a slab this many mr thick through the middle of the model.
SECTION_MR = 2.0
# The distance panel's colour scale ends here (mr); beyond NO_OVERLAP_MR a point has no other
# scan near it (a part only one scan saw), drawn grey rather than as an error.
DISTANCE_MAX_MR = 3.0
NO_OVERLAP_MR = 10.0
DISTANCE_CMAP = "RdYlBu_r"  # blue: on the other scans, red: off them
# The graph names its scans beside the nodes up to this many (beyond 8, names of at most
# NAMED_NODES_CHARS characters: they stand along the radius); else the nodes are numbered and the
# names listed beside the circle (in columns of NAMES_PER_COLUMN, at most MAX_NAME_COLUMNS).
NAMED_NODES_MAX = 16
NAMED_NODES_CHARS = 16
NAMES_PER_COLUMN = 30
MAX_NAME_COLUMNS = 4
# The graph labels accepted edges with their residual up to this many scans.
LABELLED_EDGES_MAX_SCANS = 16
# A scan's marker: its colour repeats every 20 scans (tab20), its marker changes.
MARKERS = ("o", "s", "D", "h", "p", "8", "^", "v")  # the first six hold a node's number


# matplotlib's qualitative colormaps tab10 and tab20 as uint8 RGB (their values, rounded): the
# colours of merged.ply need no matplotlib (a base install writes it).
TAB10 = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
         (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207))
TAB20 = ((31, 119, 180), (174, 199, 232), (255, 127, 14), (255, 187, 120), (44, 160, 44),
         (152, 223, 138), (214, 39, 40), (255, 152, 150), (148, 103, 189), (197, 176, 213),
         (140, 86, 75), (196, 156, 148), (227, 119, 194), (247, 182, 210), (127, 127, 127),
         (199, 199, 199), (188, 189, 34), (219, 219, 141), (23, 190, 207), (158, 218, 229))

# The graph's edges by what became of them (`MultiwayEdge.outcome`): (legend text, colour, line
# style), drawn in this order (the most telling on top); errors are counted, not drawn.
EDGE_STYLES = {
    "unused": ("not sure, not used", "0.72", ":"),
    "accepted_not_sure": ("not sure, accepted (the graph backs it)", "tab:orange", "-"),
    "accepted": ("success, accepted", "tab:green", "-"),
    "rejected": ("success, rejected by the graph", "tab:red", "--"),
}
# An accepted edge's residual label, by its kind.
LABEL_COLOURS = {"accepted": "darkgreen", "accepted_not_sure": "saddlebrown"}
# The distance panel's trees hold this many points at most (a seeded sample of a larger model;
# a distance to a surface, fitted to the nearest points, hardly depends on their density).
DISTANCE_TREE_POINTS = 250_000


def scan_colours(n: int) -> np.ndarray:
  """(n, 3) uint8 distinct colours, one per scan (matplotlib's tab10, then tab20; no
  matplotlib import)."""
  table = np.array(TAB10 if n <= 10 else TAB20, np.uint8)
  return table[np.arange(n) % len(table)]


def scan_styles(n: int) -> tuple[np.ndarray, list[str]]:
  """Each scan's colour and marker in the figures: (n, 3) float RGB in [0, 1] (`scan_colours`,
  merged.ply's) and n matplotlib marker names, "o" up to 20 scans, then a new marker for each
  further 20 (their colours repeat)."""
  markers = [MARKERS[(k // len(TAB20)) % len(MARKERS)] for k in range(n)]
  return scan_colours(n) / 255.0, markers


def _pyplot():
  return pyplot("plot", "register_all's figures")


def _sample(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
  """Sorted indices of at most k of n items (all when n <= k)."""
  if n <= k:
    return np.arange(n)
  return np.sort(rng.choice(n, k, replace=False))


def principal_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(centre (3,), axes (3, 3), rows the unit axes): the principal axes of `points`, largest
  spread first, right-handed; the third axis points to the long tail of the points along it (a
  street's "up": most points of a LiDAR sweep are on the ground), the first likewise."""
  centre = np.median(points, axis=0)
  sub = points[:: max(len(points) // 20000, 1)] - centre
  spread = sub - sub.mean(axis=0)
  _, vectors = np.linalg.eigh(spread.T @ spread)  # (3, 3) however few the points
  axes = vectors[:, ::-1].T.copy()  # rows, largest spread first
  for k in (0, 2):
    c = sub @ axes[k]
    if np.mean((c - c.mean()) ** 3) < 0:
      axes[k] = -axes[k]
  axes[1] = np.cross(axes[2], axes[0])
  return centre, axes


def distance_to_other_scans(points: np.ndarray, scan: np.ndarray, query: np.ndarray,
                            query_scan: np.ndarray, limit: float,
                            neighbours: int = 12) -> tuple[np.ndarray, np.ndarray]:
  """Each query point's distance to the other scans: to the nearest of `points` that belongs to
  another scan, and to that scan's surface there (along the normal of the nearest point's
  `neighbours` nearest points of its scan: a part one scan alone saw, beyond another's border,
  is near that surface's continuation; a misplaced scan is off it).

  Args:
    points: (m, 3) the merged points (one k-d tree per scan is built on them).
    scan: (m,) the scan of each point.
    query: (q, 3) the points asked about.
    query_scan: (q,) the scan of each of them.
    limit: the largest distance looked for (cloud units).
    neighbours: points of the normal's fit.

  Returns:
    (to the nearest point, to the surface there), each (q,) float64, inf where no other scan
    has a point within `limit`.
  """
  from scipy.spatial import cKDTree
  best = np.full(len(query), np.inf)
  best_scan = np.full(len(query), -1)
  best_index = np.zeros(len(query), np.int64)
  own, trees, boxes = {}, {}, {}
  for s in np.unique(scan):
    own[s] = points[scan == s]
    trees[s] = cKDTree(own[s])
    boxes[s] = (own[s].min(axis=0) - limit, own[s].max(axis=0) + limit)
  for s in np.unique(query_scan):
    mine = np.flatnonzero(query_scan == s)
    q = query[mine]
    for t, tree in trees.items():
      if t == s:
        continue
      near = np.all((q >= boxes[t][0]) & (q <= boxes[t][1]), axis=1)  # within its grown box
      if not near.any():
        continue
      d, i = tree.query(q[near], k=1, distance_upper_bound=limit)
      rows = mine[near]
      better = d < best[rows]
      best[rows[better]], best_scan[rows[better]] = d[better], t
      best_index[rows[better]] = i[better]
  plane = best.copy()
  for t in np.unique(best_scan[best_scan >= 0]):
    rows = np.flatnonzero(best_scan == t)
    anchor = own[t][best_index[rows]]
    k = min(neighbours, len(own[t]))
    _, nb = trees[t].query(anchor, k=k)
    patch = own[t][np.reshape(nb, (len(rows), k))]
    patch = patch - patch.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("rki,rkj->rij", patch, patch))
    normal = vectors[:, :, 0]  # the smallest spread's direction
    plane[rows] = np.abs(np.einsum("ri,ri->r", query[rows] - anchor, normal))
  return best, plane


def _scatter_scans(ax: Any, u: np.ndarray, v: np.ndarray, scan: np.ndarray, colours: np.ndarray,
                   markers: list[str], size: float, rng: np.random.Generator) -> None:
  """Points coloured by scan, in a random order (no scan always drawn over the others), one
  scatter per marker."""
  order = rng.permutation(len(u))
  u, v, scan = u[order], v[order], scan[order]
  marker_of = np.array(markers)[scan] if len(scan) else np.array([], str)
  for marker in dict.fromkeys(markers):
    sel = marker_of == marker
    if sel.any():
      ax.scatter(u[sel], v[sel], s=size, c=colours[scan[sel]], marker=marker, linewidths=0,
                 rasterized=True)


def _bare(ax: Any, title: str) -> None:
  ax.set_title(title, fontsize=10)
  ax.set_xticks([])
  ax.set_yticks([])


def _limits(values: np.ndarray, floor: float) -> tuple[float, float]:
  """Axis limits holding all but the farthest 0.5% of `values` at each end, 4% margins, at
  least `floor` wide (a LiDAR sweep's few far points would shrink the rest to a dot)."""
  if not len(values):
    return -floor / 2, floor / 2
  lo, hi = np.quantile(values, [0.005, 0.995])
  centre, half = (lo + hi) / 2, max(hi - lo, floor) / 2 * 1.08
  return float(centre - half), float(centre + half)


def _scale_bar(ax: Any, mr: float) -> None:
  """A round length in the lower left corner, in the clouds' units and in mr."""
  x0, x1 = ax.get_xlim()
  y0, y1 = ax.get_ylim()
  raw = (x1 - x0) / 5
  if not raw > 0:
    return
  bar = 10 ** np.floor(np.log10(raw))
  bar *= next(m for m in (5, 2, 1) if m * bar <= raw)
  x, y = x0 + 0.04 * (x1 - x0), y0 + 0.05 * (y1 - y0)
  ax.plot([x, x + bar], [y, y], color="black", lw=2)
  ax.text(x + bar / 2, y + 0.015 * (y1 - y0), f"{bar:g} ({bar / mr:.0f} mr)", ha="center",
          va="bottom", fontsize=8)


def merged_figure(points: np.ndarray, scan: np.ndarray, result: MultiwayResult,
                  path: str | os.PathLike, *, seed: int = 0) -> Path:
  """The merged model in three panels, and a legend of the scans.

  In the model's principal axes (`principal_frame`: axes 1 and 2 the largest spread, axis 3 the
  normal of the model's main plane, a street's "up"): the model seen along axis 3, each scan in
  its colour (`scan_styles`); a section through the middle (a slab `SECTION_MR` mr thick across
  axis 2), where scans that line up draw one curve and a misplaced one a curve of its own (a
  flat model's section is stretched along axis 3, the factor in its title); and the model seen
  along axis 3 again, each point coloured by its distance to the other scans' surface
  (`distance_to_other_scans`, against at most `DISTANCE_TREE_POINTS` of the model; the scale
  ends at `DISTANCE_MAX_MR` mr, grey where no other scan is within `NO_OVERLAP_MR` mr: a part one
  scan alone saw), the farthest drawn last, where a misplaced scan stands out. The title names
  the scans left out. Each panel draws at most `FIGURE_POINTS` (seeded samples).

  Args:
    points: (m, 3) merged points (reference frame; `merged_cloud`).
    scan: (m,) the scan of each point.
    result: the registration (names, which scans are in, mr).
    path: the PNG to write.
    seed: seed of the drawn samples.

  Returns:
    The path written.
  """
  plt = _pyplot()
  rng = np.random.default_rng(seed)
  points = np.asarray(points, np.float64)
  scan = np.asarray(scan, np.int64)
  n, mr = len(result.names), float(result.mr)
  colours, markers = scan_styles(n)
  wide = n > NAMES_PER_COLUMN  # a legend of two columns
  fig = plt.figure(figsize=(18.5 if wide else 17, 6.2))
  x0, w = (0.005, 0.255) if wide else (0.005, 0.28)  # fixed places: equal axes defeat layouts
  ax = [fig.add_axes((x0 + k * (w + 0.01), 0.13, w, 0.76)) for k in range(3)]
  titles = ["from above (along axis 3), by scan",
            f"section through the middle ({SECTION_MR:g} mr slab across axis 2), by scan",
            "distance to the other scans, from above"]
  if len(points):
    titles[1:] = _panels(fig, ax, points, scan, mr, colours, markers, rng)
  for a, title in zip(ax, titles):
    _bare(a, title)
  _scan_legend(fig.add_axes((x0 + 3 * (w + 0.01), 0.05, 1 - x0 - 3 * (w + 0.01), 0.86)), result,
               colours, markers)
  left = result.left_out
  fig.suptitle(f"merged model: {int(result.in_model.sum())} of {n} scans in the frame of "
               f"{_short(result.names[result.reference])} (mr {mr:.4g})"
               + (f"; left out: {_names(left)}" if left else ""), fontsize=12, y=0.985)
  save_figure(fig, path, dpi=FIGURE_DPI)
  plt.close(fig)
  return Path(path)


def _panels(fig: Any, ax: list[Any], points: np.ndarray, scan: np.ndarray, mr: float,
            colours: np.ndarray, markers: list[str], rng: np.random.Generator) -> list[str]:
  """Draw `merged_figure`'s three panels; the titles of the section and the distance panel."""
  centre, axes = principal_frame(points)
  top = _sample(len(points), FIGURE_POINTS, rng)
  slab = np.flatnonzero(np.abs((points - centre) @ axes[1]) <= SECTION_MR * mr / 2)
  slab = slab[_sample(len(slab), FIGURE_POINTS // 2, rng)]
  near = _sample(len(points), FIGURE_POINTS // 2, rng)
  uvw = np.zeros_like(points)  # principal coordinates, of the points drawn only
  for drawn in (top, slab, near):
    uvw[drawn] = (points[drawn] - centre) @ axes.T
  xlim, ylim = _limits(uvw[top, 0], 10 * mr), _limits(uvw[top, 1], 10 * mr)
  side = max(xlim[1] - xlim[0], ylim[1] - ylim[0]) / 2
  xlim = (sum(xlim) / 2 - side, sum(xlim) / 2 + side)
  ylim = (sum(ylim) / 2 - side, sum(ylim) / 2 + side)
  _scatter_scans(ax[0], uvw[top, 0], uvw[top, 1], scan[top], colours, markers, 0.5, rng)
  # the section: the points within SECTION_MR / 2 mr of the centre (a median) along axis 2
  _scatter_scans(ax[1], uvw[slab, 0], uvw[slab, 2], scan[slab], colours, markers, 2.0, rng)
  zlim = _limits(uvw[slab, 2], 10 * mr)
  stretch = float(np.clip(np.floor((xlim[1] - xlim[0]) / (zlim[1] - zlim[0]) / 4), 1, 20))
  ax[1].set_ylim(*zlim)
  ax[1].set_aspect(stretch)
  # the distances: a sample of the model against every other scan's points
  tree = _sample(len(points), DISTANCE_TREE_POINTS, rng)
  _, dist = distance_to_other_scans(points[tree], scan[tree], points[near], scan[near],
                                    NO_OVERLAP_MR * mr)
  dist /= mr
  lone = ~np.isfinite(dist)
  ax[2].scatter(uvw[near[lone], 0], uvw[near[lone], 1], s=0.5, c="0.85", linewidths=0,
                rasterized=True)
  order = np.flatnonzero(~lone)[np.argsort(dist[~lone], kind="stable")]  # the farthest on top
  size = np.where(dist[order] > DISTANCE_MAX_MR / 3, 3.0, 0.8)  # what may be wrong, larger
  art = ax[2].scatter(uvw[near[order], 0], uvw[near[order], 1], s=size, c=dist[order],
                      cmap=DISTANCE_CMAP, vmin=0.0, vmax=DISTANCE_MAX_MR, linewidths=0,
                      rasterized=True)
  box = ax[2].get_position()
  bar = fig.colorbar(art, cax=fig.add_axes((box.x0 + 0.1 * box.width, 0.075, 0.8 * box.width,
                                            0.025)), orientation="horizontal", extend="max")
  bar.set_label(f"distance to the other scans' surface (mr; grey: no other scan within "
                f"{NO_OVERLAP_MR:g} mr)", fontsize=9)
  for a in (ax[0], ax[2]):
    a.set_xlim(*xlim)
    a.set_ylim(*ylim)
    a.set_aspect("equal")
  ax[1].set_xlim(*xlim)
  _scale_bar(ax[0], mr)  # the section has the same horizontal scale
  finite = dist[~lone]
  stats = (f"median {np.median(finite):.2f} mr, 90% of points under "
           f"{np.quantile(finite, 0.9):.2f} mr" if len(finite) else "no two scans overlap")
  ax[2].text(0.5, 0.985, stats, transform=ax[2].transAxes, ha="center", va="top", fontsize=9,
             bbox={"fc": "white", "ec": "none", "alpha": 0.8, "pad": 1.0})
  return [f"section through the middle ({SECTION_MR:g} mr slab across axis 2), by scan"
          + ("" if stretch == 1 else f"\n(height stretched x{stretch:g}, same width as the left)"),
          "distance to the other scans, from above"]


def _scan_legend(ax: Any, result: MultiwayResult, colours: np.ndarray, markers: list[str]) -> None:
  """The scans' colours and markers (the scans left out grey), in one or two columns."""
  from matplotlib.lines import Line2D
  ax.axis("off")
  handles = [Line2D([], [], ls="", marker=markers[k], markersize=7,
                    color=colours[k] if result.in_model[k] else "0.8",
                    label=_short(name) + ("" if result.in_model[k] else " (left out)"))
             for k, name in enumerate(result.names)]
  shown = handles[:2 * NAMES_PER_COLUMN]
  if len(handles) > len(shown):
    shown[-1] = Line2D([], [], ls="", label=f"... {len(handles) - len(shown) + 1} more")
  ax.legend(handles=shown, loc="center left", title="scan", frameon=False, fontsize=8,
            ncols=1 if len(shown) <= NAMES_PER_COLUMN else 2, handletextpad=0.3,
            borderaxespad=0.0)


def _short(name: str, width: int = 24) -> str:
  """`name`, its middle cut out when longer than `width` (scans' names often differ at the
  end)."""
  if len(name) <= width:
    return name
  tail = (width - 1) // 2
  return name[: width - 1 - tail] + "\u2026" + name[-tail:]


def _names(names: Sequence[str], most: int = 6) -> str:
  shown = ", ".join(_short(n) for n in names[:most])
  return shown + (f" and {len(names) - most} more" if len(names) > most else "")


def _label_at(ax: Any, xy: np.ndarray, angle: float, text: str, radial: bool, gap_pt: float,
              **kw: Any) -> None:
  """`text` `gap_pt` points outside the node at `xy` on the circle: horizontal, or along the
  radius (never upside down) so that the labels of many nodes do not overlap."""
  c, s = float(np.cos(angle)), float(np.sin(angle))
  offset = {"xytext": (c * gap_pt, s * gap_pt), "textcoords": "offset points"}
  if radial:
    deg = float(np.degrees(angle)) % 360
    left = 90 < deg < 270
    ax.annotate(text, xy, rotation=deg - 180 if left else deg, rotation_mode="anchor",
                ha="right" if left else "left", va="center", **offset, **kw)
  else:
    ax.annotate(text, xy, ha="center" if abs(c) < 0.3 else ("right" if c < 0 else "left"),
                va="center" if abs(s) < 0.7 else ("bottom" if s > 0 else "top"), **offset, **kw)


def graph_figure(result: MultiwayResult, clouds: Sequence[np.ndarray] | None,
                 path: str | os.PathLike) -> Path:
  """The candidate graph: the scans on a circle in the given order (clockwise from the top),
  every pair registered drawn by what became of it (`EDGE_STYLES`: accepted green, wider with
  more inliers, and labelled with its residual in mr up to `LABELLED_EDGES_MAX_SCANS` scans;
  accepted on the graph's backing although "not sure" orange; a trusted edge the graph rejected
  red, dashed; "not sure" and unused grey, dotted; pairs that could not be registered counted in
  the legend, not drawn). The reference scan has a thick outline, a scan placed only through
  "not sure" edges an orange one, scans left out are grey (the legend says which is which). Up to
  `NAMED_NODES_MAX` scans (beyond 8, with names of at most `NAMED_NODES_CHARS` characters) the
  names stand beside the nodes; else the nodes are numbered (register_all's order, from 0) and
  the names listed on the right.

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
  named = n <= NAMED_NODES_MAX and (n <= 8 or max(map(len, result.names)) <= NAMED_NODES_CHARS)
  angle = np.pi / 2 - 2 * np.pi * np.arange(n) / n
  xy = np.stack([np.cos(angle), np.sin(angle)], axis=1)
  columns = 0 if named else min(-(-n // NAMES_PER_COLUMN), MAX_NAME_COLUMNS)
  width = 8.5 + 2.6 * columns
  fig = plt.figure(figsize=(width, 8.8))
  ax = fig.add_axes((0.02, 0.16, 8.5 / width * 0.96, 0.78))
  counts = _graph_edges(ax, result, xy)
  labels = [_short(name) for name in result.names]  # the legend tells the reference and the rest
  reach = 1.22
  if named and n > 8:  # radial names: room for the longest above and below the circle
    label_in = 0.075 * max(map(len, labels)) + 0.35
    reach = 1.0 / max(1.0 - 2 * label_in / (0.78 * 8.8), 0.5)
  _graph_nodes(ax, result, xy, angle, labels if named else None)
  _graph_legend(ax, result, counts)
  ax.set_xlim(-reach, reach)
  ax.set_ylim(-reach, reach)
  ax.set_aspect("equal")
  ax.axis("off")
  if not named:
    _name_list(fig, result, 8.5 / width)
  fig.suptitle(f"pose graph: {n} scans, {len(result.edges)} pairs registered, "
               f"{counts['accepted'] + counts['accepted_not_sure']} edges accepted"
               + (f"; left out: {_names(result.left_out)}" if result.left_out else ""),
               fontsize=12)
  save_figure(fig, path, dpi=FIGURE_DPI, bbox_inches="tight", pad_inches=0.15)
  plt.close(fig)
  return Path(path)


def _graph_edges(ax: Any, result: MultiwayResult, xy: np.ndarray) -> dict[str, int]:
  """Draw the edges (`EDGE_STYLES`, in its order: the most telling on top); their counts by
  kind, "error" included."""
  kinds = [e.outcome for e in result.edges]
  counts = {k: kinds.count(k) for k in (*EDGE_STYLES, "error")}
  rank = {k: r for r, k in enumerate(EDGE_STYLES)}
  thin = max(0.35, min(1.0, 30.0 / max(len(result.edges), 1)))  # many edges: thinner lines
  labelled = len(result.names) <= LABELLED_EDGES_MAX_SCANS
  for k in sorted(range(len(kinds)), key=lambda k: rank.get(kinds[k], -1)):
    e, kind = result.edges[k], kinds[k]
    if kind == "error":
      continue
    _, colour, ls = EDGE_STYLES[kind]
    (x0, y0), (x1, y1) = xy[e.i], xy[e.j]
    lw = {"accepted": (1.0 + 1.5 * np.log10(max(e.n_inliers, 1))) * thin, "unused": 0.8}.get(
        kind, 2.0 * thin)
    ax.plot([x0, x1], [y0, y1], color=colour, lw=lw, ls=ls, zorder=2 + rank[kind],
            solid_capstyle="round")
    if kind in LABEL_COLOURS and labelled and np.isfinite(e.residual_mr):
      # a third of the way from the earlier scan: diameters of the circle do not share it
      ax.text(x0 + (x1 - x0) / 3, y0 + (y1 - y0) / 3, f"{e.residual_mr:.2f}", fontsize=7,
              zorder=7, ha="center", va="center", color=LABEL_COLOURS[kind],
              bbox={"fc": "white", "ec": "none", "alpha": 0.75, "pad": 0.5})
  return counts


def _graph_nodes(ax: Any, result: MultiwayResult, xy: np.ndarray, angle: np.ndarray,
                 labels: list[str] | None) -> None:
  """Draw the scans: named beside their nodes (`labels`), else numbered (inside the node when
  it is large enough, else beside it)."""
  n = len(result.names)
  colours, markers = scan_styles(n)
  unsure = set(result.placed_not_sure)
  gap = 2 * np.pi / max(n, 1) * 8.5 * 72 / 2.9 * 0.6  # points between neighbouring nodes, x0.6
  size = float(min(420.0, gap ** 2))
  for k, name in enumerate(result.names):
    inside = bool(result.in_model[k])
    strong = k == result.reference or name in unsure
    ax.scatter(*xy[k], s=size, color=colours[k] if inside else "0.85", marker=markers[k],
               edgecolors="tab:orange" if name in unsure else "black", zorder=8,
               linewidths=2.8 if strong else 1.0)
    grey = {} if inside else {"color": "0.45"}
    if labels is not None:
      _label_at(ax, xy[k], angle[k], labels[k], n > 8, np.sqrt(size) / 2 + 4, fontsize=10,
                zorder=9, **grey)
    elif size >= 150:
      ax.text(*xy[k], str(k), ha="center", va="center", fontsize=7 if k < 100 else 6, zorder=9,
              **grey)
    else:
      _label_at(ax, xy[k], angle[k], str(k), True, np.sqrt(size) / 2 + 2, fontsize=6, zorder=9,
                **grey)


def _graph_legend(ax: Any, result: MultiwayResult, counts: dict[str, int]) -> None:
  """The legend under the graph: each kind of edge with its count, the node outlines."""
  from matplotlib.lines import Line2D
  labelled = len(result.names) <= LABELLED_EDGES_MAX_SCANS
  handles = [Line2D([], [], color=EDGE_STYLES[kind][1], ls=EDGE_STYLES[kind][2],
                    lw=3 if kind == "accepted" else 2,
                    label=f"{EDGE_STYLES[kind][0]} ({counts[kind]})"
                    + ("; label: residual, mr" if kind == "accepted" and labelled else ""))
             for kind in ("accepted", "accepted_not_sure", "rejected", "unused")]
  handles.append(Line2D([], [], ls="", label=f"could not be registered, not drawn "
                                             f"({counts['error']})"))
  node: dict[str, Any] = {"ls": "", "marker": "o", "markersize": 10, "markeredgewidth": 2.5}
  handles.append(Line2D([], [], color="white", markeredgecolor="black", **node,
                        label=f"reference: {_short(result.names[result.reference])}"))
  if result.placed_not_sure:
    handles.append(Line2D([], [], color="white", markeredgecolor="tab:orange", **node,
                          label=f"placed only through \"not sure\" edges "
                                f"({len(result.placed_not_sure)})"))
  if result.left_out:
    handles.append(Line2D([], [], color="0.85", markeredgecolor="black",
                          **dict(node, markeredgewidth=1.0),
                          label=f"left out ({len(result.left_out)})"))
  ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0), fontsize=9,
            frameon=False, ncols=2)


def _name_list(fig: Any, result: MultiwayResult, x0: float) -> None:
  """The names of the numbered nodes, in columns right of the graph (from figure x `x0`)."""
  n = len(result.names)
  room = NAMES_PER_COLUMN * MAX_NAME_COLUMNS
  shown = range(n if n <= room else room - 1)
  columns = -(-len(shown) // NAMES_PER_COLUMN)
  col_w = (1.0 - x0 - 0.01) / max(columns, 1)
  fig.text(x0, 0.93, "scans (node number: name)", fontsize=10, va="bottom")
  for k in shown:
    c, r = divmod(k, NAMES_PER_COLUMN)
    text = f"{k:>3}  {_short(result.names[k], 22)}" + (" (ref.)" if k == result.reference else "")
    fig.text(x0 + c * col_w, 0.91 - r * 0.026, text, fontsize=8, va="top", family="monospace",
             color="black" if result.in_model[k] else "0.5")
  if len(shown) < n:
    c, r = divmod(len(shown), NAMES_PER_COLUMN)
    fig.text(x0 + c * col_w, 0.91 - r * 0.026, f"... {n - len(shown)} more (edges.tsv)",
             fontsize=8, va="top")
