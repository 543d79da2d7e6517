"""Host (numpy, numba) versions of `register`'s hypothesis and scoring steps.

`lrf_jax.registration.lrf_ransac` and `ransac_3point` generate and score their hypotheses as
jitted `jax.vmap` programs. `register` runs the same computations on the host instead: a fresh
process (the `lrf-register` command) would otherwise trace, lower and load four JAX programs for
a few milliseconds of arithmetic. The results agree with the jitted ones up to float32 rounding
(the host works in float64 on the same float32 centred coordinates): poses to about 1e-5, inlier
counts except for correspondences within that distance of the threshold.

* `kabsch_batch`: the least-squares rigid transform of each of H point sets (geometry.kabsch).
* `lrf_hypotheses`: one pose per correspondence from its two LRFs (paper figure `fig_SVD`).
* `count_inliers`: for each of H poses, the correspondences within the threshold.
* `select_and_refine`: the refit of one pose on its inliers, and its inlier mask.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax import compilation_cache

compilation_cache.announce_compiles()  # numba cache keys (lrf_jax.kernel_cache), the compile note


def kabsch_batch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
  """Least-squares rigid transforms with dst[h] ≈ R[h] src[h] + t[h] (Kabsch, no scale).

  Args:
    src: (H, n, 3) point sets.
    dst: (H, n, 3) corresponding points.
    weights: (H, n) optional non-negative weights, each row with a positive sum.

  Returns:
    (R (H, 3, 3) float64 rotations with det +1, t (H, 3) float64); a reflection of the SVD is
    flipped on its smallest singular direction, as `lrf_jax.geometry.ops.kabsch` does.
  """
  a = np.asarray(src, np.float64)
  b = np.asarray(dst, np.float64)
  w = np.ones(a.shape[:2]) if weights is None else np.asarray(weights, np.float64)
  w = w / w.sum(axis=1, keepdims=True)
  ca = np.einsum("hn,hni->hi", w, a)
  cb = np.einsum("hn,hni->hi", w, b)
  h = np.einsum("hni,hnj->hij", a - ca[:, None], (b - cb[:, None]) * w[..., None])
  r = proper_rotation(h)
  return r, cb - np.einsum("hij,hj->hi", r, ca)


def proper_rotation(h: np.ndarray) -> np.ndarray:
  """Kabsch's rotation from a cross-covariance: R = V diag(1, 1, d) Uᵀ for h = U S Vᵀ, d the sign
  of det(V Uᵀ) (1 where it is 0), the rotation (det +1) that maximises trace(R h); the one
  host (float64) form, used by `kabsch_batch` and point-to-point ICP
  (`lrf_jax.geometry.ops.kabsch` is its jitted float32 counterpart).

  Args:
    h: (..., 3, 3) sum of (a - ca)(b - cb)ᵀ over the pairs (weighted or not).

  Returns:
    (..., 3, 3) float64 rotations.
  """
  u, _, vt = np.linalg.svd(np.asarray(h, np.float64))
  v = np.swapaxes(vt, -1, -2)
  d = np.sign(np.linalg.det(v @ np.swapaxes(u, -1, -2)))
  v[..., :, 2] *= np.where(d == 0, 1.0, d)[..., None]
  return v @ np.swapaxes(u, -1, -2)


def lrf_hypotheses(src: np.ndarray, src_frames: np.ndarray, dst: np.ndarray,
                   dst_frames: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
  """One pose per correspondence from its LRFs (`registration.pose_from_correspondence`).

  Args:
    src: (H, 3) source points; src_frames (H, 3, 3) their LRFs, rows x, y, z.
    dst: (H, 3) target points; dst_frames (H, 3, 3) theirs.
    scale: frame arm length s (cloud units): Kabsch on p, p + s x, p + s y and q, q + s x',
      q + s y'.

  Returns:
    (R (H, 3, 3), t (H, 3)) float64, q ≈ R p + t.
  """
  p = np.asarray(src, np.float64)[:, None, :]
  q = np.asarray(dst, np.float64)[:, None, :]
  fs = np.asarray(src_frames, np.float64)
  fd = np.asarray(dst_frames, np.float64)
  a = np.concatenate([p, p + scale * fs[:, :2]], axis=1)  # (H, 3, 3): p, p + s x, p + s y
  b = np.concatenate([q, q + scale * fd[:, :2]], axis=1)
  return kabsch_batch(a, b)


@nb.njit(parallel=True, cache=True)
def _inliers(rs, ts, src, dst, t2, masks):
  """Per pose h, the count of the m with |R_h src[m] + t_h - dst[m]|^2 <= t2; for the first
  masks.shape[0] poses also which m (into masks[h])."""
  out = np.zeros(rs.shape[0], np.int64)
  for h in nb.prange(rs.shape[0]):
    r = rs[h]
    c = 0
    for m in range(src.shape[0]):
      x, y, z = src[m, 0], src[m, 1], src[m, 2]
      ex = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + ts[h, 0] - dst[m, 0]
      ey = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + ts[h, 1] - dst[m, 1]
      ez = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + ts[h, 2] - dst[m, 2]
      inside = (ex * ex + ey * ey + ez * ez) <= t2
      c += inside
      if h < masks.shape[0]:
        masks[h, m] = inside
    out[h] = c
  return out


def _run_inliers(rotations, translations, src, dst, threshold, n_masks):
  masks = np.zeros((n_masks, len(src)), bool)
  counts = _inliers(np.ascontiguousarray(rotations, np.float64).reshape(-1, 3, 3),
                    np.ascontiguousarray(translations, np.float64).reshape(-1, 3),
                    np.ascontiguousarray(src, np.float64), np.ascontiguousarray(dst, np.float64),
                    float(threshold) ** 2, masks)
  return counts, masks


def count_inliers(rotations: np.ndarray, translations: np.ndarray, src: np.ndarray,
                  dst: np.ndarray, threshold: float) -> np.ndarray:
  """Inliers of each pose: (H,) int64 counts of the m with |R src[m] + t - dst[m]| <= threshold.

  Args:
    rotations: (H, 3, 3); translations: (H, 3).
    src, dst: (M, 3) corresponding points.
    threshold: inlier distance (cloud units).
  """
  return _run_inliers(rotations, translations, src, dst, threshold, 0)[0]


def inlier_mask(rotation: np.ndarray, translation: np.ndarray, src: np.ndarray, dst: np.ndarray,
                threshold: float) -> np.ndarray:
  """(M,) bool: |R src + t - dst| <= threshold for one pose (R (3, 3), t (3,)), the test
  `count_inliers` counts."""
  return _run_inliers(rotation, translation, src, dst, threshold, 1)[1][0]


def inlier_masks(rotations: np.ndarray, translations: np.ndarray, src: np.ndarray,
                 dst: np.ndarray, threshold: float) -> np.ndarray:
  """(H, M) bool: the `count_inliers` test of each of H poses, as masks."""
  return _run_inliers(rotations, translations, src, dst, threshold, len(rotations))[1]


def select_and_refine(rotation: np.ndarray, translation: np.ndarray, src: np.ndarray,
                      dst: np.ndarray, threshold: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """A pose refitted by Kabsch on its inliers (kept when it has fewer than 3), with the inlier
  mask under the result: (R (3, 3), t (3,), mask (M,) bool)."""
  r = np.asarray(rotation, np.float64)
  t = np.asarray(translation, np.float64)
  mask = inlier_mask(r, t, src, dst, threshold)
  if mask.sum() >= 3:
    rr, tt = kabsch_batch(np.asarray(src)[None], np.asarray(dst)[None],
                          mask.astype(np.float64)[None])
    r, t = rr[0], tt[0]
    mask = inlier_mask(r, t, src, dst, threshold)
  return r, t, mask
