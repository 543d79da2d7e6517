"""Host-side radius search: a cloud and keypoints -> fixed-size, padded patches.

This is the only place where shapes depend on the data. Everything downstream (frames, losses,
descriptors) takes a `Patches` of static shape and is jitted.

Two neighborhoods are gathered per keypoint p with one search of radius r:

* the *patch*: up to K neighbors q with |q - p| <= r, as offsets q - p, padded to K with a mask.
  When the ball holds more than K points a seeded subsample is kept. The subsample depends only on
  (seed, point index) through an integer hash, never on coordinates or on the order the search
  returns points: rotating or translating the cloud selects the same neighbors.
* the *z support*: *all* neighbors within `z_ratio * r` (r/3 for TOLDI and LRF-Net), reduced
  on the host, in float64, to their count, centroid offset and covariance about the centroid. The
  z-axis therefore never depends on the K-point subsample (on BR a 15 mr ball holds 380-2800
  points, a 256-point subsample only 20-35 inside r/3).

Both come from one call of the compiled engine (`lrf_jax.search.engine`: a uniform grid, numba,
multi-threaded), which writes the arrays of `Patches` directly.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from lrf_jax.checks import (validate_cloud, validate_keypoints, validate_radius,
                            validate_scale)
from lrf_jax.search import engine

if TYPE_CHECKING:
  from typing import TypeAlias

  import jax

  # A pytree leaf such as a `Patches` field: a numpy array on the host (`build_patches`), a
  # jax.Array on the device and under jit (`search.device`, `geometry.ops.sanitize`, the frames).
  AnyArray: TypeAlias = np.ndarray | jax.Array

# Multiplier of the splitmix64 finaliser (public domain, Steele et al.).
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
# Grid cells per support radius (cell side r / 3).
CELLS_PER_RADIUS = 3.0


class Patches(NamedTuple):
  """Fixed-size neighborhoods of N keypoints (a pytree; all leaves share the leading axis N).

  Attributes:
    offsets: (N, K, 3) float32, q - p for the kept neighbors, zeros in padding (cloud units).
    mask: (N, K) bool, True for real neighbors.
    indices: (N, K) int32, the cloud index of each kept neighbor, -1 in padding.
    count: (N,) int32, number of points within r (keypoint included) before subsampling.
    radius: (N,) float32, the support radius r (cloud units).
    z_cov: (N, 3, 3) float32, covariance of all offsets within z_ratio * r about their centroid.
    z_mean: (N, 3) float32, centroid of those offsets (relative to the keypoint).
    z_count: (N,) int32, number of points within z_ratio * r (keypoint included).
  """

  offsets: AnyArray
  mask: AnyArray
  indices: AnyArray
  count: AnyArray  # type: ignore[assignment]  # a field named like tuple.count (public)
  radius: AnyArray
  z_cov: AnyArray
  z_mean: AnyArray
  z_count: AnyArray

  @property
  def num_keypoints(self) -> int:
    return self.offsets.shape[0]

  @property
  def k(self) -> int:
    return self.offsets.shape[1]


def unit_scaled(points: np.ndarray, radius: float, viewpoint: np.ndarray | None = None
                ) -> tuple[np.ndarray, float, np.ndarray | None]:
  """A cloud, its support radius and sensor position in units of the radius (radius 1).

  Every LRF method is invariant to a common scale of cloud and radius (frames are directions),
  so the frames of the result are those of the input; normals and faces need no change. In
  these units float32 patches, squared distances and the methods' small tolerances behave
  alike at every scale, and two clouds that differ by a scale factor give the same patches up
  to float64 rounding. One pass over the cloud.

  Args:
    points: (n, 3) float64 cloud, validated.
    radius: support radius r (cloud units).
    viewpoint: optional (3,) sensor position (cloud units).

  Returns:
    (points / r (n, 3) float64, 1.0, viewpoint / r or None).

  Raises:
    ValueError: a radius outside `MIN_SCALE` .. `MAX_SCALE` (`validate_radius`).
  """
  r = validate_radius(radius)
  vp = None if viewpoint is None else np.asarray(viewpoint, np.float64) / r
  return np.asarray(points, np.float64) / r, 1.0, vp


def hash_priority(seed: int, point: np.ndarray) -> np.ndarray:
  """A pseudo-random uint64 per (seed, point index): splitmix64 of a mixed key.

  Args:
    seed: integer seed.
    point: (M,) point indices.

  Returns:
    (M,) uint64 priorities; a subsampled ball keeps its K points of smallest priority.
  """
  with np.errstate(over="ignore"):
    x = np.uint64(seed & 0xFFFFFFFFFFFFFFFF) * _GOLDEN + point.astype(np.uint64)
    x = (x ^ (x >> np.uint64(30))) * _MIX1
    x = (x ^ (x >> np.uint64(27))) * _MIX2
    return x ^ (x >> np.uint64(31))


class SearchIndex:
  """The cloud binned for the engine's radius search, reusable across calls.

  Ranks are the seeded priority order (`hash_priority(seed, index)`, ties broken by index), so
  that "the K points of smallest priority" of a ball are its K points of smallest rank. Grids
  (`lrf_jax.search.engine.Grid`) are built lazily, one per cell size, for cells of `radius / 3` (any
  radius is answered by any grid, only the speed changes).

  Args:
    points: (n, 3) cloud (float64 on the host).
    seed: the subsample seed.
  """

  def __init__(self, points: np.ndarray, seed: int = 0):
    self.points = np.ascontiguousarray(points, np.float64)
    self.seed = int(seed)
    n = len(self.points)
    # The priorities are distinct (splitmix64 is a bijection of the distinct keys seed * golden
    # + index), so the fast unstable sort gives the one possible order.
    self.order = np.argsort(hash_priority(self.seed, np.arange(n)))
    self.rank = np.empty(n, np.int64)
    self.rank[self.order] = np.arange(n)
    self.max_abs = float(np.abs(self.points).max()) if n else 0.0
    self._grids: dict[float, engine.Grid] = {}

  def matches(self, points: np.ndarray) -> bool:
    """Whether this index was built from `points` (the same array, or equal values)."""
    return points is self.points or (np.shape(points) == self.points.shape
                                     and np.array_equal(points, self.points))

  @property
  def data(self) -> np.ndarray:
    """(n, 3) the points in priority order (row i has rank i)."""
    return self.points[self.order]

  def grid(self, radius: float) -> engine.Grid:
    """The grid for balls of `radius` (cells of radius / 3), built on first use.

    Raises:
      ValueError: a radius or cloud outside the supported scale (`validate_scale`).
    """
    cell = float(radius) / CELLS_PER_RADIUS
    g = self._grids.get(cell)
    if g is None:
      validate_scale(self.max_abs, float(radius))
      if len(self._grids) >= 4:
        self._grids.clear()
      g = self._grids[cell] = engine.Grid(self.points, cell, self.rank)
    return g


def _round_up(k: int) -> int:
  """The smallest size of the ladder 32, 48, 64, 96, 128, 192, ... that is >= k."""
  size = 32
  while True:
    if size >= k:
      return size
    if size * 3 // 2 >= k:
      return size * 3 // 2
    size *= 2


def validate_index(index: Any, points: np.ndarray) -> None:
  """Raise a ValueError unless `index` is a `SearchIndex` of exactly these points (the same
  array, or the same shape and values, `SearchIndex.matches`): an index of another cloud would
  silently answer with its points."""
  if not isinstance(index, SearchIndex):
    raise ValueError("index: expected a SearchIndex built from these points (SearchIndex(points, "
                     f"seed)), got {type(index).__name__}")
  if not index.matches(points):
    raise ValueError(f"index: a SearchIndex of a different cloud ({index.points.shape[0]} "
                     f"points, not equal to the {np.shape(points)[0]} points given); build it "
                     "with SearchIndex(points, seed) from these points")


def build_patches(
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
    shells: tuple[float, float] | None = None,
    into: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    stats_from: Patches | None = None,
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
    validate: check the inputs; False only for arguments the caller has checked already
      (`compute_frames`, `compute_descriptors`, the training batches, the device search):
      a finite (n, 3) cloud, (m,) integer indices into it, positive `radius` and `z_ratio`,
      `k` a positive integer or None, `index` None or an index of `points`. The cloud is read
      as float64 and the keypoints as int64 (no copy when they already are).
    max_k: with `k=None`, an upper bound on K: larger balls keep their `max_k` points of smallest
      priority (the same seeded subsample as an integer k). None = no bound.
    shells: (a, b) fractions of r: the patch holds only the neighbors within a * r or beyond
      b * r, still in priority order (for methods that read nothing in between, e.g. FLARE: its
      r/3 z support and its 0.85 r margin). `count` still counts every point within r.
    into: with an integer k, optional (offsets (m, K, 3) float32, mask (m, K) bool, indices
      (m, K) int32) arrays (e.g. row ranges of larger arrays, any contents: every element is
      written) that receive those fields instead of new arrays; the returned Patches holds them.
    stats_from: optional Patches of the same points, keypoints, radius and z_ratio built
      earlier with any seed and K (e.g. the previous epoch's): `count`, `z_cov`, `z_mean` and
      `z_count` do not depend on the seed or K, so they are taken from it and the search skips
      the two passes that compute them (the result is identical). Not with `shells`; its radius
      must equal `radius`.

  Returns:
    `Patches` with N = m; within a patch, neighbors are stored in priority order.

  Raises:
    ValueError: bad cloud, keypoints, radius or K.
  """
  if validate:
    points = validate_cloud(points)
    keypoints = validate_keypoints(keypoints, points.shape[0])
    radius = validate_radius(radius)
    z_ratio = validate_radius(z_ratio, "z_ratio")
    if k is not None and (int(k) != k or k < 1):
      raise ValueError(f"k: expected a positive integer patch size or None, got {k!r}")
    if index is not None:
      validate_index(index, points)
  points = np.asarray(points, np.float64)
  keypoints = np.asarray(keypoints, np.int64)
  if index is None or index.seed != seed or index.points.shape != points.shape:
    index = SearchIndex(points, seed)
  m = keypoints.shape[0]
  centers = points[keypoints]
  grid = index.grid(radius)
  if k is None:
    counts = engine.ball_counts(grid, centers, radius, shells)
    k = _round_up(int(counts.max()) if m else 1)
    if max_k is not None:
      k = min(k, int(max_k))
  known = None
  if stats_from is not None:
    if stats_from.count.shape != (m,) or not np.all(stats_from.radius == np.float32(radius)):
      raise ValueError(f"stats_from: expected Patches of these {m} keypoints at radius "
                       f"{radius}, got {stats_from.count.shape[0]} at "
                       f"{np.unique(stats_from.radius)[:3]}")
    known = stats_from.count
  out = engine.patches(grid, centers, radius, int(k), z_ratio * radius, shells, into, known)
  if stats_from is not None:
    z_cov, z_mean, z_count = stats_from.z_cov, stats_from.z_mean, stats_from.z_count
  else:  # no counts given: the engine computed the statistics
    assert out["z_cov"] is not None and out["z_mean"] is not None and out["z_count"] is not None
    z_cov = out["z_cov"].astype(np.float32)
    z_mean = out["z_mean"].astype(np.float32)
    z_count = out["z_count"].astype(np.int32)
  return Patches(
      offsets=out["offsets"],
      mask=out["mask"],
      indices=out["indices"],
      count=out["count"].astype(np.int32),
      radius=np.full((m,), radius, np.float32),
      z_cov=z_cov,
      z_mean=z_mean,
      z_count=z_count,
  )


