"""The host search lrf_jax used before the engine (scipy cKDTree, seeded prefix trees), kept as
the baseline of bench_engine.py. Same contract and output as `lrf_jax.build_patches`."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from lrf_jax.search.neighborhoods import Patches, hash_priority, _round_up


class SearchIndex:
  """KD-trees over the cloud stored in seeded priority order, reusable across calls.

  Storing the points sorted by `hash_priority(seed, index)` makes the sorted ball lists that
  cKDTree returns come out in priority order, so "the K points of smallest priority" is simply
  the first K of each list: no per-ball sort on the host.

  It also keeps trees over the priority-order *prefixes* of n/2, n/4, ... points. A prefix holds,
  in every ball, exactly the ball's points of smallest priority; so when the prefix ball still
  holds at least K points, its first K are the same K points as the full ball's, found while
  materialising about K to 2K neighbors instead of all of them (a 15 mr ball on BR holds up to
  2800 points for K = 256).
  """

  def __init__(self, points: np.ndarray, seed: int = 0, min_prefix: int = 2048):
    self.points = np.asarray(points, np.float64)
    self.seed = int(seed)
    self.order = np.argsort(hash_priority(self.seed, np.arange(len(self.points))), kind="stable")
    self.tree = cKDTree(self.points[self.order])
    self.prefix_trees = []  # (size, tree), largest first, sizes n/2, n/4, ...
    size = len(self.points) // 2
    while size >= min_prefix:
      self.prefix_trees.append((size, cKDTree(self.tree.data[:size])))
      size //= 2

  def first_k(self, centers: np.ndarray, radius: float, k: int) -> tuple[list, np.ndarray]:
    """Per center, the tree indices (= priority ranks) of its first min(K, count) ball points.

    Returns:
      (lists, counts): lists[i] holds up to K sorted tree indices; counts (m,) the exact number
      of points within `radius`.
    """
    counts = self.tree.query_ball_point(centers, radius, workers=-1, return_length=True)
    counts = np.asarray(counts, np.int64)
    lists: list = [None] * len(centers)
    todo = np.arange(len(centers))
    for _size, tree in reversed(self.prefix_trees):  # coarsest first
      if not todo.size:
        break
      n_pref = tree.query_ball_point(centers[todo], radius, workers=-1, return_length=True)
      ready = todo[np.asarray(n_pref) >= k]
      if ready.size:
        found = tree.query_ball_point(centers[ready], radius, workers=-1, return_sorted=True)
        for i, b in zip(ready, found):
          lists[i] = b[:k]
      todo = todo[np.asarray(n_pref) < k]
    if todo.size:
      found = self.tree.query_ball_point(centers[todo], radius, workers=-1, return_sorted=True)
      for i, b in zip(todo, found):
        lists[i] = b[:k]
    return lists, counts


def _flatten(lists, counts: np.ndarray) -> np.ndarray:
  return np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64,
                     count=int(counts.sum()))


def ckdtree_build_patches(
    points: np.ndarray,
    keypoints: np.ndarray,
    radius: float,
    k: int | None = 256,
    *,
    seed: int = 0,
    z_ratio: float = 1.0 / 3.0,
    index: SearchIndex | None = None,
    validate: bool = True,
    max_k: int | None = None,
) -> Patches:
  """Radius search around keypoints into fixed-size padded patches.

  Args:
    points: (n, 3) cloud (any float dtype; computed in float64 on the host).
    keypoints: (m,) integer indices into `points`.
    radius: support radius r, in the cloud's units (> 0).
    k: patch size K. Balls with more than K points keep the K points of smallest
      `hash_priority(seed, point index)`: a subsample that depends only on point indices and the
      seed. `None` keeps every neighbor: K becomes the largest ball size rounded up to the next
      size of the ladder 32, 48, 64, 96, 128, 192, ... (at most 1.5x padding and two sizes per
      octave, so that runs over many clouds compile a handful of shapes, not one per cloud).
    seed: seed of the subsample.
    z_ratio: the normal support radius as a fraction of r (1/3: TOLDI, LRF-Net).
    index: an optional prebuilt `SearchIndex(points, seed)` to reuse across calls.
    validate: check the inputs (disable only for already validated arrays).
    max_k: with `k=None`, an upper bound on K: larger balls keep their `max_k` points of smallest
      priority (the same seeded subsample as an integer k). None = no bound.

  Returns:
    `Patches` with N = m; within a patch, neighbors are stored in priority order.

  Raises:
    ValueError: bad cloud, keypoints, radius or K.
  """
  points = np.asarray(points, np.float64)
  keypoints = np.asarray(keypoints, np.int64)
  if index is None or index.seed != seed or index.points.shape != points.shape:
    index = SearchIndex(points, seed)
  m = keypoints.shape[0]
  centers = points[keypoints]

  # Normal support: every neighbor within z_ratio * r, reduced to float64 statistics.
  inner = index.tree.query_ball_point(centers, z_ratio * radius, workers=-1, return_sorted=False)
  z_count = np.fromiter(map(len, inner), dtype=np.int64, count=m)
  r_in = np.repeat(np.arange(m), z_count)
  o_in = index.tree.data[_flatten(inner, z_count)] - centers[r_in]
  s1 = np.stack([np.bincount(r_in, o_in[:, a], minlength=m) for a in range(3)], axis=1)
  s2 = np.empty((m, 3, 3))
  for a in range(3):
    for b in range(a, 3):
      s2[:, a, b] = s2[:, b, a] = np.bincount(r_in, o_in[:, a] * o_in[:, b], minlength=m)
  denom = np.maximum(z_count, 1).astype(np.float64)
  z_mean = s1 / denom[:, None]
  z_cov = s2 / denom[:, None, None] - z_mean[:, :, None] * z_mean[:, None, :]

  # Patch: the ball in priority order (sorted tree indices), truncated to K.
  if k is None:
    counts = np.asarray(index.tree.query_ball_point(centers, radius, workers=-1,
                                                    return_length=True), np.int64)
    k = _round_up(int(counts.max()) if m else 1)
    if max_k is not None:
      k = min(k, int(max_k))
  balls, counts = index.first_k(centers, radius, k)
  kept = np.minimum(counts, k)
  cols = _flatten(balls, kept)
  rows = np.repeat(np.arange(m), kept)
  slot = np.arange(cols.size) - np.repeat(np.cumsum(kept) - kept, kept)

  offsets = np.zeros((m, k, 3), np.float32)
  mask = np.zeros((m, k), bool)
  indices = np.full((m, k), -1, np.int32)
  offsets[rows, slot] = index.tree.data[cols] - centers[rows]
  mask[rows, slot] = True
  indices[rows, slot] = index.order[cols]
  return Patches(
      offsets=offsets,
      mask=mask,
      indices=indices,
      count=counts.astype(np.int32),
      radius=np.full((m,), radius, np.float32),
      z_cov=z_cov.astype(np.float32),
      z_mean=z_mean.astype(np.float32),
      z_count=z_count.astype(np.int32),
  )
