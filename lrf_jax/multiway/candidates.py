"""Which pairs of many scans `register_all` registers: every pair of a few scans; of many, each
scan with the next ones in the given order plus loop-closure candidates of similar shape (the
D2 shape distribution, `shape_signature`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["ALL_PAIRS_MAX", "candidate_pairs", "shape_signature"]

# Scans up to this many: every pair is a candidate.
ALL_PAIRS_MAX = 12


def shape_signature(points: np.ndarray, *, max_distance: float, bins: int = 32,
                    samples: int = 4000, seed: int = 0) -> np.ndarray:
  """The D2 shape distribution of a cloud: a normalised histogram of the distances between
  `samples` seeded random point pairs over [0, max_distance] (Osada et al., "Shape
  distributions", TOG 2002). Invariant to rigid motion, cheap, and similar for scans that see
  the same part of an object.

  Args:
    points: (n, 3) cloud.
    max_distance: upper edge of the histogram (cloud units; the same for scans compared).
    bins: histogram bins.
    samples: point pairs drawn.
    seed: seed of the pairs.

  Returns:
    (bins,) float64 summing to 1.
  """
  rng = np.random.default_rng(seed)
  pts = np.asarray(points, np.float64)
  a, b = rng.integers(len(pts), size=(2, samples))
  d = np.linalg.norm(pts[a] - pts[b], axis=1)
  hist, _ = np.histogram(np.minimum(d, max_distance), bins=bins, range=(0.0, max_distance))
  return hist / max(hist.sum(), 1)


def candidate_pairs(clouds: Sequence[np.ndarray], *, all_pairs_max: int = ALL_PAIRS_MAX,
                    neighbors: int = 1, loop_candidates: int = 3, seed: int = 0
                    ) -> list[tuple[int, int]]:
  """The pairs (i, j), i < j, to register (see the module docstring, step 1).

  Args:
    clouds: n (m_k, 3) clouds in the given order.
    all_pairs_max: up to this many scans, every pair.
    neighbors: otherwise, each scan with this many next scans in the order.
    loop_candidates: plus, per scan, this many scans of closest D2 signature.
    seed: seed of the signatures' point pairs.

  Returns:
    Sorted unique pairs.
  """
  n = len(clouds)
  if n <= all_pairs_max:
    return [(i, j) for i in range(n) for j in range(i + 1, n)]
  pairs = {(i, j) for i in range(n) for j in range(i + 1, min(i + 1 + neighbors, n))}
  extent = max(float(np.linalg.norm(np.ptp(c, axis=0))) for c in clouds)
  sig = np.stack([shape_signature(c, max_distance=extent, seed=seed) for c in clouds])
  k = min(loop_candidates, n - 1)
  if k > 0:
    for i, j in _closest_signatures(sig, k):
      pairs.add((min(i, j), max(i, j)))
  return sorted(pairs)


def _closest_signatures(sig: np.ndarray, k: int) -> list[tuple[int, int]]:
  """(i, j) for each scan i and its k scans j != i of smallest L1 signature distance, ties to
  the lower index: the n x n comparison's result from a k-d tree (O(n log n)). The k-th
  distance is found first, then every scan within it (the ties) ranked exactly."""
  from scipy.spatial import cKDTree
  tree = cKDTree(sig)
  dk, _ = tree.query(sig, k=k + 1, p=1)
  out = []
  for i in range(len(sig)):
    near = np.asarray(tree.query_ball_point(sig[i], float(dk[i, -1]) * (1 + 1e-9) + 1e-12,
                                            p=1), np.int64)
    near = near[near != i]
    d = np.abs(sig[near] - sig[i]).sum(axis=1)
    out += [(i, int(j)) for j in near[np.lexsort((near, d))[:k]]]
  return out
