"""SHOT local reference frames (Tombari, Salti, Di Stefano 2010), as PCL 1.13 computes them.

For a keypoint p with neighbors q_i within r (offsets pq_i = q_i - p; points that coincide with p
are skipped, as in PCL's `SHOTLocalReferenceFrameEstimation::getLocalRF`):

* C = Σ w_i pq_i pq_iᵀ / Σ w_i with w_i = r - |pq_i| (paper eq. `eq_shot`: about the keypoint,
  not the centroid);
* x = the eigenvector of the largest eigenvalue, z = that of the smallest, y = z × x;
* signs (Bro et al. 2008, PCL): an axis v keeps its sign when #{pq_i · v >= 0} > n/2, flips when
  it is < n/2; on an exact tie the 5 neighbors around the median distance (ranks n/2 - 2 ...
  n/2 + 2 of the distance-sorted list) vote with pq_i · v > 0 and v flips unless >= 3 agree.

Minimum neighbors: 5 points distinct from p (PCL's rule). Invalid (identity, `valid = False`)
also when two eigenvalues of C coincide (relative gap <= `geometry.DEGENERATE_EPS`, e.g. collinear
points; PCL returns an arbitrary frame there) or an input is not finite. SHOT uses every point
of the ball: call it with `k=None` (the registry's default).

Deviations from PCL: the jitted `shot_frames` computes C in float32 (the host fast path
`SPEC.host_frames`, `compute_frames`' default on the CPU, in double as PCL); equal distances in
the tie rule are ordered by cloud index (PCL: the kd-tree's order).

References:
  Tombari, Salti, Di Stefano, "Unique signatures of histograms for local surface description",
  ECCV 2010, section 3. PCL 1.13 `features/impl/shot_lrf.hpp`.
"""

from __future__ import annotations

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.host_path import BallKernel
from lrf_jax.frames.spec import MethodSpec
from lrf_jax.geometry.ops import sanitize
from lrf_jax.search.neighborhoods import Patches

MIN_NEIGHBORS = 5
TIE_VOTERS = 5


def _tie_vote(axis: jax.Array, offsets: jax.Array, use: jax.Array, dist2: jax.Array,
              index: jax.Array, n: jax.Array) -> jax.Array:
  """PCL's tie rule: True to keep `axis` (>= 3 of the 5 median-distance neighbors have dp > 0)."""
  big = jnp.iinfo(jnp.int32).max
  key = jnp.where(use, dist2, jnp.inf)
  idx = jnp.where(use, index.astype(jnp.int32), big)
  slots = jnp.arange(offsets.shape[0], dtype=jnp.int32)
  _, _, order = jax.lax.sort((key, idx, slots), num_keys=2)
  ranks = n // 2 + jnp.arange(-(TIE_VOTERS // 2), TIE_VOTERS // 2 + 1)
  ranks = jnp.clip(ranks, 0, offsets.shape[0] - 1)
  voters = offsets[order[ranks]]
  plus = jnp.sum((voters @ axis) > 0)
  return plus >= TIE_VOTERS // 2 + 1


def _apply(axis: jax.Array, balance: jax.Array, tie_keep: jax.Array) -> jax.Array:
  keep = jnp.where(balance == 0, tie_keep, balance > 0)
  return jnp.where(keep, axis, -axis)


def _axes_and_votes(offsets, mask, radius):
  """Eigen-axes, validity and vote balances of one keypoint (everything but the tie rule)."""
  dist2 = jnp.sum(offsets * offsets, axis=-1)
  use = mask & (dist2 > 0)
  n = jnp.sum(use, dtype=jnp.int32)
  w = jnp.where(use, radius - geometry.safe_norm(offsets), 0.0)
  cov = geometry.weighted_covariance(offsets, w)
  _, evecs, ok = geometry.eigen_frame(cov)
  bx = geometry.majority_balance(evecs[0], offsets, use)
  bz = geometry.majority_balance(evecs[2], offsets, use)
  return evecs[0], evecs[2], bx, bz, use, dist2, n, ok & (n >= MIN_NEIGHBORS)


def _assemble(x, z, ok):
  frame, x_ok = geometry.frame_from_zx(z, x)
  valid = ok & x_ok
  return geometry.identity_where_invalid(frame, valid), valid


def shot_frame(offsets: jax.Array, mask: jax.Array, index: jax.Array,
               radius: jax.Array) -> tuple[jax.Array, jax.Array]:
  """SHOT frame of one keypoint (reference version; `shot_frames` is the fast batched one).

  Args:
    offsets: (K, 3) pq_i (cloud units), finite.
    mask: (K,) bool, real neighbors.
    index: (K,) int cloud indices (tie-breaking only).
    radius: () support radius r.

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool); the identity where invalid.
  """
  x, z, bx, bz, use, dist2, n, ok = _axes_and_votes(offsets, mask, radius)
  x = _apply(x, bx, _tie_vote(x, offsets, use, dist2, index, n))
  z = _apply(z, bz, _tie_vote(z, offsets, use, dist2, index, n))
  return _assemble(x, z, ok)


