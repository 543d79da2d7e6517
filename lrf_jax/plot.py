"""Figures a user looks at: local reference frames drawn on their cloud."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lrf_jax.io import atomic

AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")  # x, y, z


def frames(points: np.ndarray, keypoints: np.ndarray, frames: np.ndarray,
           path: str | os.PathLike, *, valid: np.ndarray | None = None, sample: int = 60,
           length: float | None = None, seed: int = 0, title: str | None = None) -> Path:
  """Draw a cloud (grey dots) with the LRF axes of a sample of keypoints as arrows.

  x red, y green, z blue, each of length `length` (default: 4 % of the cloud's bounding-box
  diagonal); invalid frames are skipped. Two views: an oblique one and the view along the mean z.

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
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  pts = np.asarray(points, np.float64)
  kp = np.asarray(keypoints, np.int64)
  f = np.asarray(frames, np.float64)
  ok = np.ones(len(kp), bool) if valid is None else np.asarray(valid, bool)
  idx = np.flatnonzero(ok)
  rng = np.random.default_rng(seed)
  if len(idx) > sample:
    idx = np.sort(rng.choice(idx, sample, replace=False))
  diag = float(np.linalg.norm(np.ptp(pts, axis=0))) or 1.0
  length = 0.04 * diag if length is None else float(length)
  shown = pts[rng.choice(len(pts), min(len(pts), 20000), replace=False)]
  fig = plt.figure(figsize=(11, 5.5))
  views = ((25, -60, "oblique view"), (90, -90, "top view (along +z of the data)"))
  for i, (elev, azim, name) in enumerate(views):
    ax = fig.add_subplot(1, 2, i + 1, projection="3d")
    ax.scatter(*shown.T, s=0.3, c="0.6", alpha=0.5, depthshade=False)
    for a, colour in enumerate(AXIS_COLOURS):
      base = pts[kp[idx]]
      d = f[idx, a] * length
      ax.quiver(*base.T, *d.T, color=colour, linewidth=1.0, arrow_length_ratio=0.25)
    ax.view_init(elev=elev, azim=azim)
    ax.set_title(name)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if elev == 90:  # seen from above the z ticks collapse onto one another
      ax.set_zticks([])
    else:
      ax.set_zlabel("z")
    lo, hi = pts.min(0), pts.max(0)
    c, half = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_zlim(c[2] - half, c[2] + half)
  handles = [plt.Line2D([], [], color=col, label=lab) for col, lab in zip(AXIS_COLOURS, "xyz")]
  fig.legend(handles=handles, loc="upper right", title="LRF axis")
  fig.suptitle(title or f"{len(idx)} of {len(kp)} frames ({int(ok.sum())} valid)")
  out = Path(path)
  out.parent.mkdir(parents=True, exist_ok=True)
  try:
    atomic.save_figure(fig, out, dpi=110)  # a failed write leaves the previous file
  finally:
    plt.close(fig)
  return out
