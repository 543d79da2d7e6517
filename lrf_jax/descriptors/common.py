"""Helpers shared by the LRF-based descriptors: local coordinates, padding, validation.

Every descriptor takes the same inputs: a `Patches` batch (normally with *every* neighbor in the
ball, `k=None`, as the original descriptors use) and frames from ANY LRF method, rows x, y, z
(they map world offsets into the LRF: `local = F @ (q - p)`).
"""

from __future__ import annotations

from lrf_jax._jax import jax, jnp
import numpy as np

from lrf_jax.search import engine
from lrf_jax.search.neighborhoods import Patches, SearchIndex, build_patches


def local_coordinates(offsets: jax.Array, frames: jax.Array) -> jax.Array:
  """Neighbor offsets expressed in their keypoint's LRF.

  Args:
    offsets: (N, K, 3) q - p (cloud units).
    frames: (N, 3, 3) rows x, y, z.

  Returns:
    (N, K, 3) local coordinates (x, y, z) = F (q - p).
  """
  return jnp.einsum("nij,nkj->nki", frames, offsets)


def sanitize_inputs(patches: Patches, frames: jax.Array,
                    valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
  """Finite offsets/frames for the arithmetic, and which keypoints may be described.

  Args:
    patches: `Patches` (N keypoints, K slots).
    frames: (N, 3, 3).
    valid: (N,) bool validity of the frames.

  Returns:
    (offsets (N, K, 3) with non-finite rows zeroed, mask (N, K) of finite real neighbors,
    frames (N, 3, 3) with non-finite frames replaced by the identity, ok (N,) = valid and finite
    frame and finite radius).
  """
  offsets = jnp.asarray(patches.offsets)
  row_ok = jnp.all(jnp.isfinite(offsets), axis=-1)
  mask = jnp.asarray(patches.mask) & row_ok
  offsets = jnp.where(row_ok[..., None], offsets, 0.0)
  frames = jnp.asarray(frames, offsets.dtype)
  f_ok = jnp.all(jnp.isfinite(frames), axis=(-1, -2))
  frames = jnp.where(f_ok[:, None, None], frames, jnp.eye(3, dtype=frames.dtype))
  r_ok = jnp.isfinite(jnp.asarray(patches.radius)) & (jnp.asarray(patches.radius) > 0)
  return offsets, mask, frames, jnp.asarray(valid, bool) & f_ok & r_ok


def pad_patches(patches: Patches, k: int) -> Patches:
  """Pad a batch of patches to K = `k` slots (padding never changes a descriptor).

  Used to bucket K so that clouds with slightly different ball sizes share one compiled shape.

  Args:
    patches: `Patches` with K <= k.
    k: the new slot count.

  Returns:
    `Patches` with K = k (offsets 0, mask False, indices -1 in the new slots).
  """
  n, k0 = np.shape(patches.mask)
  if k < k0:
    raise ValueError(f"k: cannot pad {k0} slots down to {k}")
  if k == k0:
    return patches
  extra = k - k0
  return patches._replace(
      offsets=np.concatenate([np.asarray(patches.offsets),
                              np.zeros((n, extra, 3), np.float32)], axis=1),
      mask=np.concatenate([np.asarray(patches.mask), np.zeros((n, extra), bool)], axis=1),
      indices=np.concatenate([np.asarray(patches.indices),
                              np.full((n, extra), -1, np.int32)], axis=1))


def bucket_k(k: int) -> int:
  """Round a slot count up to the next of 64, 96, 128, 192, 256, 384, 512, 768, 1024, ...

  (powers of two and their 1.5 multiples): at most 50 % padding, few distinct compiled shapes.
  """
  b = 64
  while b < k:
    b = b * 3 // 2 if (b & (b - 1)) == 0 else (b // 3) * 4
  return b


def ball_patches(index: SearchIndex, points: np.ndarray, keypoints: np.ndarray,
                 radius: float) -> Patches:
  """Patches with EVERY neighbor within `radius` (the engine's radius search), K bucketed.

  The descriptors' neighborhood (the original descriptors use the whole ball). Slot order (the
  index's priority order) does not matter: descriptors are sums or extrema over the slots.

  Args:
    index: `SearchIndex(points, seed)`.
    points: (n, 3) float64 cloud.
    keypoints: (m,) indices.
    radius: r.

  Returns:
    `Patches` with K = `bucket_k(largest ball)`.
  """
  centers = points[keypoints]
  grid = index.grid(radius)
  counts = engine.ball_counts(grid, centers, radius)
  k = bucket_k(int(counts.max()) if len(keypoints) else 1)
  return build_patches(points, keypoints, radius, k, seed=index.seed, index=index, validate=False)
