"""Figures a user looks at: frames drawn on their cloud, the repeatability of frames between two
scans, and the correspondences a registration used.

Every view is an orthographic projection onto two principal axes of the cloud drawn at equal
aspect ratio (an object keeps its proportions whatever its coordinate axes), and every figure is
written atomically (`lrf_jax.io.atomic.save_figure`).

* `frames`: the LRF axes of a sample of keypoints on one cloud (lrf-frames --png);
* `repeatability`: two scans' keypoints coloured by per-keypoint MeanCos, and a few numbered
  frames drawn at the same points on both (lrf-frames A --pair B --gt T --png);
* `correspondences`: a registration's inliers and outliers joining the two clouds side by side
  (lrf-register --png).
"""

from __future__ import annotations

import os
from pathlib import Path
import numpy as np

from lrf_jax.extras import pyplot
from lrf_jax.io import atomic

AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")  # x, y, z
MAX_SHOWN_POINTS = 20000  # cloud points drawn per panel (a seeded sample)
# MeanCos above which a frame counts as repeated (the paper's second statistic).
REPEATED_MEANCOS = 0.97


def _pyplot():
  plt = pyplot("plot", "the --png figures")
  return plt


def principal_axes(points: np.ndarray) -> np.ndarray:
  """(3, 3) rows: the principal axes of `points` (n, 3), largest spread first, right-handed;
  the first two signed to point along the coordinate axis each is closest to.

  Projecting onto rows 0 and 1 shows the cloud face-on (along its thinnest direction); rows 0
  and 2 show it from the side."""
  pts = np.asarray(points, np.float64)
  centred = pts - pts.mean(0)
  _, vecs = np.linalg.eigh(centred.T @ centred)
  axes = vecs[:, ::-1].T.copy()
  for a in axes[:2]:  # each points along the data axis it follows most (a bunny stays upright)
    a *= np.sign(a[np.argmax(np.abs(a))]) or 1.0
  axes[2] = np.cross(axes[0], axes[1])
  return axes


def _sample(n: int, m: int, seed: int) -> np.ndarray:
  """At most `m` sorted indices of range(n), seeded."""
  if n <= m:
    return np.arange(n)
  return np.sort(np.random.default_rng(seed).choice(n, m, replace=False))


def _arrows(ax, base2: np.ndarray, frames: np.ndarray, basis: np.ndarray, length: float) -> None:
  """Draw the projected x, y, z axes of `frames` (k, 3, 3) at `base2` (k, 2) on a 2D axes."""
  for a, colour in enumerate(AXIS_COLOURS):
    d = frames[:, a] @ basis.T * length  # (k, 2): the axis seen in the view plane
    ax.quiver(base2[:, 0], base2[:, 1], d[:, 0], d[:, 1], color=colour, angles="xy",
              scale_units="xy", scale=1.0, width=0.004, headwidth=3.5, headlength=4,
              zorder=4)


def _frame_legend(fig, loc: str = "upper right") -> None:
  plt = _pyplot()
  handles = [plt.Line2D([], [], color=c, label=f"{a} axis") for c, a in zip(AXIS_COLOURS, "xyz")]
  fig.legend(handles=handles, loc=loc, title="LRF (projected)", fontsize=8, title_fontsize=8)


