"""RoPS (Guo, Sohel, Bennamoun, Lu, Wan 2013) on an external LRF, as PCL 1.13 `ROPSEstimation`.

The local surface (every point within r, keypoint included, in the LRF) is rotated about each LRF
axis by theta = 22.5, 45 and 67.5 deg (PCL: `number_of_rotations = 3`, step 90 / (3 + 1)). Each
rotated cloud is projected on the xy, xz and yz planes; each projection is binned into a 5 x 5
distribution matrix D over the rotated cloud's axis-aligned bounding box (counts / points); and D
is summarised by the central moments mu_11, mu_21, mu_12, mu_22 (bin indices 1..5 about their
mean) and the Shannon entropy -sum D log D.

Layout (135 = 3 axes x 3 rotations x 3 planes x 5 statistics), index
= ((axis * 3 + rotation) * 3 + plane) * 5 + statistic, with axis (x, y, z), rotation (22.5, 45,
67.5 deg), plane (xy, xz, yz), statistic (mu_11, mu_21, mu_12, mu_22, entropy). The vector is
L1-normalised (PCL; the paper does not normalise).

Only the LRF of RoPS needs the mesh (`lrf_jax.frames.rops`); the descriptor, in PCL as here,
uses the points within r. Deviation from the paper: PCL (and we) skip the paper's mesh
resampling. Invalid (zeros, `valid = False`): an invalid frame or fewer than 5 points in the ball
(PCL has no minimum; with fewer points the statistics are meaningless). A projection whose box
has zero extent along a coordinate puts every point into bin 0 of that coordinate (PCL divides
by zero there).

References:
  Guo, Sohel, Bennamoun, Lu, Wan, "Rotational projection statistics for 3D local surface
  description and object recognition", IJCV 105(1), 2013, section 4. PCL 1.13
  `features/impl/rops_estimation.hpp` (`computeFeature`, `rotateCloud`, `getDistributionMatrix`,
  `computeCentralMoments`).
"""

from __future__ import annotations

from lrf_jax._jax import jax, jnp
import numpy as np

from lrf_jax.descriptors.common import local_coordinates, sanitize_inputs
from lrf_jax.search.neighborhoods import Patches

N_BINS = 5
N_ROTATIONS = 3
DIM = 3 * N_ROTATIONS * 3 * 5  # 135
MIN_POINTS = 5
_PLANES = ((0, 1), (0, 2), (1, 2))


def rotation_matrices(n_rotations: int = N_ROTATIONS) -> np.ndarray:
  """The (3 * n_rotations, 3, 3) float32 rotations of PCL's `rotateCloud`, axis-major.

  Rodrigues' formula about the unit axes, angles step, 2 step, ... < 90 deg with
  step = 90 / (n_rotations + 1), evaluated in float32 like PCL.
  """
  step = np.float32(90.0) / np.float32(n_rotations + 1)
  rad = np.float32(np.pi) / np.float32(180.0)
  out = []
  for axis in np.eye(3, dtype=np.float32):
    x, y, z = axis
    theta = step
    while theta < np.float32(90.0):
      c, s = np.cos(theta * rad, dtype=np.float32), np.sin(theta * rad, dtype=np.float32)
      out.append(np.array(
          [[c + (1 - c) * x * x, (1 - c) * x * y - s * z, (1 - c) * x * z + s * y],
           [(1 - c) * y * x + s * z, c + (1 - c) * y * y, (1 - c) * y * z - s * x],
           [(1 - c) * z * x - s * y, (1 - c) * z * y + s * x, c + (1 - c) * z * z]],
          np.float32))
      theta = np.float32(theta + step)
  return np.stack(out)


def _moments(dist: jax.Array) -> jax.Array:
  """(mu_11, mu_21, mu_12, mu_22, entropy) of a (B, B) distribution matrix (PCL's order)."""
  idx = jnp.arange(1, N_BINS + 1, dtype=dist.dtype)
  mi = jnp.sum(idx[:, None] * dist)
  mj = jnp.sum(idx[None, :] * dist)
  fi = (idx - mi)[:, None]
  fj = (idx - mj)[None, :]
  pos = dist > 0
  ent = -jnp.sum(jnp.where(pos, dist * jnp.log(jnp.where(pos, dist, 1.0)), 0.0))
  return jnp.stack([jnp.sum(fi * fj * dist), jnp.sum(fi * fi * fj * dist),
                    jnp.sum(fi * fj * fj * dist), jnp.sum(fi * fi * fj * fj * dist), ent])


def _rops_one(local: jax.Array, mask: jax.Array, rotations: jax.Array) -> jax.Array:
  """Unnormalised RoPS vector of one keypoint: local (K, 3), mask (K,) -> (135,)."""
  rotated = jnp.einsum("rij,kj->rki", rotations, local)  # (R, K, 3)
  big = jnp.finfo(local.dtype).max
  lo = jnp.min(jnp.where(mask[None, :, None], rotated, big), axis=1)   # (R, 3)
  hi = jnp.max(jnp.where(mask[None, :, None], rotated, -big), axis=1)
  length = (hi - lo) / N_BINS
  pos = length > 0
  ratio = (rotated - lo[:, None, :]) / jnp.where(pos, length, 1.0)[:, None, :]
  ratio = jnp.where(pos[:, None, :] & mask[None, :, None], ratio, 0.0)
  cell = jnp.clip(jnp.floor(ratio).astype(jnp.int32), 0, N_BINS - 1)  # PCL: bin B -> B - 1
  n = jnp.maximum(jnp.sum(mask), 1).astype(local.dtype)
  n_rot = rotations.shape[0]
  feats = []
  for a, b in _PLANES:
    flat = (jnp.arange(n_rot)[:, None] * N_BINS * N_BINS + cell[:, :, a] * N_BINS + cell[:, :, b])
    counts = jnp.zeros(n_rot * N_BINS * N_BINS, local.dtype).at[flat.reshape(-1)].add(
        jnp.tile(mask.astype(local.dtype), n_rot))
    dist = counts.reshape(n_rot, N_BINS, N_BINS) / n
    feats.append(jax.vmap(_moments)(dist))  # (R, 5)
  return jnp.stack(feats, axis=1).reshape(-1)  # (R, plane, 5) flattened, R axis-major


def rops_descriptors(patches: Patches, frames: jax.Array,
                     valid: jax.Array) -> tuple[jax.Array, jax.Array]:
  """RoPS descriptors of a batch (pure, jittable).

  Args:
    patches: `Patches` with every neighbor within r (`k=None`).
    frames: (N, 3, 3) LRFs, rows x, y, z, from any method.
    valid: (N,) bool validity of the frames.

  Returns:
    (descriptors (N, 135) float32, L1 norm 1, zeros where invalid; valid (N,) bool).
  """
  offsets, mask, frames, ok = sanitize_inputs(patches, frames, valid)
  local = local_coordinates(offsets, frames)
  rotations = jnp.asarray(rotation_matrices(), local.dtype)
  feat = jax.vmap(_rops_one, in_axes=(0, 0, None))(local, mask, rotations)
  norm = jnp.sum(jnp.abs(feat), axis=-1)
  eps = jnp.finfo(feat.dtype).eps
  feat = feat / jnp.where(norm < eps, 1.0, norm)[:, None]
  ok = ok & (jnp.sum(mask, axis=-1) >= MIN_POINTS)
  return jnp.where(ok[:, None], feat, 0.0), ok
