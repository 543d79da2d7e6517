"""A compatibility-graph estimator for `register`: correspondences that agree with each other.

Two correspondences (p_i, q_i) and (p_j, q_j) of a rigid motion preserve their distance,
|p_i - p_j| = |q_i - q_j|, and, when both carry LRFs, give the same rotation: the
one-correspondence poses R_i, R_j of `host.lrf_hypotheses` (paper section 3.2.3)
differ by a small angle. An outlier agrees with an inlier by chance only, so the inliers form a
dense cluster of the graph whose edges are these agreements (Leordeanu & Hebert 2005; SC2-PCR,
Chen et al. 2022; MAC, Zhang et al. 2023). The estimator:

1. first-order compatibility C_ij = [ | |p_i - p_j| - |q_i - q_j| | < d ] and, with LRFs,
   [ angle(R_i R_jᵀ) < a ] (`compatibility`);
2. a score per correspondence: the leading eigenvector of C (spectral matching, power
   iteration from a constant vector: deterministic);
3. seeds: the best-scoring correspondences, at most one per `nms` ball of source points
   (spatial non-maximum suppression, as SC2-PCR);
4. per seed s the second-order compatibilities SC2_sj = C_sj (C C)_sj, the number of
   correspondences compatible with both s and j (SC2-PCR's measure, computed for the seeds' rows
   only, as popcounts of C's rows packed into bits: `second_order`); its consensus set: s and
   the `consensus` j of largest SC2_sj;
5. per seed one hypothesis: Kabsch on its consensus set weighted by the leading eigenvector of
   the set's own compatibility submatrix.

Memory: C is an (N, N) float32 matrix for N correspondences (4 N^2 bytes: 4 MB at N = 1,000,
36 MB at N = 3,000), filled by a numba kernel with no temporaries, and its bit rows N^2 / 8
bytes; the seeds' second-order rows are (seeds, N). `register` keeps N at its
`n_correspondences` (at most `MAX_CORRESPONDENCES`).

The compatibility matrix and the seeds' suppression are numba kernels, the rest numpy (BLAS for
the spectral products, `np.bitwise_count` for the second order); no JAX program is traced or
loaded.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax import compilation_cache
from lrf_jax.registration import host
from lrf_jax.search.bits import pack_rows
from lrf_jax.search.grid import run_blocks, task_jit

compilation_cache.announce_compiles()  # numba cache keys (lrf_jax.kernel_cache), the compile note

# Power iterations of the spectral score (enough to order the correspondences: the score only
# picks the seeds, the consensus sets are chosen by second-order compatibility).
SCORE_ITERATIONS = 10
# Largest number of correspondences the dense compatibility matrix is built for (100 MB).
MAX_CORRESPONDENCES = 5000


def compatibility(src: np.ndarray, dst: np.ndarray, distance: float,
                  rotations: np.ndarray | None = None, angle_deg: float | None = None
                  ) -> np.ndarray:
  """First-order compatibility of N correspondences, (N, N) float32 of 0/1, zero diagonal.

  Args:
    src: (N, 3) source points of the correspondences.
    dst: (N, 3) their target points.
    distance: d, correspondences i, j are compatible when | |p_i - p_j| - |q_i - q_j| | < d
      (cloud units).
    rotations: optional (N, 3, 3) one-correspondence rotations (q ≈ R_i p + t_i); with
      `angle_deg` the pair must also satisfy angle(R_i R_jᵀ) < angle_deg.
    angle_deg: the rotation agreement bound in degrees (None: distances only).

  Returns:
    (N, N) float32 matrix C with C_ij in {0, 1}, symmetric, C_ii = 0.
  """
  p = np.ascontiguousarray(src, np.float64)
  q = np.ascontiguousarray(dst, np.float64)
  n = len(p)
  if n > MAX_CORRESPONDENCES:
    raise ValueError(f"compatibility: {n} correspondences, at most {MAX_CORRESPONDENCES} "
                     f"(the dense matrix takes 4 N^2 bytes)")
  use_rot = rotations is not None and angle_deg is not None
  rf = (np.ascontiguousarray(rotations, np.float64).reshape(n, 9) if use_rot
        else np.zeros((n, 9)))
  # angle(R_i R_jᵀ) < a  <=>  trace(R_i R_jᵀ) = sum of the entries of R_i ⊙ R_j > 1 + 2 cos a
  min_trace = (1.0 + 2.0 * np.cos(np.radians(float(angle_deg)))  # type: ignore[arg-type]
               if use_rot else -np.inf)  # use_rot: angle_deg is not None
  out = np.empty((n, n), np.float32)
  args = (p, q, rf, float(distance), float(min_trace), bool(use_rot), out)
  run_blocks(lambda lo, hi: _compatibility(*args, lo, hi), (n + 1) // 2)
  return out


@task_jit
def _compatibility(p, q, rf, distance, min_trace, use_rot, out, lo, hi):
  """`compatibility`'s matrix: the upper triangle, mirrored (each test is symmetric in i and j to
  the bit); rows i and n - 1 - i in one task (tasks lo..hi-1 here), so that tasks have equal
  work. The rotation test (nine products) goes first: most pairs fail it and skip the two
  square roots."""
  n = p.shape[0]
  for task in range(lo, hi):
    for side in range(2):
      i = task + side * (n - 1 - 2 * task)  # task, then n - 1 - task
      if side == 1 and i == task:
        break
      out[i, i] = 0.0
      for j in range(i + 1, n):
        ok = True
        if use_rot:
          tr = 0.0
          for k in range(9):
            tr += rf[i, k] * rf[j, k]
          ok = tr > min_trace
        if ok:
          dp = np.sqrt((p[i, 0] - p[j, 0]) ** 2 + (p[i, 1] - p[j, 1]) ** 2
                       + (p[i, 2] - p[j, 2]) ** 2)
          dq = np.sqrt((q[i, 0] - q[j, 0]) ** 2 + (q[i, 1] - q[j, 1]) ** 2
                       + (q[i, 2] - q[j, 2]) ** 2)
          ok = abs(dp - dq) < distance
        v = 1.0 if ok else 0.0
        out[i, j] = v
        out[j, i] = v


def leading_eigenvector(matrix: np.ndarray, iterations: int = 30) -> np.ndarray:
  """The leading eigenvector of a symmetric non-negative matrix, or of each of a stack of them,
  by power iteration from the constant vector (deterministic), scaled to a maximum of 1.

  Args:
    matrix: (N, N) or (B, N, N).
    iterations: power iterations.

  Returns:
    (N,) or (B, N) in the matrix's float dtype; zeros for a zero matrix.
  """
  m = np.asarray(matrix)
  v = np.ones(m.shape[:-1], m.dtype)
  for _ in range(int(iterations)):
    w = np.einsum("...ij,...j->...i", m, v) if m.ndim == 3 else m @ v
    v = w / np.maximum(np.linalg.norm(w, axis=-1, keepdims=True), 1e-30)
  return v / np.maximum(v.max(axis=-1, keepdims=True), 1e-30)


def select_seeds(points: np.ndarray, scores: np.ndarray, n_seeds: int, nms: float
                 ) -> np.ndarray:
  """Up to `n_seeds` correspondence indices by decreasing score, none within `nms` of a better
  seed's source point (greedy spatial non-maximum suppression); zero scores are never seeds.
  Ties go to the smaller index. (S,) int64."""
  scores = np.asarray(scores)
  order = np.lexsort((np.arange(len(scores)), -scores))
  out = np.empty(max(int(n_seeds), 0), np.int64)
  count = _suppress(np.ascontiguousarray(points, np.float64), scores[order] > 0, order,
                    float(nms) ** 2, out)
  return out[:count]


@nb.njit(cache=True)
def _suppress(pts, positive, order, nms2, out):
  """`select_seeds`' greedy pass over `order`: writes the seeds into `out`, returns their count."""
  count = 0
  for a in range(order.shape[0]):
    if not positive[a] or count >= out.shape[0]:
      break
    i = order[a]
    free = True
    for b in range(count):
      j = out[b]
      d2 = ((pts[j, 0] - pts[i, 0]) ** 2 + (pts[j, 1] - pts[i, 1]) ** 2
            + (pts[j, 2] - pts[i, 2]) ** 2)
      if d2 < nms2:
        free = False
        break
    if free:
      out[count] = i
      count += 1
  return count