def _write(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
  plt = _pyplot()
  out = Path(path)
  out.parent.mkdir(parents=True, exist_ok=True)
  try:
    atomic.save_figure(fig, out, dpi=dpi)  # a failed write leaves the previous file
  finally:
    plt.close(fig)
  return out


def _view(ax, points2: np.ndarray, title: str, xlabel: str, ylabel: str) -> None:
  """A grey cloud, equal aspect ratio, a little margin, a few ticks."""
  ax.scatter(points2[:, 0], points2[:, 1], s=0.4, c="0.75", linewidths=0, zorder=1)
  ax.set_aspect("equal", adjustable="datalim")
  ax.set_title(title, fontsize=10)
  ax.set_xlabel(xlabel, fontsize=8)
  ax.set_ylabel(ylabel, fontsize=8)
  ax.tick_params(labelsize=7)
  ax.locator_params(nbins=5)


def frames(points: np.ndarray, keypoints: np.ndarray, frames: np.ndarray,
           path: str | os.PathLike, *, valid: np.ndarray | None = None, sample: int = 60,
           length: float | None = None, seed: int = 0, title: str | None = None) -> Path:
  """Draw a cloud (grey dots) with the LRF axes of a sample of keypoints as arrows.

  x red, y green, z blue, each of length `length` (default: 4 % of the cloud's bounding-box
  diagonal), projected into the view; invalid frames are skipped. Two views at equal aspect
  ratio: face-on (the cloud's two largest principal axes) and from the side (largest and
  smallest).

  Args:
    points: (n, 3) cloud.
    keypoints: (m,) indices of the frames' keypoints.
    frames: (m, 3, 3) frames, rows x, y, z.
    path: the figure to write (PNG, or the format of its suffix), atomically.
    valid: (m,) validity (default: every frame).
    sample: at most this many keypoints are drawn (seeded choice).
    length: arrow length in cloud units.
    seed: seed of the sample.
    title: figure title.

  Returns:
    The path written.
  """
  plt = _pyplot()
  pts = np.asarray(points, np.float64)
  kp = np.asarray(keypoints, np.int64)
  f = np.asarray(frames, np.float64)
  ok = np.ones(len(kp), bool) if valid is None else np.asarray(valid, bool)
  idx = np.flatnonzero(ok)
  idx = idx[_sample(len(idx), sample, seed)]
  diag = float(np.linalg.norm(np.ptp(pts, axis=0))) or 1.0
  length = 0.04 * diag if length is None else float(length)
  axes = principal_axes(pts)
  shown = pts[_sample(len(pts), MAX_SHOWN_POINTS, seed)] - pts.mean(0)
  fig, panels = plt.subplots(1, 2, figsize=(11, 5.2))
  for ax, (i, j, name) in zip(panels, ((0, 1, "face-on"), (0, 2, "from the side"))):
    basis = axes[[i, j]]
    _view(ax, shown @ basis.T, f"{name} (principal axes {i + 1} and {j + 1})",
          f"principal axis {i + 1}", f"principal axis {j + 1}")
    _arrows(ax, (pts[kp[idx]] - pts.mean(0)) @ basis.T, f[idx], basis, length)
  _frame_legend(fig)
  fig.suptitle(title or f"{len(idx)} of {len(kp)} frames ({int(ok.sum())} valid)")
  fig.tight_layout(rect=(0, 0, 0.88, 0.95))
  return _write(fig, path)


def _moved(points: np.ndarray, transform: np.ndarray, inverse: bool = False) -> np.ndarray:
  """(n, 3) float64 `points` moved by the rigid (4, 4) `transform` (p -> R p + t), or by its
  inverse (p -> Rᵀ (p - t)) with `inverse`."""
  t = np.asarray(transform, np.float64)
  p = np.asarray(points, np.float64)
  return (p - t[:3, 3]) @ t[:3, :3] if inverse else p @ t[:3, :3].T + t[:3, 3]


def spread_choice(points: np.ndarray, k: int) -> np.ndarray:
  """`k` indices of `points` (m, 3) spread over the cloud: farthest-point sampling started at
  the point farthest from the centroid (deterministic). Fewer when m < k."""
  pts = np.asarray(points, np.float64)
  if len(pts) == 0 or k <= 0:
    return np.zeros(0, np.int64)
  chosen = [int(np.argmax(np.linalg.norm(pts - pts.mean(0), axis=1)))]
  dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
  while len(chosen) < min(k, len(pts)):
    nxt = int(np.argmax(dist))
    chosen.append(nxt)
    dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
  return np.asarray(chosen, np.int64)


def repeatability(model_points: np.ndarray, scene_points: np.ndarray,
                  model_keypoints: np.ndarray, scene_keypoints: np.ndarray,
                  model_frames: np.ndarray, scene_frames: np.ndarray, meancos: np.ndarray,
                  transform: np.ndarray, path: str | os.PathLike, *, n_frames: int = 6,
                  length: float | None = None, seed: int = 0, title: str | None = None,
                  names: tuple[str, str] = ("A", "B")) -> Path:
  """Whether frames repeat between two scans: keypoints coloured by per-keypoint MeanCos, a few
  numbered frames drawn at the same points on both scans, and the MeanCos histogram.

  The scene (B) is drawn in the model's (A's) coordinates (moved by the inverse of `transform`,
  its frames' rows by the same rotation), so both panels share one view: a repeatable frame
  looks the same in both. Keypoint i of A corresponds to keypoint i of B.

  Args:
    model_points: (n, 3) cloud A.
    scene_points: (n', 3) cloud B, same units.
    model_keypoints: (m,) indices into A.
    scene_keypoints: (m,) indices into B of the corresponding points.
    model_frames: (m, 3, 3) frames on A (rows x, y, z).
    scene_frames: (m, 3, 3) frames on B.
    meancos: (m,) per-keypoint MeanCos in [-1, 1] (0 where a frame is invalid;
      `lrf_jax.meancos`).
    transform: (4, 4) ground truth mapping A's points onto B's.
    path: the figure to write, atomically.
    n_frames: frames drawn on both scans (spread over A, numbered 1..n_frames).
    length: arrow length in cloud units (default: 6 % of A's bounding-box diagonal).
    seed: seed of the sample of cloud points drawn.
    title: figure title.
    names: labels of the two scans (e.g. their file names).

  Returns:
    The path written.
  """
  plt = _pyplot()
  a = np.asarray(model_points, np.float64)
  rot = np.asarray(transform, np.float64)[:3, :3]
  b = _moved(scene_points, transform, inverse=True)  # B in A's coordinates
  mk, sk = np.asarray(model_keypoints, np.int64), np.asarray(scene_keypoints, np.int64)
  fa = np.asarray(model_frames, np.float64)
  fb = np.asarray(scene_frames, np.float64) @ rot  # rows mapped back: L_s R
  mc = np.asarray(meancos, np.float64)
  centre, axes = a.mean(0), principal_axes(a)
  basis = axes[:2]
  diag = float(np.linalg.norm(np.ptp(a, axis=0))) or 1.0
  length = 0.06 * diag if length is None else float(length)
  drawn = spread_choice(a[mk], n_frames)
  fig = plt.figure(figsize=(13, 6.2))
  grid = fig.add_gridspec(2, 3, width_ratios=(1, 1, 0.7), height_ratios=(1, 0.035),
                          wspace=0.25, hspace=0.28, left=0.05, right=0.98, top=0.9,
                          bottom=0.08)
  panels = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])]
  hist = fig.add_subplot(grid[0, 2])
  scatter = None
  for ax, pts, kp, f, name in ((panels[0], a, mk, fa, names[0]),
                               (panels[1], b, sk, fb, f"{names[1]} (in {names[0]}'s frame)")):
    shown = pts[_sample(len(pts), MAX_SHOWN_POINTS, seed)]
    _view(ax, (shown - centre) @ basis.T, name, "principal axis 1", "principal axis 2")
    k2 = (pts[kp] - centre) @ basis.T
    scatter = ax.scatter(k2[:, 0], k2[:, 1], c=mc, cmap="RdYlGn", vmin=0.0, vmax=1.0, s=9,
                         linewidths=0.2, edgecolors="0.3", zorder=3)
    _arrows(ax, k2[drawn], f[drawn], basis, length)
    for number, i in enumerate(drawn, 1):
      ax.annotate(str(number), k2[i], xytext=(5, 5), textcoords="offset points", fontsize=8,
                  zorder=5, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="0.5", lw=0.5))
  lim = [np.r_[p.get_xlim(), p.get_ylim()] for p in panels]  # one scale for both panels
  lo, hi = np.min(lim, 0), np.max(lim, 0)
  for ax in panels:
    ax.set_xlim(lo[0], hi[1])
    ax.set_ylim(lo[2], hi[3])
    ax.set_aspect("equal", adjustable="box")
  cbar = fig.colorbar(scatter, cax=fig.add_subplot(grid[1, :2]), orientation="horizontal")
  cbar.set_label("MeanCos per keypoint (1: the same frame on both scans; invalid: 0)",
                 fontsize=8)
  cbar.ax.tick_params(labelsize=7)
  _meancos_histogram(hist, mc, drawn)
  _frame_legend(fig, loc="lower right")
  fig.suptitle(title or f"repeatability of {len(mk)} keypoints: mean MeanCos {mc.mean():.3f}",
               fontsize=11)
  return _write(fig, path)