def shot_frames(patches: Patches) -> tuple[jax.Array, jax.Array]:
  """SHOT frames for a batch of patches (pure, jittable).

  The tie rule needs the neighbors sorted by distance, which costs more than everything else;
  it is evaluated only for the (about 1 % of) keypoints whose vote is tied: up to N / 16 of them
  are gathered and sorted, and all N are sorted in the rare batch that has more ties.

  Args:
    patches: `Patches` (N keypoints); `k=None` (every neighbor) reproduces PCL.

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  patches, finite = sanitize(patches)
  off, idx = patches.offsets, patches.indices
  x, z, bx, bz, use, dist2, n, ok = jax.vmap(_axes_and_votes)(off, patches.mask, patches.radius)
  votes = jax.vmap(lambda a, b, *rest: jnp.stack([_tie_vote(a, *rest), _tie_vote(b, *rest)]))

  def all_rows():
    return votes(x, z, off, use, dist2, idx, n)

  n_batch = off.shape[0]
  cap = min(n_batch, max(8, n_batch // 16))
  tied = (bx == 0) | (bz == 0)

  def tied_rows():
    sel = jnp.nonzero(tied, size=cap, fill_value=0)[0]
    out = votes(x[sel], z[sel], off[sel], use[sel], dist2[sel], idx[sel], n[sel])
    return jnp.zeros((n_batch, 2), bool).at[sel].set(out)

  keep = jax.lax.cond(jnp.sum(tied) > cap, all_rows, tied_rows)
  x = jax.vmap(_apply)(x, bx, keep[:, 0])
  z = jax.vmap(_apply)(z, bz, keep[:, 1])
  frames, valid = jax.vmap(_assemble)(x, z, ok & finite)
  return geometry.identity_where_invalid(frames, valid), valid

# ------------------------------------------------------------------------------ host fast path
# The same frame computed on the host from the engine's ball lists, in float64, one keypoint per
# thread: no padded patch, no sort but for the tied votes. `compute_frames`' default on the CPU.


@nb.njit(inline="always")
def _host_sign(axis, off, d2, ids, n):
  """PCL's sign of `axis` over the n offsets `off` (3, n): +1 keep, -1 flip (`_apply`)."""
  plus = 0
  for t in range(n):
    if off[0, t] * axis[0] + off[1, t] * axis[1] + off[2, t] * axis[2] >= 0.0:
      plus += 1
  balance = 2 * plus - n
  if balance != 0:
    return 1.0 if balance > 0 else -1.0
  # The tie rule: the neighbors around the median distance vote (equal distances by index).
  by_id = np.argsort(ids[:n], kind="mergesort")
  order = by_id[np.argsort(d2[:n][by_id], kind="mergesort")]
  votes = 0
  for v in range(n // 2 - TIE_VOTERS // 2, n // 2 + TIE_VOTERS // 2 + 1):
    j = order[min(max(v, 0), n - 1)]
    if off[0, j] * axis[0] + off[1, j] * axis[1] + off[2, j] * axis[2] > 0.0:
      votes += 1
  return 1.0 if votes >= TIE_VOTERS // 2 + 1 else -1.0


@nb.njit(parallel=True, cache=True)
def _shot_host_kernel(points, centers, ptr, ball, r, eps, frames, valid):
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    off = np.empty((3, stop - start))
    d2 = np.empty(stop - start)
    ids = np.empty(stop - start, np.int64)
    n = 0
    cov = np.zeros((3, 3))
    wsum = 0.0
    for t in range(start, stop):
      j = ball[t]
      dx, dy, dz, dd = hg.offset(points, j, centers[i])
      if dd <= 0.0:
        continue  # the keypoint itself (and exact duplicates of it)
      w = r - np.sqrt(dd)
      off[0, n], off[1, n], off[2, n] = dx, dy, dz
      d2[n] = dd
      ids[n] = j
      n += 1
      wsum += w
      cov[0, 0] += w * dx * dx
      cov[0, 1] += w * dx * dy
      cov[0, 2] += w * dx * dz
      cov[1, 1] += w * dy * dy
      cov[1, 2] += w * dy * dz
      cov[2, 2] += w * dz * dz
    if n < MIN_NEIGHBORS or not wsum > 0.0:
      continue
    cov[1, 0], cov[2, 0], cov[2, 1] = cov[0, 1], cov[0, 2], cov[1, 2]
    evals, evecs = np.linalg.eigh(cov / wsum)  # ascending
    if not hg.full_spectrum_ok(evals, eps):
      continue
    x = evecs[:, 2] * _host_sign(evecs[:, 2], off, d2, ids, n)
    z = evecs[:, 0] * _host_sign(evecs[:, 0], off, d2, ids, n)
    hg.write_frame(frames, valid, i, z, x)


# ------------------------------------------------------------------------------ registry entry

def _shot(patches: Patches, extra: None):
  del extra
  return shot_frames(patches)


SPEC = MethodSpec(
    "shot", _shot, default_k=None,
    host_frames=BallKernel(_shot_host_kernel, ("radius",), (hg.EPS,)),
    description="SHOT (Tombari et al. 2010): (r-d)-weighted covariance about p, majority-vote "
                "signs (PCL)")
