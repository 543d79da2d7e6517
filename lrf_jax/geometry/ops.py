"""Shared, pure geometry for every LRF method.

All functions but `sanitize` (the input hygiene every method applies to a whole `Patches` batch
first) are written for one keypoint and are meant to be `jax.vmap`-ed over keypoints. They
never return NaN: degenerate inputs are handled with the "double where" idiom (the unsafe branch is
fed a harmless value so that neither the value nor its gradient can become NaN), and callers get a
boolean flag telling them whether the result is meaningful.

Conventions: a frame is a (3, 3) array whose *rows* are the x, y, z axes;
it maps world vectors into the LRF; right-handed (y = z × x, det = +1).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lrf_jax._jax import jax, jnp

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray, Patches

  Array = jax.Array  # annotations only (they are strings here): no JAX import for it

# Relative tolerance below which a vector or an eigenvalue gap counts as degenerate.
DEGENERATE_EPS = 1e-6


def safe_norm(v: AnyArray, axis: int = -1, keepdims: bool = False) -> Array:
  """Euclidean norm whose gradient is finite (zero) at the zero vector.

  Args:
    v: (..., 3) vectors.
    axis: axis to reduce.
    keepdims: keep the reduced axis.

  Returns:
    (...) norms; exactly 0 where `v` is 0, with a zero (not NaN) gradient there.
  """
  sq = jnp.sum(v * v, axis=axis, keepdims=keepdims)
  positive = sq > 0
  return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def safe_normalize(v: Array, eps: float = 0.0) -> tuple[Array, Array]:
  """Unit vector along `v` and whether it was well defined.

  Args:
    v: (..., 3) vector.
    eps: norms `<= eps` count as degenerate.

  Returns:
    (unit, ok): `unit` (..., 3) is `v / |v|` where `ok`, else the zero vector; `ok` (...) bool.
  """
  n = safe_norm(v, keepdims=True)
  ok = n > eps
  unit = jnp.where(ok, v / jnp.where(ok, n, 1.0), 0.0)
  return unit, ok[..., 0]


def frame_from_zx(z: Array, x_raw: Array, eps: float = 0.0) -> tuple[Array, Array]:
  """Right-handed frame with rows (x, y = z × x, z) from a unit z and an unnormalised x.

  `x_raw` is first projected onto the plane orthogonal to `z` (a no-op for the methods that already
  sum tangent-plane projections) and then normalised.

  Args:
    z: (3,) unit z-axis.
    x_raw: (3,) vector giving the x direction.
    eps: an x whose tangent part has norm `<= eps` is degenerate.

  Returns:
    (frame, ok): frame (3, 3) with rows x, y, z; ok is False when the x direction is undefined.
  """
  x_t = x_raw - jnp.dot(x_raw, z) * z
  x, ok = safe_normalize(x_t, eps)
  y = jnp.cross(z, x)
  return jnp.stack([x, y, z]), ok


def tangent_projection(offsets: AnyArray, z: Array) -> AnyArray:
  """Projection of neighbor offsets on the tangent plane of `z` (paper eq. `eq_vector_x`).

  Args:
    offsets: (K, 3) vectors pq_i = q_i - p.
    z: (3,) unit normal.

  Returns:
    (K, 3) v_i = pq_i - (pq_i · z) z.
  """
  return offsets - (offsets @ z)[:, None] * z[None, :]


def weighted_covariance(offsets: Array, weights: Array, center: Array | None = None) -> Array:
  """Σ w_i (q_i - c)(q_i - c)ᵀ / Σ w_i.

  Args:
    offsets: (K, 3) points (usually relative to the keypoint).
    weights: (K,) non-negative weights; padded entries must carry weight 0.
    center: (3,) the point the covariance is taken about; the keypoint (origin) when None.

  Returns:
    (3, 3) symmetric matrix (zeros when all weights are 0).
  """
  d = offsets if center is None else offsets - center
  wsum = jnp.sum(weights)
  c = jnp.einsum("k,ki,kj->ij", weights, d, d)
  return c / jnp.where(wsum > 0, wsum, 1.0)


def smallest_eigvec(cov: Array) -> tuple[Array, Array]:
  """Eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix, and whether it is unique.

  The smallest eigenvector is ill-defined when the two smallest eigenvalues (nearly) coincide
  relative to the largest one: collinear points, a single repeated point, an isotropic blob.

  Args:
    cov: (3, 3) symmetric positive semi-definite matrix.

  Returns:
    (v, ok): v (3,) unit vector (sign arbitrary); ok is False for a degenerate spectrum.
  """
  evals, evecs = jnp.linalg.eigh(cov)
  scale = jnp.maximum(evals[2], 0.0)
  ok = (evals[1] - evals[0]) > DEGENERATE_EPS * scale
  ok = ok & (scale > 0) & jnp.all(jnp.isfinite(evals))
  return evecs[:, 0], ok


def eigen_frame(cov: Array) -> tuple[Array, Array, Array]:
  """Eigenvectors of a symmetric 3x3 matrix, largest eigenvalue first.

  Args:
    cov: (3, 3) symmetric matrix.

  Returns:
    (evals, evecs, ok): evals (3,) descending; evecs (3, 3) whose *rows* are the matching unit
    eigenvectors (signs arbitrary); ok False when two eigenvalues coincide (relative to the largest).
  """
  evals, evecs = jnp.linalg.eigh(cov)
  evals = evals[::-1]
  evecs = evecs[:, ::-1].T
  scale = jnp.maximum(jnp.abs(evals[0]), 0.0)
  gap = jnp.minimum(evals[0] - evals[1], evals[1] - evals[2])
  ok = (gap > DEGENERATE_EPS * scale) & (scale > 0) & jnp.all(jnp.isfinite(evals))
  return evals, evecs, ok


def disambiguate_sign(axis: Array, offsets: Array, weights: Array) -> Array:
  """Flip `axis` so that the weighted majority of offsets lies on its positive side.

  Returns `axis` if Σ w_i (offsets_i · axis) >= 0, else `-axis` (ties keep the sign).

  Args:
    axis: (3,) unit vector.
    offsets: (K, 3).
    weights: (K,) weights (0 for padding).

  Returns:
    (3,) the oriented axis.
  """
  s = jnp.sum(weights * (offsets @ axis))
  return jnp.where(s >= 0, axis, -axis)


def toldi_normal(cov: Array, mean: Array, count: Array, min_count: int = 3) -> tuple[Array, Array]:
  """The TOLDI z-axis from the statistics of the neighbors within r/3 (Yang et al. 2017).

  z is the eigenvector of the smallest eigenvalue of the covariance of the r/3 neighbors about
  their centroid, oriented so that Σ_i (p - q_i)·z >= 0, i.e. `mean · z <= 0` where `mean` is the
  centroid of the offsets q_i - p (the original C++ rule; LRF-Net keeps it).

  Args:
    cov: (3, 3) covariance of the r/3 neighbor offsets about their centroid.
    mean: (3,) centroid of the r/3 neighbor offsets q_i - p.
    count: () number of neighbors within r/3 (keypoint included).
    min_count: fewer neighbors than this make the normal invalid.

  Returns:
    (z, ok): z (3,) unit z-axis; ok False for too few neighbors or a degenerate spectrum.
  """
  finite = jnp.all(jnp.isfinite(cov)) & jnp.all(jnp.isfinite(mean))
  cov = jnp.where(finite, cov, jnp.eye(3, dtype=cov.dtype))
  mean = jnp.where(finite, mean, 0.0)
  z, ok = smallest_eigvec(cov)
  z = jnp.where(jnp.dot(mean, z) <= 0, z, -z)
  return z, ok & finite & (count >= min_count)


def kabsch(src: Array, dst: Array, weights: Array | None = None) -> tuple[Array, Array]:
  """Least-squares rigid transform with dst ≈ R src + t (Kabsch / Umeyama without scale).

  Args:
    src: (n, 3) points.
    dst: (n, 3) corresponding points.
    weights: (n,) optional non-negative weights.

  Returns:
    (R, t): R (3, 3) rotation with det +1, t (3,).
  """
  w = jnp.ones(src.shape[0], src.dtype) if weights is None else weights
  w = w / jnp.sum(w)
  cs = w @ src
  cd = w @ dst
  h = (src - cs).T @ ((dst - cd) * w[:, None])
  u, _, vt = jnp.linalg.svd(h)
  d = jnp.sign(jnp.linalg.det(vt.T @ u.T))
  d = jnp.where(d == 0, 1.0, d)
  r = vt.T @ jnp.diag(jnp.array([1.0, 1.0, d], src.dtype)) @ u.T
  return r, cd - r @ cs


def identity_where_invalid(frames: Array, valid: Array) -> Array:
  """Replace invalid frames by the identity (invalid frames are flagged, never NaN).

  Args:
    frames: (..., 3, 3).
    valid: (...) bool.

  Returns:
    (..., 3, 3) frames with identity where `valid` is False.
  """
  eye = jnp.eye(3, dtype=frames.dtype)
  return jnp.where(valid[..., None, None], frames, eye)


# ------------------------------------------------------------------------------------------------
# Helpers shared by the hand-crafted LRFs (frames/mian.py, shot.py, rops.py, board.py, flare.py,
# ps.py, gframes.py). All are for one keypoint; vmap them over keypoints.
# ------------------------------------------------------------------------------------------------


def finite_or_zero(x: AnyArray) -> Array:
  """`x` with non-finite entries replaced by 0 (safe to feed to arithmetic under jax_debug_nans).

  Args:
    x: any array.

  Returns:
    Same shape and dtype; 0 where `x` was NaN or ±inf.
  """
  return jnp.where(jnp.isfinite(x), x, jnp.zeros((), x.dtype))


def all_finite_rows(v: Array) -> Array:
  """Whether every component of each row is finite: (..., 3) -> (...) bool."""
  return jnp.all(jnp.isfinite(v), axis=-1)


def centered_covariance(offsets: Array, weights: Array) -> tuple[Array, Array]:
  """Weighted covariance of points about their weighted centroid (a least-squares plane fit).

  Args:
    offsets: (K, 3) points (usually relative to the keypoint).
    weights: (K,) non-negative weights; 0 for padding (use the mask as 0/1 weights).

  Returns:
    (cov, mean): cov (3, 3) = Σ w_i (q_i - m)(q_i - m)ᵀ / Σ w_i; mean (3,) = m (zeros when all
    weights are 0).
  """
  wsum = jnp.sum(weights)
  mean = (weights @ offsets) / jnp.where(wsum > 0, wsum, 1.0)
  return weighted_covariance(offsets, weights, center=mean), mean


def orient_like(axis: Array, reference: Array) -> Array:
  """Flip `axis` so that `axis · reference >= 0` (ties and a zero reference keep the sign).

  The rule of Mian et al. (2010) for the z-axis, and of PCL's `flipNormalTowardsNormalsMean`
  (FLARE) and BOARD's `normalDisambiguation` with `reference` = the mean of the neighbors' normals.

  Args:
    axis: (3,) unit vector.
    reference: (3,) vector (need not be unit).

  Returns:
    (3,) ±axis.
  """
  return jnp.where(jnp.dot(axis, reference) >= 0, axis, -axis)


def majority_balance(axis: Array, offsets: Array, mask: Array) -> Array:
  """The count-based sign vote of Bro et al. (2008) as used by SHOT: #{dp >= 0} - #{dp < 0}.

  Args:
    axis: (3,) unit vector.
    offsets: (K, 3) neighbor offsets pq_i.
    mask: (K,) bool, the neighbors that vote.

  Returns:
    () int32 balance 2·#{i: pq_i·axis >= 0} - n; the axis is kept for a positive balance and
    flipped for a negative one (SHOT's tie rule for 0 lives in frames/shot.py).
  """
  dp = offsets @ axis
  plus = jnp.sum(mask & (dp >= 0), dtype=jnp.int32)
  return 2 * plus - jnp.sum(mask, dtype=jnp.int32)


def lexicographic_argmax(score: Array, candidates: Array, dist2: Array,
                         index: Array) -> tuple[Array, Array]:
  """Slot of the candidate with the largest score; ties go to the nearer, then lower-index point.

  PCL's BOARD and FLARE scan the radius-search result (sorted by distance) and keep the first
  strict improvement, so a tie goes to the nearer point; breaking the remaining ties by the cloud
  index makes the choice independent of slot order and padding.

  Args:
    score: (K,) scores (finite where `candidates`).
    candidates: (K,) bool, the slots that may be chosen.
    dist2: (K,) squared distances to the keypoint.
    index: (K,) integer cloud indices of the slots.

  Returns:
    (slot, found): slot () int32; found () bool, False when there is no candidate.
  """
  s = jnp.where(candidates, score, -jnp.inf)
  best = jnp.max(s)
  c1 = candidates & (s == best)
  d = jnp.where(c1, dist2, jnp.inf)
  c2 = c1 & (d == jnp.min(d))
  big = jnp.iinfo(jnp.int32).max
  idx = jnp.where(c2, index.astype(jnp.int32), big)
  c3 = c2 & (idx == jnp.min(idx))
  slot = jnp.argmax(c3).astype(jnp.int32)
  return slot, jnp.any(candidates)


def directed_tangent_axis(z: Array, offset: Array, eps: float = 0.0) -> tuple[Array, Array]:
  """Unit projection of one offset on the tangent plane of `z` (PCL's `directedOrthogonalAxis`).

  Args:
    z: (3,) unit normal.
    offset: (3,) q - p.
    eps: a projection of norm `<= eps` is degenerate.

  Returns:
    (x, ok): x (3,) unit vector orthogonal to z; ok False when the projection vanishes.
  """
  return safe_normalize(offset - jnp.dot(offset, z) * z, eps)


def sanitize(patches: Patches) -> tuple[Patches, jax.Array]:
  """Zero out non-finite inputs so nothing downstream sees NaN; report which keypoints had any.

  Returns:
    (patches, finite): finite (N,) is False where a keypoint's offsets or statistics were not finite.
  """
  off_ok = jnp.all(jnp.isfinite(patches.offsets), axis=-1)  # (N, K)
  finite = (jnp.all(off_ok | ~patches.mask, axis=-1)
            & jnp.all(jnp.isfinite(patches.z_cov), axis=(-1, -2))
            & jnp.all(jnp.isfinite(patches.z_mean), axis=-1)
            & jnp.isfinite(patches.radius) & (patches.radius > 0))
  patches = patches._replace(
      offsets=jnp.where(off_ok[..., None], patches.offsets, 0.0),
      mask=patches.mask & off_ok,
      z_cov=jnp.where(jnp.isfinite(patches.z_cov), patches.z_cov, 0.0),
      z_mean=jnp.where(jnp.isfinite(patches.z_mean), patches.z_mean, 0.0),
      radius=jnp.where(jnp.isfinite(patches.radius) & (patches.radius > 0), patches.radius, 1.0),
  )
  return patches, finite