def _meancos_histogram(ax, mc: np.ndarray, drawn: np.ndarray) -> None:
  """MeanCos histogram with the repeated threshold and the drawn frames' values listed."""
  ax.hist(np.clip(mc, -1, 1), bins=np.linspace(-1, 1, 41), color="0.55")
  ax.axvline(REPEATED_MEANCOS, color="tab:green", lw=1)
  share = float(np.mean(mc > REPEATED_MEANCOS)) if len(mc) else 0.0
  ax.set_title(f"MeanCos: mean {mc.mean():.3f}, {share:.0%} > {REPEATED_MEANCOS:g}",
               fontsize=10)
  ax.set_xticks([-1.0, -0.5, 0.0, 0.5, 1.0])
  ax.set_xlabel("MeanCos", fontsize=8)
  ax.set_ylabel("keypoints", fontsize=8)
  ax.tick_params(labelsize=7)
  listing = "\n".join(f"frame {n}: {mc[i]:.3f}" for n, i in enumerate(drawn, 1))
  ax.text(0.03, 0.97, listing, transform=ax.transAxes, va="top", fontsize=8, family="monospace",
          bbox=dict(fc="white", ec="0.7", lw=0.5))


def correspondences(source_points: np.ndarray, target_points: np.ndarray,
                    pairs: np.ndarray, inliers: np.ndarray, transform: np.ndarray,
                    path: str | os.PathLike, *, max_lines: int = 150, seed: int = 0,
                    title: str | None = None, names: tuple[str, str] = ("source", "target")
                    ) -> Path:
  """A registration's correspondences: the source (moved by `transform`, so both clouds look
  alike) on the left, the target on the right, joined by a line per correspondence: inliers
  green, outliers red. Under a right transform the inlier lines are parallel.

  Args:
    source_points: (n, 3) source cloud.
    target_points: (n', 3) target cloud, same units.
    pairs: (C, 2) int (source index, target index) (`Registration.correspondences`).
    inliers: (C,) bool (`Registration.inliers`).
    transform: (4, 4) source -> target (`Registration.transform`).
    path: the figure to write, atomically.
    max_lines: at most this many lines of each kind (a seeded sample; the counts in the legend
      are of all of them).
    seed: seed of the samples.
    title: figure title.
    names: labels of the two clouds (e.g. their file names).

  Returns:
    The path written.
  """
  plt = _pyplot()
  src = _moved(source_points, transform)
  dst = np.asarray(target_points, np.float64)
  pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
  inl = np.asarray(inliers, bool).reshape(-1)
  if len(inl) != len(pairs):
    raise ValueError(f"correspondences: inliers {inl.shape} do not match pairs {pairs.shape}")
  centre, basis = dst.mean(0), principal_axes(dst)[:2]
  s2, d2 = (src - centre) @ basis.T, (dst - centre) @ basis.T
  gap = 1.35 * max(np.ptp(d2[:, 0]), np.ptp(s2[:, 0]), 1e-12)
  # side by side: each cloud's box centred at -gap/2 and +gap/2 (only x moves: inlier lines
  # of a right transform stay horizontal)
  s2 = s2 - [(s2[:, 0].min() + s2[:, 0].max()) / 2 + gap / 2, 0]
  d2 = d2 - [(d2[:, 0].min() + d2[:, 0].max()) / 2 - gap / 2, 0]
  fig, ax = plt.subplots(figsize=(12, 6))
  for pts in (s2, d2):
    shown = pts[_sample(len(pts), MAX_SHOWN_POINTS, seed)]
    ax.scatter(shown[:, 0], shown[:, 1], s=0.4, c="0.75", linewidths=0, zorder=1)
  from matplotlib.collections import LineCollection
  for mask, colour, label, z in ((~inl, "tab:red", "outliers", 2), (inl, "tab:green",
                                                                    "inliers", 3)):
    idx = np.flatnonzero(mask)
    shown = idx[_sample(len(idx), max_lines, seed)]
    segs = np.stack([s2[pairs[shown, 0]], d2[pairs[shown, 1]]], axis=1)
    # an (N, 2, 2) array of segments, which matplotlib takes (its stub asks for a sequence)
    ax.add_collection(LineCollection(segs, colors=colour, linewidths=0.5,  # type: ignore[arg-type]
                                     alpha=0.35 if colour == "tab:red" else 0.7, zorder=z,
                                     label=f"{label}: {len(idx)}"
                                           + (f" ({len(shown)} drawn)" if len(shown) < len(idx)
                                              else "")))
    ends = np.r_[s2[pairs[shown, 0]], d2[pairs[shown, 1]]]
    ax.scatter(ends[:, 0], ends[:, 1], s=4, c=colour, linewidths=0, zorder=z)
  both = np.r_[s2, d2]
  pad = 0.03 * np.ptp(both, axis=0).max()
  ax.set_xlim(both[:, 0].min() - pad, both[:, 0].max() + pad)
  lo, hi = both[:, 1].min() - pad, both[:, 1].max() + pad
  for x, name in ((-gap / 2, f"{names[0]} (moved by the transform)"), (gap / 2, names[1])):
    ax.text(x, hi, name, ha="center", va="bottom", fontsize=9)
  ax.set_ylim(lo, hi + 0.06 * (hi - lo))
  ax.set_aspect("equal", adjustable="box")
  ax.set_xticks([])
  ax.set_yticks([])
  ax.legend(loc="lower center", ncol=2, fontsize=9, frameon=False,
            bbox_to_anchor=(0.5, -0.08))
  ax.set_title(title or f"{len(pairs)} correspondences, {int(inl.sum())} inliers", fontsize=11)
  fig.tight_layout()
  return _write(fig, path)

