"""The joint ICP of `register_all`: every accepted pair's point-to-plane residuals, all poses of
the model moved at once."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lrf_jax.multiway import pose_graph
from lrf_jax.registration.icp_normals import TargetNormals
from lrf_jax.search import engine as search_engine

__all__ = ["REFINE_STEPS", "refine_poses"]

# Joint ICP: Gauss-Newton steps (residual evaluations) per re-pairing round.
REFINE_STEPS = 3


def _apply(t: np.ndarray, p: np.ndarray) -> np.ndarray:
  return p @ t[:3, :3].T + t[:3, 3]


def refine_poses(clouds: Sequence[np.ndarray], poses: np.ndarray,
                 pairs: Sequence[tuple[int, int]], *, reference: int, mr: float,
                 icp_mr: float = 3.0, robust_mr: float = 1.0, iterations: int = 10,
                 samples: int = 1000, seed: int = 0) -> np.ndarray:
  """Joint point-to-plane ICP of all scans' poses at once.

  Each round, for every pair (i, j) in both directions: `samples` seeded points of scan i under
  the current poses are paired with their nearest point of scan j within icp_mr mr; one
  `scipy.optimize.least_squares` (Cauchy loss of scale robust_mr mr) moves every pose but the
  reference's to reduce the point-to-plane distances ((X_i p - X_j q) · R_j n, unsigned PCA
  normals of scan j). Stops when no pose moves by more than 0.01 mr at its scan's points.

  Args:
    clouds: n (m_k, 3) scans, each in its own frame.
    poses: (n, 4, 4) start (each maps its scan into the common frame).
    pairs: the overlapping pairs to pair points over (the scans not in any stay fixed).
    reference: the scan whose pose stays fixed.
    mr: mesh resolution (cloud units).
    icp_mr: pairing distance in mr.
    robust_mr: the loss scale in mr.
    iterations: rounds (re-pairings) at most.
    samples: points per scan and direction.
    seed: seed of the samples.

  Returns:
    (n, 4, 4) refined poses.
  """
  poses = np.array(poses, np.float64)
  if not pairs:
    return poses
  rng = np.random.default_rng(seed)
  scans = sorted({k for p in pairs for k in p})
  grids = {k: search_engine.knn_grid(clouds[k]) for k in scans}
  normals = {k: TargetNormals(clouds[k], icp_mr * mr, grids[k]) for k in scans}  # where paired
  subs = {k: clouds[k][np.sort(rng.choice(len(clouds[k]), min(samples, len(clouds[k])),
                                          replace=False))] for k in scans}
  free = [k for k in scans if k != reference]
  for _ in range(int(iterations)):
    blocks = []
    for a, b in pairs:
      for i, j in ((a, b), (b, a)):
        moved = _apply(np.linalg.inv(poses[j]) @ poses[i], subs[i])
        d, idx = search_engine.knn(grids[j], moved, 1, icp_mr * mr)
        ok = np.isfinite(d[:, 0])
        normals[j].require(idx[ok, 0])
        ok[ok] = np.all(np.isfinite(normals[j].pca[idx[ok, 0]]), axis=1)
        if ok.sum() >= 3:
          blocks.append(pose_graph.PointPairs(i, j, subs[i][ok], clouds[j][idx[ok, 0]],
                                              normals[j].pca[idx[ok, 0]]))
    new = pose_graph.least_squares_poses(poses, blocks, free, scale=mr, robust=robust_mr,
                                         max_nfev=REFINE_STEPS)
    moved_by = max((np.abs(_apply(new[k], subs[k]) - _apply(poses[k], subs[k])).max()
                    for k in free), default=0.0)
    poses = new
    if moved_by < 0.01 * mr:
      break
  return poses