def second_order(c: np.ndarray, seeds: np.ndarray) -> np.ndarray:
  """SC2-PCR's second-order compatibility of the seeds' rows: SC2_sj = C_sj (C C)_sj, the number
  of correspondences compatible with both s and j where s and j are compatible, else 0.

  Args:
    c: (N, N) first-order compatibility, 0/1 (`compatibility`).
    seeds: (S,) row indices.

  Returns:
    (S, N) float32, equal to `c[seeds] * (c[seeds] @ c)` (counts are exact in float32), from
    popcounts of ANDed bit rows (`np.bitwise_count`) at the non-zero C_sj only, instead of a
    matrix product.
  """
  bits = pack_rows(np.asarray(c) > 0)
  seeds = np.asarray(seeds, np.int64)
  out = np.zeros((len(seeds), len(c)), np.float32)
  rows, cols = np.nonzero(np.asarray(c)[seeds])
  for lo in range(0, len(rows), SECOND_ORDER_CHUNK):  # bounded temporaries
    r, j = rows[lo:lo + SECOND_ORDER_CHUNK], cols[lo:lo + SECOND_ORDER_CHUNK]
    out[r, j] = np.bitwise_count(bits[seeds[r]] & bits[j]).sum(axis=1)
  return out


# Non-zero entries per step of `second_order` (its temporaries: 8 N / 64 bytes each).
SECOND_ORDER_CHUNK = 65536


