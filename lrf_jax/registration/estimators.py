"""6-DoF pose from correspondences (paper section 3.2.3): the minimal solvers and two RANSACs.

Two RANSAC estimators that differ ONLY in the minimal sample (same inlier threshold, same score =
number of correspondences within the threshold, same final refit, seeded and deterministic,
hypotheses generated and scored at once with `jax.vmap`):

* `lrf_ransac` (the paper's LRF-Net variant, 100 iterations): one correspondence per hypothesis.
  With LRFs F_s, F_t (rows x, y, z) at the points p, q, three point pairs (p, q),
  (p + s x_s, q + s x_t), (p + s y_s, q + s y_t) give the pose by Kabsch (paper figure
  `fig_SVD`): for exactly repeatable frames (F_t = F_s Rᵀ) it is R = F_tᵀ F_s, t = q - R p.
* `ransac_3point` (classic RANSAC, 1000 iterations): three distinct correspondences per
  hypothesis, Kabsch.

The best hypothesis (most inliers; ties: the earliest) is refitted by Kabsch on its inliers
(`refine=True`; skipped when it has fewer than 3) and the inliers are recounted. `register`'s
graph estimator is in `graph.py`, its host versions of these steps in `host.py`.

References:
  Fischler & Bolles, "Random sample consensus", CACM 1981. Kabsch, Acta Cryst. A32, 1976.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from lrf_jax._jax import jax, jit, jnp
import numpy as np

from lrf_jax.geometry.ops import kabsch
from lrf_jax.registration.errors import to_transform


def frame_point_triplets(points: jax.Array, frames: jax.Array, scale: float) -> jax.Array:
  """The three points p, p + s x, p + s y of each (point, frame): (..., 3) -> (..., 3, 3)."""
  return jnp.stack([points, points + scale * frames[..., 0, :],
                    points + scale * frames[..., 1, :]], axis=-2)


def pose_from_correspondence(src_point: Any, src_frame: Any, dst_point: Any, dst_frame: Any, *,
                             scale: float = 1.0) -> tuple[jax.Array, jax.Array]:
  """The pose from ONE correspondence with LRFs: Kabsch on three point pairs (paper fig_SVD).

  Args:
    src_point: (3,) keypoint p on the source.
    src_frame: (3, 3) its LRF, rows x, y, z.
    dst_point: (3,) corresponding keypoint q on the target.
    dst_frame: (3, 3) its LRF.
    scale: s, the length of the frame arms (any positive value; for exact frames the pose does
      not depend on it; the support radius is a natural choice).

  Returns:
    (R (3, 3), t (3,)) with q ≈ R p + t and F_dst ≈ F_src Rᵀ.
  """
  src = frame_point_triplets(jnp.asarray(src_point), jnp.asarray(src_frame), scale)
  dst = frame_point_triplets(jnp.asarray(dst_point), jnp.asarray(dst_frame), scale)
  return kabsch(src, dst)


# ------------------------------------------------------------------------------------------------
# RANSAC
# ------------------------------------------------------------------------------------------------


class RansacResult(NamedTuple):
  """Result of a RANSAC estimator.

  Attributes:
    transform: (4, 4) float64, source -> target (after the refit when `refine`).
    inliers: (M,) bool, correspondences within the threshold under `transform`.
    n_inliers: number of inliers under `transform`.
    best_hypothesis: index of the winning hypothesis.
    hypothesis_inliers: inlier count of the winning hypothesis (before the refit).
  """

  transform: np.ndarray
  inliers: np.ndarray
  n_inliers: int
  best_hypothesis: int
  hypothesis_inliers: int


def _inlier_mask(r: jax.Array, t: jax.Array, src: jax.Array, dst: jax.Array,
                 threshold: float | jax.Array) -> jax.Array:
  res = src @ r.T + t - dst
  return jnp.sum(res * res, axis=-1) <= threshold * threshold


@jit(static_argnames=("refine",))
def _select_and_refine(rs: jax.Array, ts: jax.Array, src: jax.Array, dst: jax.Array,
                       threshold: jax.Array, refine: bool):
  masks = jax.vmap(lambda r, t: _inlier_mask(r, t, src, dst, threshold))(rs, ts)  # (H, M)
  counts = jnp.sum(masks, axis=1)
  best = jnp.argmax(counts)  # first maximum: deterministic
  r, t, mask = rs[best], ts[best], masks[best]
  if refine:
    ok = jnp.sum(mask) >= 3
    w = jnp.where(ok, mask.astype(src.dtype), jnp.ones_like(mask, src.dtype))
    r2, t2 = kabsch(src, dst, w)
    r = jnp.where(ok, r2, r)
    t = jnp.where(ok, t2, t)
    mask = _inlier_mask(r, t, src, dst, threshold)
  return r, t, mask, best, counts[best]


def _check_correspondences(src: Any, dst: Any, threshold: float,
                           iterations: int) -> tuple[np.ndarray, np.ndarray]:
  s = np.asarray(src, np.float64)
  d = np.asarray(dst, np.float64)
  if s.ndim != 2 or s.shape[1] != 3 or d.shape != s.shape:
    raise ValueError(f"correspondences: expected source and target points of the same shape "
                     f"(M, 3), got {s.shape} and {d.shape}")
  if not (np.all(np.isfinite(s)) and np.all(np.isfinite(d))):
    raise ValueError("correspondences: expected finite coordinates, found NaN or inf")
  if not (np.isfinite(threshold) and threshold > 0):
    raise ValueError(f"inlier_threshold: expected a positive distance, got {threshold!r}")
  if int(iterations) < 1 or int(iterations) != iterations:
    raise ValueError(f"iterations: expected a positive integer, got {iterations!r}")
  return s, d


def finish_result(r: Any, t: Any, mask: Any, best: Any, count: Any) -> RansacResult:
  """A `RansacResult` from an estimator's best rotation (3, 3), translation (3,), inlier mask
  (n,), best hypothesis index and inlier count."""
  mask = np.asarray(mask)
  return RansacResult(to_transform(np.asarray(r), np.asarray(t)), mask, int(mask.sum()),
                      int(best), int(count))


def centred(s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """float32 coordinates about the source/target centroids (precision away from the origin)."""
  cs, cd = s.mean(axis=0), d.mean(axis=0)
  return ((s - cs).astype(np.float32), (d - cd).astype(np.float32), cs, cd)


def uncentre(r: Any, t: Any, cs: np.ndarray, cd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """The pose (r (3, 3), t (3,)) found on `centred` coordinates, in the original ones: the
  translation moved back by the centroids `cs`, `cd` (float64)."""
  r = np.asarray(r, np.float64)
  return r, np.asarray(t, np.float64) + cd - r @ cs


def lrf_ransac(src_points: Any, dst_points: Any, src_frames: Any, dst_frames: Any, *,
               inlier_threshold: float, scale: float, iterations: int = 100, seed: int = 0,
               valid: Any = None, refine: bool = True) -> RansacResult:
  """RANSAC with ONE correspondence per hypothesis, the pose from the two LRFs (LRF-Net paper).

  Args:
    src_points: (M, 3) source keypoints of the correspondences.
    dst_points: (M, 3) their target keypoints.
    src_frames: (M, 3, 3) source LRFs, rows x, y, z.
    dst_frames: (M, 3, 3) target LRFs.
    inlier_threshold: a correspondence is an inlier when |R p + t - q| <= this (cloud units).
    scale: frame arm length s of `pose_from_correspondence` (e.g. the support radius).
    iterations: hypotheses (the paper: 100).
    seed: sampling seed (`jax.random.key(seed)`); the same seed gives the same result.
    valid: (M,) bool, correspondences whose two frames are valid (only those are sampled;
      all count for the score). None: all.
    refine: refit the best hypothesis by Kabsch on its inliers.

  Returns:
    `RansacResult` (transform source -> target).

  Raises:
    ValueError: mismatched shapes, non-finite input, a bad threshold/iteration count, or no
      valid correspondence.
  """
  s, d = _check_correspondences(src_points, dst_points, inlier_threshold, iterations)
  m = s.shape[0]
  fs = np.asarray(src_frames, np.float64)
  fd = np.asarray(dst_frames, np.float64)
  if fs.shape != (m, 3, 3) or fd.shape != (m, 3, 3):
    raise ValueError(f"frames: expected source and target frames of shape ({m}, 3, 3), got "
                     f"{fs.shape} and {fd.shape}")
  v = np.ones(m, bool) if valid is None else np.asarray(valid, bool).reshape(-1)
  if v.shape != (m,):
    raise ValueError(f"valid: expected shape ({m},), got {v.shape}")
  v = v & np.all(np.isfinite(fs), axis=(1, 2)) & np.all(np.isfinite(fd), axis=(1, 2))
  if not v.any():
    raise ValueError("correspondences: none has two valid frames; cannot form a hypothesis")
  if not (np.isfinite(scale) and scale > 0):
    raise ValueError(f"scale: expected a positive length, got {scale!r}")
  src, dst, cs, cd = centred(s, d)
  pick = jax.random.choice(jax.random.key(seed), jnp.asarray(np.flatnonzero(v)),
                           (int(iterations),), replace=True)
  rs, ts = _lrf_hypotheses(src[pick], jnp.asarray(fs[pick], jnp.float32), dst[pick],
                           jnp.asarray(fd[pick], jnp.float32), float(scale))
  r, t, mask, best, count = _select_and_refine(rs, ts, src, dst, float(inlier_threshold), refine)
  r, t = uncentre(r, t, cs, cd)
  return finish_result(r, t, mask, best, count)


@jit
def _lrf_hypotheses(ps, fs, qs, fd, scale):
  return jax.vmap(lambda p, f, q, g: pose_from_correspondence(p, f, q, g, scale=scale))(
      ps, fs, qs, fd)


@jit
def _kabsch_batch(a: jax.Array, b: jax.Array):
  return jax.vmap(kabsch)(a, b)


def ransac_3point(src_points: Any, dst_points: Any, *, inlier_threshold: float,
                  iterations: int = 1000, seed: int = 0, refine: bool = True) -> RansacResult:
  """Classic RANSAC: three distinct correspondences per hypothesis, Kabsch.

  Same threshold, score and refit as `lrf_ransac`; only the sample differs.

  Args:
    src_points: (M, 3) source keypoints, M >= 3.
    dst_points: (M, 3) target keypoints.
    inlier_threshold: inlier distance (cloud units).
    iterations: hypotheses (the paper: 1000).
    seed: sampling seed.
    refine: refit the best hypothesis on its inliers.

  Returns:
    `RansacResult` (transform source -> target).

  Raises:
    ValueError: mismatched shapes, fewer than 3 correspondences, bad threshold or iterations.
  """
  s, d = _check_correspondences(src_points, dst_points, inlier_threshold, iterations)
  m = s.shape[0]
  if m < 3:
    raise ValueError(f"correspondences: 3-point RANSAC needs at least 3, got {m}")
  src, dst, cs, cd = centred(s, d)
  samples = triples(m, iterations, seed)
  rs, ts = _kabsch_batch(src[samples], dst[samples])
  r, t, mask, best, count = _select_and_refine(rs, ts, src, dst, float(inlier_threshold), refine)
  r, t = uncentre(r, t, cs, cd)
  return finish_result(r, t, mask, best, count)


def triples(m: int, iterations: int, seed: int) -> jax.Array:
  """(iterations, 3) seeded triples of distinct correspondence indices."""
  keys = jax.random.split(jax.random.key(seed), int(iterations))
  return jax.vmap(lambda k: jax.random.choice(k, m, (3,), replace=False))(keys)