def graph_hypotheses(src: np.ndarray, dst: np.ndarray, rotations: np.ndarray | None, *,
                     distance: float, angle_deg: float | None, n_seeds: int, consensus: int,
                     nms: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """One rigid hypothesis per seed of the compatibility graph (module docstring, steps 1-5).

  Args:
    src: (N, 3) source points of the correspondences (centred coordinates are best).
    dst: (N, 3) target points.
    rotations: (N, 3, 3) one-correspondence rotations or None (distance compatibility only).
    distance: compatibility distance d (cloud units).
    angle_deg: rotation agreement bound (degrees) or None.
    n_seeds: at most this many seeds (hypotheses).
    consensus: consensus-set size per seed, besides the seed.
    nms: seed suppression radius (cloud units).

  Returns:
    (R (H, 3, 3), t (H, 3)) float64 hypotheses, the seeds (H,) int64 and the spectral scores
    (N,) float64. H = 0 when no two correspondences are compatible.
  """
  c = compatibility(src, dst, distance, rotations, angle_deg)
  scores = leading_eigenvector(c, SCORE_ITERATIONS)
  seeds = select_seeds(src, scores * (c.sum(axis=1) > 0), n_seeds, nms)
  if len(seeds) == 0:
    return np.zeros((0, 3, 3)), np.zeros((0, 3)), seeds, scores
  sc2 = second_order(c, seeds)           # (S, N), seed rows only
  k = int(min(consensus, len(src) - 1))
  members = np.argsort(-sc2, axis=1, kind="stable")[:, :k]
  sets = np.concatenate([seeds[:, None], members], axis=1)       # (S, k + 1)
  keep = np.concatenate([np.ones((len(seeds), 1), bool),
                         np.take_along_axis(sc2, members, axis=1) > 0], axis=1)
  sets = np.where(keep, sets, seeds[:, None])  # dropped members repeat the seed, weight 0
  sub = c[sets[:, :, None], sets[:, None, :]] * (keep[:, :, None] & keep[:, None, :])
  sub = sub + np.eye(sets.shape[1], dtype=np.float32) * keep[:, :, None]
  weights = leading_eigenvector(sub).astype(np.float64) * keep
  p = np.asarray(src, np.float64)
  q = np.asarray(dst, np.float64)
  rs, ts = host.kabsch_batch(p[sets], q[sets], weights)
  small = keep.sum(axis=1) < 3  # Kabsch needs three points: the seed's own LRF pose instead
  if rotations is not None and small.any():
    r1 = np.asarray(rotations, np.float64)[seeds[small]]
    rs[small] = r1
    ts[small] = q[seeds[small]] - np.einsum("hij,hj->hi", r1, p[seeds[small]])
  return rs, ts, seeds, scores


__all__ = ["compatibility", "graph_hypotheses", "leading_eigenvector", "second_order",
           "select_seeds"]
