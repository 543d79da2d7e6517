"""The compiled neighbourhood engine: uniform-grid radius and nearest-neighbour search (numba).

Every radius and nearest-neighbour query on the paths `compute_frames`, training, evaluation,
descriptors and `register` run goes through this module. It is host code, compiled once by
numba (`cache=True`: the machine code is stored on disk and reused by later processes) and
multi-threaded over query points (`parallel=True`).

Design:

* A `Grid` bins the cloud into cubic cells of side h (the patch search uses h = r / 3) and
  stores the points sorted by (cell, rank) with a counting sort, O(n), one row per coordinate.
  `rank` is any permutation of the point indices; the patch search uses the seeded priority
  order of `hash_priority`, so that within every cell the points come in priority order.
* A ball query of radius r visits the columns (x cell, y cell) within ceil(r / h) cells whose
  box comes within r of the centre, and in each column only the run of consecutive z cells the
  ball's slice can reach (`_columns`); every point there is tested with cKDTree's rule: float64
  squared distance, summed over x, y, z in that order, `<= r * r`. Cells whose box lies inside
  the ball (with a margin) count whole without a test (`_column_runs`).
* The patch kernel writes `Patches` directly: the ball's count, the float64 statistics of the
  inner ball (z_ratio * r: count, centroid, covariance about the centroid) and the K in-ball
  points of smallest rank, sorted by rank. Only the ranks below a limit that the K smallest lie
  under but for about one ball in 10^4 are collected (a cell's scan stops there; a ball the
  limit misses is collected again without it), then bucket-sorted by rank. The subsample is
  therefore exactly the one of `neighborhoods.hash_priority`: the same indices whatever the
  search order, the thread count or the cloud's pose.
* Nearest-neighbour queries (ICP pairs, mesh areas, the normal-orientation graph) grow the
  scanned cube of cells ring by ring around the query's cell until the k-th distance found (or
  the bound) is within the ring's guaranteed radius; `icp_sums` reduces one ICP step's pairs to
  their sums in the same pass. "Any point within r" (overlap scores) visits the ball's columns
  and stops at the first point found.

Compile time: the patch kernel calls its ball-query helpers as functions (`*_called`, the same
code compiled on its own) instead of inlining them: numba's `inline="always"` re-types each call
site inside a parallel kernel, which tripled the patch kernel's compile (18.7 -> 6.8 s of CPU on
a first `build_patches`), for the same results and speed. The other kernels keep the inlined
helpers: without them the ball lists, normals and k-NN queries run 1.3-5x slower.

Threads: `set_num_threads(n)` or the environment variable `LRF_JAX_NUM_THREADS` (read at import);
the default is every core numba sees. Results do not depend on the thread count: each query's
output is computed by one thread, in a fixed order.

Memory: the grid holds the cloud once more in float64 plus O(n + cells) int64; the number of
cells is bounded by `max(8 n, 4096)` (h grows past r when a tiny radius would need more), so a
far-flung cloud with a tiny radius costs time, never an unbounded table.
"""

from __future__ import annotations

import os

import numba as nb
import numpy as np

from lrf_jax import compilation_cache

compilation_cache.announce_compiles()  # one stderr line when a kernel is compiled (a cache miss)

_ENV_THREADS = "LRF_JAX_NUM_THREADS"
# Cells are enlarged by this factor over the requested side (a cell side is a speed setting:
# ball queries prune columns with their own margin, `_PRUNE_MARGIN`).
_CELL_MARGIN = 1e-6
_BLOCK = 32  # queries per parallel task
_SHELL_SLACK = 1e-5


def num_threads() -> int:
  """The number of threads the engine's kernels use."""
  return int(nb.get_num_threads())


def set_num_threads(n: int | None = None) -> int:
  """Set the engine's thread count (None: every core numba sees); returns the count set.

  Raises:
    ValueError: `n` not a positive integer.
  """
  limit = int(nb.config.NUMBA_NUM_THREADS)
  if n is None:
    n = limit
  if isinstance(n, bool) or int(n) != n or n < 1:
    raise ValueError(f"num_threads: expected a positive integer, got {n!r}")
  nb.set_num_threads(min(int(n), limit))
  return num_threads()


def _threads_from_env() -> None:
  value = os.environ.get(_ENV_THREADS)
  if value:
    try:
      set_num_threads(int(value))
    except ValueError:
      raise ValueError(f"{_ENV_THREADS}: expected a positive integer, got {value!r}") from None


_threads_from_env()


# ---------------------------------------------------------------------------------------------
# Grid construction.


@nb.njit(cache=True)
def _bin(points, rank, origin, h, dims):
  """Counting sort of the points by (cell, rank). Returns (slot_index, starts)."""
  n = points.shape[0]
  ncell = dims[0] * dims[1] * dims[2]
  cell_of = np.empty(n, np.int64)
  starts = np.zeros(ncell + 1, np.int64)
  for i in range(n):
    c = _cell_id(points[i, 0], points[i, 1], points[i, 2], origin, h, dims)
    cell_of[i] = c
    starts[c + 1] += 1
  for c in range(ncell):
    starts[c + 1] += starts[c]
  # Visit points in rank order so that each cell's run is sorted by rank.
  by_rank = np.empty(n, np.int64)
  for i in range(n):
    by_rank[rank[i]] = i
  fill = starts[:-1].copy()
  slot_index = np.empty(n, np.int64)
  for r in range(n):
    i = by_rank[r]
    c = cell_of[i]
    slot_index[fill[c]] = i
    fill[c] += 1
  return slot_index, starts


@nb.njit(cache=True)
def _bounds(points):
  """(min, max) of an (n >= 1, 3) array per coordinate, in one pass (numpy's axis-0 reductions
  of a C-ordered (n, 3) array are several times slower)."""
  lo = points[0].copy()
  hi = points[0].copy()
  for i in range(1, points.shape[0]):
    for a in range(3):
      v = points[i, a]
      if v < lo[a]:
        lo[a] = v
      if v > hi[a]:
        hi[a] = v
  return lo, hi


@nb.njit(inline="always")
def _coord(x, o, h, d):
  c = int(np.floor((x - o) / h))
  return min(max(c, 0), d - 1)


@nb.njit(inline="always")
def _cell_id(x, y, z, origin, h, dims):
  cx = _coord(x, origin[0], h, dims[0])
  cy = _coord(y, origin[1], h, dims[1])
  cz = _coord(z, origin[2], h, dims[2])
  return (cx * dims[1] + cy) * dims[2] + cz


class Grid:
  """A cloud binned into cubic cells of side `cell`, points sorted by (cell, rank).

  Args:
    points: (n, 3) float64 cloud (finite; not checked here).
    cell: cell side h (cloud units); any radius can be queried (a ball of radius r visits
      ceil(r / h) cells each way), the side only sets the speed. It is enlarged when the
      cloud's bounding box would need more than max(8 n, 4096) cells.
    rank: (n,) permutation of 0..n-1; within a cell, points are stored by increasing rank
      (default: the point index).

  Attributes:
    points: (n, 3) float64, the cloud as given (indexed by point index).
    xyz: (3, n) float64, the cloud in slot order, one row per coordinate (contiguous loads).
    slot_index: (n,) int64, the point index of each slot.
    slot_rank: (n,) int64, the rank of each slot's point.
    starts: (cells + 1,) int64, slot range of each cell.
    origin: (3,) float64, the corner of cell (0, 0, 0).
    dims: (3,) int64, cells per axis.
    h: float, the cell side actually used (>= `cell`).
  """

  def __init__(self, points: np.ndarray, cell: float, rank: np.ndarray | None = None):
    pts = np.ascontiguousarray(points, np.float64)
    n = pts.shape[0]
    if rank is None:
      rank = np.arange(n, dtype=np.int64)
    lo, hi = _bounds(pts) if n else (np.zeros(3), np.zeros(3))
    extent = np.maximum(hi - lo, 0.0)
    h = float(cell) * (1.0 + _CELL_MARGIN)
    span = float(extent.max()) if n else 0.0
    # At most 2**20 cells per axis, and a positive cell even for a zero radius or one point.
    h = max(h, span * 2.0**-20, np.finfo(np.float64).tiny * 2.0**60)
    if not np.isfinite(h):
      raise ValueError(f"cell: expected a finite cell size, got {cell!r}")
    limit = max(8 * n, 4096)
    while True:
      dims = (np.floor(extent / h) + 1).astype(np.int64)
      if float(np.prod(dims.astype(np.float64))) <= limit:
        break
      h *= max(1.01, (float(np.prod(dims.astype(np.float64))) / limit) ** (1.0 / 3.0))
    self.points = pts
    self.origin = lo.astype(np.float64)
    self.dims = dims
    self.h = h
    self.slot_index, self.starts = _bin(pts, np.asarray(rank, np.int64), self.origin, h, dims)
    self.slot_rank = np.asarray(rank, np.int64)[self.slot_index]
    self.xyz = np.take(pts.T, self.slot_index, axis=1)  # (3, n) contiguous: x, y, z rows


# ---------------------------------------------------------------------------------------------
# Ball queries.

# Columns are pruned with a radius enlarged by this factor: a point's cell comes from a rounded
# division, its column's box from a rounded product; the margin keeps every in-ball point.
_PRUNE_MARGIN = 1e-5


@nb.njit(inline="always")
def _cell(x, o, h):
  """The (unclamped) cell index of coordinate x, bounded to +-2**40 so that it fits an int64."""
  return int(min(max(np.floor((x - o) / h), -1099511627776.0), 1099511627776.0))


@nb.njit(inline="always")
def _columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je):
  """Cell ranges [js, je) (consecutive cell ids) that may hold points within r of (cx, cy, cz).

  For each column (x cell, y cell) within `reach` cells whose box comes within r of the centre,
  the z cells that the ball's slice through that column can reach; the slots of cells js..je-1
  are starts[js]..starts[je]. Returns the number of ranges.
  """
  return _column_runs(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, False, js, je)


@nb.njit(inline="always")
def _far(c, lo, h, e):
  """The largest distance from c to the interval [lo - e, lo + h + e]."""
  return max(c - lo + e, lo + h + e - c)


@nb.njit(inline="always")
def _column_runs(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, inner, ji, jk):
  """`_columns`; with `inner`, also the cells [ji, jk) of each range whose whole box lies inside
  the ball, with a margin (relative 1e-9 of r, and of the coordinates' size) that keeps every
  point binned to them within r by cKDTree's float64 rule (ji = jk: none)."""
  rp = r * (1.0 + _PRUNE_MARGIN)
  rp2 = rp * rp
  e = 1e-9 * h + 1e-12 * (abs(cx) + abs(cy) + abs(cz) + abs(origin[0]) + abs(origin[1])
                          + abs(origin[2]))
  ri2 = (r * (1.0 - 1e-9)) ** 2
  ix = _cell(cx, origin[0], h)
  iy = _cell(cy, origin[1], h)
  n = 0
  for a in range(max(ix - reach, 0), min(ix + reach, dims[0] - 1) + 1):
    lox = origin[0] + a * h
    ddx = lox - cx if cx < lox else (cx - lox - h if cx > lox + h else 0.0)
    rx = rp2 - ddx * ddx
    if rx < 0.0:
      continue
    for b in range(max(iy - reach, 0), min(iy + reach, dims[1] - 1) + 1):
      lo = origin[1] + b * h
      ddy = lo - cy if cy < lo else (cy - lo - h if cy > lo + h else 0.0)
      rem = rx - ddy * ddy
      if rem < 0.0:
        continue
      t = np.sqrt(rem)
      z0 = max(_cell(cz - t, origin[2], h), 0)
      z1 = min(_cell(cz + t, origin[2], h), dims[2] - 1)
      if z0 > z1:
        continue
      base = (a * dims[1] + b) * dims[2]
      if starts[base + z1 + 1] > starts[base + z0]:
        js[n] = base + z0
        je[n] = base + z1 + 1
        if inner:
          ji[n] = jk[n] = base + z0
          fx, fy = _far(cx, lox, h, e), _far(cy, lo, h, e)
          rin = ri2 - fx * fx - fy * fy
          if rin > 0.0:  # the z cells whose box (+- 2e) lies within the slice cz +- sqrt(rin)
            tin = np.sqrt(rin)
            i0 = max(int(np.ceil((cz - tin + 2.0 * e - origin[2]) / h)), z0)
            i1 = min(int(np.floor((cz + tin - 2.0 * e - origin[2]) / h)) - 1, z1)
            if i0 <= i1:
              ji[n], jk[n] = base + i0, base + i1 + 1
        n += 1
  return n


@nb.njit(inline="always")
def _count_slots(pts, a, b, cx, cy, cz, r2):
  """Points of slots a..b-1 within sqrt(r2) of (cx, cy, cz)."""
  c = 0
  for j in range(a, b):
    dx = pts[0, j] - cx
    dy = pts[1, j] - cy
    dz = pts[2, j] - cz
    c += (dx * dx + dy * dy + dz * dz) <= r2
  return c


@nb.njit(inline="always")
def _count_runs(pts, starts, cx, cy, cz, r2, nr, js, je, ji, jk):
  """Points within sqrt(r2) of (cx, cy, cz) in the ranges js..je whose cells ji..jk are inside
  the ball (`_column_runs`): those cells count whole, the others point by point."""
  c = 0
  for q in range(nr):
    c += starts[jk[q]] - starts[ji[q]]
    c += _count_slots(pts, starts[js[q]], starts[ji[q]], cx, cy, cz, r2)
    c += _count_slots(pts, starts[jk[q]], starts[je[q]], cx, cy, cz, r2)
  return c


@nb.njit(inline="always")
def _count_ball(pts, starts, cx, cy, cz, r2, kin2, kout2, nr, js, je):
  """(points within sqrt(r2) of (cx, cy, cz) in the slot ranges js..je, those of them within
  sqrt(kin2) or beyond sqrt(kout2)): the ball's size and its candidates."""
  c = 0
  ck = 0
  for q in range(nr):
    for j in range(starts[js[q]], starts[je[q]]):
      dx = pts[0, j] - cx
      dy = pts[1, j] - cy
      dz = pts[2, j] - cz
      d2 = dx * dx + dy * dy + dz * dz
      inside = d2 <= r2
      c += inside
      ck += inside & ((d2 <= kin2) | (d2 > kout2))  # no branches: balls are random
  return c, ck


@nb.njit(parallel=True, cache=True)
def _ball_counts(pts, starts, origin, h, dims, centers, order, r, reach, kin2, kout2):
  """(points within r of each centre, those of them within sqrt(kin2) or beyond sqrt(kout2)),
  centres visited in `order`."""
  m = centers.shape[0]
  full = np.zeros(m, np.int64)
  out = np.zeros(m, np.int64)
  r2 = r * r
  ncol = (2 * reach + 1) ** 2
  nblock = (m + _BLOCK - 1) // _BLOCK
  for blk in nb.prange(nblock):
    js = np.empty(ncol, np.int64)
    je = np.empty(ncol, np.int64)
    for t in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      i = order[t]
      cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
      nr = _columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
      full[i], out[i] = _count_ball(pts, starts, cx, cy, cz, r2, kin2, kout2, nr, js, je)
  return full, out


# Running moment sums of a ball's offsets: (count, x, y, z, xx, xy, xz, yy, yz, zz).
NO_MOMENTS = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@nb.njit(inline="always")
def add_moment(s, dx, dy, dz):
  """The running sums s (`NO_MOMENTS` to start) with the offset (dx, dy, dz) added."""
  return (s[0] + 1.0, s[1] + dx, s[2] + dy, s[3] + dz, s[4] + dx * dx, s[5] + dx * dy,
          s[6] + dx * dz, s[7] + dy * dy, s[8] + dy * dz, s[9] + dz * dz)


@nb.njit(inline="always")
def store_moments(s, mean, cov):
  """From the running sums s (`add_moment`), the centroid into mean (3,) and the covariance
  about it into cov (3, 3) (zeros for no point); returns the count."""
  d = max(s[0], 1.0)
  mx, my, mz = s[1] / d, s[2] / d, s[3] / d
  mean[0], mean[1], mean[2] = mx, my, mz
  cov[0, 0] = s[4] / d - mx * mx
  cov[0, 1] = cov[1, 0] = s[5] / d - mx * my
  cov[0, 2] = cov[2, 0] = s[6] / d - mx * mz
  cov[1, 1] = s[7] / d - my * my
  cov[1, 2] = cov[2, 1] = s[8] / d - my * mz
  cov[2, 2] = s[9] / d - mz * mz
  return int(s[0])


@nb.njit(inline="always")
def _scanned(starts, nr, js, je):
  """The number of slots in the ranges js..je."""
  t = 0
  for q in range(nr):
    t += starts[je[q]] - starts[js[q]]
  return t


@nb.njit(inline="always")
def _stats_one(pts, starts, cx, cy, cz, r2, nr, js, je, mean, cov, off):
  """Count, centroid and covariance about the centroid of the points within sqrt(r2).

  The in-ball offsets are gathered into off (3, >= slots in the ranges) by a branch-free pass,
  then summed in slot order: the sums of a branch-free weighted pass, bit for bit, at a third
  less time (the sums' dependency chains run over the in-ball points only)."""
  n = 0
  for q in range(nr):
    for j in range(starts[js[q]], starts[je[q]]):
      dx = pts[0, j] - cx
      dy = pts[1, j] - cy
      dz = pts[2, j] - cz
      off[0, n] = dx
      off[1, n] = dy
      off[2, n] = dz
      n += 1 if dx * dx + dy * dy + dz * dz <= r2 else 0
  s = NO_MOMENTS
  for e in range(n):
    s = add_moment(s, off[0, e], off[1, e], off[2, e])
  return store_moments(s, mean, cov)


@nb.njit(inline="always")
def _room(off, need):
  """off, or a larger (3, 2 * need + 1) buffer when it holds fewer than need + 1 columns."""
  if off.shape[1] > need:
    return off
  return np.empty((3, 2 * need + 1))


@nb.njit(parallel=True, cache=True)
def _ball_stats(pts, starts, origin, h, dims, centers, r, reach):
  """Count, centroid offset and covariance (about the centroid) of each ball, float64."""
  m = centers.shape[0]
  count = np.zeros(m, np.int64)
  mean = np.zeros((m, 3))
  cov = np.zeros((m, 3, 3))
  ncol = (2 * reach + 1) ** 2
  nblock = (m + _BLOCK - 1) // _BLOCK
  for blk in nb.prange(nblock):
    js = np.empty(ncol, np.int64)
    je = np.empty(ncol, np.int64)
    off = np.empty((3, 256))
    for i in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
      nr = _columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
      off = _room(off, _scanned(starts, nr, js, je))
      count[i] = _stats_one(pts, starts, cx, cy, cz, r * r, nr, js, je, mean[i], cov[i], off)
  return count, mean, cov


@nb.njit(inline="always")
def _pow2(x):
  p = 1
  while p < x:
    p *= 2
  return p


@nb.njit(cache=True)
def _smallest_sorted(keys, c, k, cnt, out, span):
  """The min(c, k) smallest of keys[:c] into out[:min(c, k)], sorted; returns min(c, k).

  keys are rank << 32 | slot with distinct ranks in [0, span). A bucket sort on the rank (the
  ranks of a ball are a seeded random sample, so the c buckets hold about one key each), then one
  insertion sort over the buckets that hold the k smallest: only keys sharing a bucket are out of
  order, so it is O(c), not O(c log c), with few mispredicted branches.
  """
  if c == 0:
    return 0
  nbk = _pow2(c)
  mult = (np.int64(nbk) << 32) // max(span, 1) + 1  # bucket = rank * nbk / span, < nbk
  for b in range(nbk + 1):
    cnt[b] = 0
  for e in range(c):
    b = min(((keys[e] >> 32) * mult) >> 32, nbk - 1)
    cnt[b + 1] += 1
  for b in range(nbk):
    cnt[b + 1] += cnt[b]
  for e in range(c):
    b = min(((keys[e] >> 32) * mult) >> 32, nbk - 1)
    out[cnt[b]] = keys[e]
    cnt[b] += 1
  # cnt[b] is now the end of bucket b; the first bucket end >= want bounds the prefix to sort.
  want = min(c, k)
  lo, hi = 0, nbk - 1
  while lo < hi:
    mid = (lo + hi) >> 1
    if cnt[mid] >= want:
      hi = mid
    else:
      lo = mid + 1
  for x in range(1, cnt[lo]):
    v = out[x]
    y = x - 1
    while y >= 0 and out[y] > v:
      out[y + 1] = out[y]
      y -= 1
    out[y + 1] = v
  return want


@nb.njit(inline="always")
def _rank_limit(k, c, n_rank):
  """A rank below which the K smallest of c random ranks out of n_rank lie but for about one
  ball in 10^4 (the K-th is about n_rank K / c, give or take n_rank sqrt(K) / c: a margin of
  3.5 sqrt(K) + 8; a ball it misses is collected again without a limit); none for c <= K."""
  if c <= k:
    return np.int64(1) << 62
  return np.int64((k + 3.5 * np.sqrt(k) + 8.0) / c * n_rank) + 1


@nb.njit(inline="always")
def _collect(pts, slot_rank, starts, cx, cy, cz, r2, kin2, kout2, limit, nr, js, je, buf):
  """The keys rank << 32 | slot of the candidates of rank below `limit` into buf (room for one
  per candidate and one more); each cell's run is sorted by rank, so a cell's scan stops at the
  limit. Returns their number."""
  got = 0
  for q in range(nr):
    for cell in range(js[q], je[q]):
      for j in range(starts[cell], starts[cell + 1]):
        if slot_rank[j] >= limit:
          break
        dx = pts[0, j] - cx
        dy = pts[1, j] - cy
        dz = pts[2, j] - cz
        buf[got] = (slot_rank[j] << 32) | j
        d2 = dx * dx + dy * dy + dz * dz
        got += (d2 <= r2) & ((d2 <= kin2) | (d2 > kout2))
  return got


# The patch kernel calls these instead of inlining them (see the module's docstring).
_columns_called = nb.njit(_columns.py_func)
_column_runs_called = nb.njit(_column_runs.py_func)
_count_ball_called = nb.njit(_count_ball.py_func)
_count_runs_called = nb.njit(_count_runs.py_func)
_stats_one_called = nb.njit(_stats_one.py_func)
_collect_called = nb.njit(_collect.py_func)


@nb.njit(parallel=True, cache=True)
def _patch_kernel(pts, slot_index, slot_rank, starts, origin, h, dims, centers, order, r, rz, k,
                  n_rank, reach, reach_in, kin2, kout2, known, offsets, mask, indices, count,
                  z_count, z_mean, z_cov):
  """Patches of the K points of smallest rank within r (of those within sqrt(kin2) or beyond
  sqrt(kout2): all of them when kin2 >= r * r), plus the inner-ball statistics; the centres are
  visited in the order `order` (`query_order`), each written whole to its own row (padding
  included: the outputs may start uninitialised). With `known`, count
  holds the in-ball counts already (no shells) and neither they nor the statistics are computed."""
  m = centers.shape[0]
  r2 = r * r
  ncol = (2 * max(reach, reach_in) + 1) ** 2  # the inner radius may exceed r
  nblock = (m + _BLOCK - 1) // _BLOCK
  for blk in nb.prange(nblock):
    js = np.empty(ncol, np.int64)
    je = np.empty(ncol, np.int64)
    ji = np.empty(ncol, np.int64)
    jk = np.empty(ncol, np.int64)
    off = np.empty((3, 256))
    cap = 1024
    buf = np.empty(cap, np.int64)
    out = np.empty(cap, np.int64)
    cnt = np.empty(_pow2(cap) + 1, np.int64)
    for t in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      i = order[t]
      cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
      if not known:
        nr = _columns_called(cx, cy, cz, origin, h, dims, starts, rz, reach_in, js, je)
        off = _room(off, _scanned(starts, nr, js, je))
        z_count[i] = _stats_one_called(pts, starts, cx, cy, cz, rz * rz, nr, js, je, z_mean[i],
                                z_cov[i], off)
      whole = not known and kin2 >= r2  # no shells: cells inside the ball count whole
      nr = _column_runs_called(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, whole, ji,
                               jk)
      if known:  # every in-ball point is a candidate (no shells)
        c = count[i]
      elif whole:
        c = count[i] = _count_runs_called(pts, starts, cx, cy, cz, r2, nr, js, je, ji, jk)
      else:
        count[i], c = _count_ball_called(pts, starts, cx, cy, cz, r2, kin2, kout2, nr, js, je)
      if c >= cap:  # room for the c in-ball keys and one overwritten trailing write
        cap = 2 * c + 2
        buf = np.empty(cap, np.int64)
        out = np.empty(cap, np.int64)
        cnt = np.empty(_pow2(cap) + 1, np.int64)
      limit = _rank_limit(k, c, n_rank)
      got = _collect_called(pts, slot_rank, starts, cx, cy, cz, r2, kin2, kout2, limit, nr, js, je,
                            buf)
      if got < min(c, k):  # not enough under the limit: every candidate
        limit = np.int64(1) << 62
        got = _collect_called(pts, slot_rank, starts, cx, cy, cz, r2, kin2, kout2, limit, nr, js,
                              je, buf)
      kept = _smallest_sorted(buf, got, k, cnt, out, min(limit, n_rank))
      for s in range(kept):
        j = out[s] & 0xFFFFFFFF
        offsets[i, s, 0] = pts[0, j] - cx
        offsets[i, s, 1] = pts[1, j] - cy
        offsets[i, s, 2] = pts[2, j] - cz
        mask[i, s] = True
        indices[i, s] = slot_index[j]
      for s in range(kept, k):  # the padding: every element of the row is written
        offsets[i, s, 0] = offsets[i, s, 1] = offsets[i, s, 2] = 0.0
        mask[i, s] = False
        indices[i, s] = -1


def query_order(grid: Grid, centers: np.ndarray) -> np.ndarray:
  """A visiting order of `centers` (m, 3) by grid cell (m,) int64: consecutive queries then
  scan overlapping cells, which stay in the core's caches. Results never depend on it."""
  cell = np.floor((centers - grid.origin) / grid.h)
  cell = np.clip(np.nan_to_num(cell), 0, grid.dims - 1).astype(np.int64)
  return np.argsort((cell[:, 0] * grid.dims[1] + cell[:, 1]) * grid.dims[2] + cell[:, 2],
                    kind="stable")


def _reach(grid: Grid, radius: float) -> int:
  return max(int(np.ceil(float(radius) / grid.h)), 1)


def _centers(centers: np.ndarray) -> np.ndarray:
  return np.ascontiguousarray(centers, np.float64).reshape(-1, 3)


def _keep(radius: float, shells: tuple[float, float] | None) -> tuple[float, float]:
  """(kin2, kout2) squared radii of the kept shells (everything when `shells` is None), widened
  by `_SHELL_SLACK` so that a float32 test of the same thresholds downstream finds every point
  it would find in a full patch."""
  r = float(radius)
  if shells is None:
    return r * r, r * r
  a, b = float(shells[0]) * r * (1 + _SHELL_SLACK), float(shells[1]) * r * (1 - _SHELL_SLACK)
  return a * a, b * b


def ball_counts(grid: Grid, centers: np.ndarray, radius: float,
                shells: tuple[float, float] | None = None) -> np.ndarray:
  """Number of grid points within `radius` of each centre (cKDTree's rule), (m,) int64; with
  `shells=(a, b)`, only those within a * radius or beyond b * radius count."""
  r = float(radius)
  kin2, kout2 = _keep(r, shells)
  c = _centers(centers)
  return _ball_counts(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, c,
                      query_order(grid, c), r, _reach(grid, r), kin2, kout2)[1]


def ball_stats(grid: Grid, centers: np.ndarray, radius: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Float64 statistics of every ball of `radius` around `centers` (m, 3).

  Returns:
    (count (m,) int64, centroid offset (m, 3), covariance about the centroid (m, 3, 3)), the
    offsets taken relative to the centre (numerically stable far from the origin); zeros for an
    empty ball.
  """
  r = float(radius)
  return _ball_stats(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, _centers(centers),
                     r, _reach(grid, r))


def patches(grid: Grid, centers: np.ndarray, radius: float, k: int, inner_radius: float,
            shells: tuple[float, float] | None = None,
            into: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
            count: np.ndarray | None = None) -> dict[str, np.ndarray | None]:
  """The fields of `neighborhoods.Patches` for balls of `radius` around `centers`.

  Args:
    grid: a `Grid` whose ranks are the subsample priority order.
    centers: (m, 3) query points.
    radius: ball radius r (cloud units).
    k: patch size K >= 1; balls of more points keep the K of smallest rank, sorted by rank.
    inner_radius: radius of the normal-support statistics.
    shells: (a, b): the patch holds only the in-ball points within a * radius or beyond
      b * radius (a method that reads nothing in between); None: every in-ball point.
    into: optional (offsets, mask, indices) arrays of the returned shapes and dtypes to write
      into instead of new ones (e.g. rows of a larger array); every element is written (the
      padding as zeros, False and -1), so their contents on entry do not matter.
    count: optional (m,) in-ball counts of these centres and radius, from an earlier call on the
      same points (counts do not depend on the ranks); the count and inner-statistics passes are
      then skipped. Not with `shells`.

  Returns:
    dict with offsets (m, K, 3) float32, mask (m, K) bool, indices (m, K) int32 (-1 padding),
    count (m,) int64 (every point within radius, whatever `shells`), z_count (m,) int64, z_mean
    (m, 3) and z_cov (m, 3, 3) float64 (these three None when `count` is given).
  """
  n = grid.xyz.shape[1]
  if n >= 2**31:
    raise ValueError(f"points: the engine indexes at most 2**31 - 1 points, got {n}")
  c = _centers(centers)
  m, k = c.shape[0], int(k)
  if into is None:
    # Uninitialised: the kernel writes every element, and the threads fault the pages in.
    into = (np.empty((m, k, 3), np.float32), np.empty((m, k), bool), np.empty((m, k), np.int32))
  shapes = [a.shape for a in into]
  if shapes != [(m, k, 3), (m, k), (m, k)] or [a.dtype for a in into] != [np.float32, bool,
                                                                          np.int32]:
    raise ValueError(f"into: expected float32 ({m}, {k}, 3), bool ({m}, {k}), int32 ({m}, {k}) "
                     f"arrays, got {[(a.dtype.name, a.shape) for a in into]}")
  known = count is not None
  if known:
    if shells is not None:
      raise ValueError("count: known counts hold every in-ball point; not with shells")
    count = np.array(count, np.int64).reshape(-1)
    if count.shape != (m,):
      raise ValueError(f"count: expected ({m},) counts, got shape {count.shape}")
  out = dict(
      offsets=into[0],
      mask=into[1],
      indices=into[2],
      count=count if known else np.zeros(m, np.int64),
      z_count=None if known else np.zeros(m, np.int64),
      z_mean=None if known else np.zeros((m, 3)),
      z_cov=None if known else np.zeros((m, 3, 3)),
  )
  z = ((np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))) if known else
       (out["z_count"], out["z_mean"], out["z_cov"]))
  r, rz = float(radius), float(inner_radius)
  _patch_kernel(grid.xyz, grid.slot_index, grid.slot_rank, grid.starts, grid.origin, grid.h,
                grid.dims, c, query_order(grid, c), r, rz, k, n, _reach(grid, r),
                _reach(grid, rz), *_keep(r, shells), known, out["offsets"], out["mask"],
                out["indices"], out["count"], *z)
  return out


# ---------------------------------------------------------------------------------------------
# Nearest neighbours.


@nb.njit(inline="always")
def _insert(bd, bi, k, d2, j):
  """Insert (d2, j) into the ascending arrays bd, bi of length k (ties: smaller j first)."""
  if d2 > bd[k - 1] or (d2 == bd[k - 1] and j >= bi[k - 1]):
    return
  p = k - 1
  while p > 0 and (bd[p - 1] > d2 or (bd[p - 1] == d2 and bi[p - 1] > j)):
    bd[p] = bd[p - 1]
    bi[p] = bi[p - 1]
    p -= 1
  bd[p] = d2
  bi[p] = j


@nb.njit(inline="always")
def _outside(i, d):
  """How many cells index i lies outside 0..d-1."""
  return -i if i < 0 else (i - d + 1 if i > d - 1 else 0)


@nb.njit(inline="always")
def _knn_cells(pts, slot_index, starts, base, z0, z1, qx, qy, qz, max_d2, bd, bi, k):
  if z0 > z1:
    return
  for j in range(starts[base + z0], starts[base + z1 + 1]):
    dx = pts[0, j] - qx
    dy = pts[1, j] - qy
    dz = pts[2, j] - qz
    d2 = dx * dx + dy * dy + dz * dz
    if d2 <= max_d2:
      _insert(bd, bi, k, d2, slot_index[j])


@nb.njit(inline="always")
def _knn_query(pts, slot_index, starts, origin, h, dims, qx, qy, qz, k, max_d2, bd, bi):
  """The k nearest grid points of one query into bd, bi (ascending; inf / n where missing), by
  growing cubes of cells around the query's cell."""
  n = pts.shape[1]
  for t in range(k):
    bd[t] = np.inf
    bi[t] = n
  ix = _cell(qx, origin[0], h)
  iy = _cell(qy, origin[1], h)
  iz = _cell(qz, origin[2], h)
  # Start at the first ring that reaches the grid (a query may lie far outside it).
  ring = max(_outside(ix, dims[0]), max(_outside(iy, dims[1]), _outside(iz, dims[2])))
  while True:
    for a in range(max(ix - ring, 0), min(ix + ring, dims[0] - 1) + 1):
      for b in range(max(iy - ring, 0), min(iy + ring, dims[1] - 1) + 1):
        base = (a * dims[1] + b) * dims[2]
        if abs(a - ix) == ring or abs(b - iy) == ring:  # a side of the shell: whole column
          _knn_cells(pts, slot_index, starts, base, max(iz - ring, 0),
                     min(iz + ring, dims[2] - 1), qx, qy, qz, max_d2, bd, bi, k)
        else:  # inside: only the shell's two z faces
          if 0 <= iz - ring < dims[2]:
            _knn_cells(pts, slot_index, starts, base, iz - ring, iz - ring, qx, qy, qz,
                       max_d2, bd, bi, k)
          if ring > 0 and 0 <= iz + ring < dims[2]:
            _knn_cells(pts, slot_index, starts, base, iz + ring, iz + ring, qx, qy, qz,
                       max_d2, bd, bi, k)
    # Every point not yet scanned lies outside the cube of cells ix +- ring.
    g = np.inf
    g = min(g, qx - (origin[0] + (ix - ring) * h), origin[0] + (ix + ring + 1) * h - qx)
    g = min(g, qy - (origin[1] + (iy - ring) * h), origin[1] + (iy + ring + 1) * h - qy)
    g = min(g, qz - (origin[2] + (iz - ring) * h), origin[2] + (iz + ring + 1) * h - qz)
    g = g * (1.0 - _PRUNE_MARGIN)
    if g > 0.0 and (g * g >= bd[k - 1] or g * g >= max_d2):
      break
    if (ix - ring <= 0 and ix + ring >= dims[0] - 1 and iy - ring <= 0
        and iy + ring >= dims[1] - 1 and iz - ring <= 0 and iz + ring >= dims[2] - 1):
      break  # the cube holds the whole grid
    ring += 1


@nb.njit(parallel=True, cache=True)
def _knn_kernel(pts, slot_index, starts, origin, h, dims, queries, k, max_d2, out_d, out_i):
  """k nearest grid points of each query (`_knn_query`)."""
  m = queries.shape[0]
  nblock = (m + _BLOCK - 1) // _BLOCK
  for blk in nb.prange(nblock):
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    for i in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      _knn_query(pts, slot_index, starts, origin, h, dims, queries[i, 0], queries[i, 1],
                 queries[i, 2], k, max_d2, bd, bi)
      for t in range(k):
        out_d[i, t] = np.sqrt(bd[t])
        out_i[i, t] = bi[t]


def knn(grid: Grid, queries: np.ndarray, k: int, max_distance: float = np.inf
        ) -> tuple[np.ndarray, np.ndarray]:
  """The k nearest grid points of each query, as `cKDTree.query(queries, k)` returns them.

  Args:
    grid: a `Grid` of the cloud (any cell size; `knn_grid` picks a good one).
    queries: (m, 3) query points.
    k: neighbours per query (>= 1).
    max_distance: neighbours farther than this are not returned.

  Returns:
    (distances (m, k) float64 ascending, indices (m, k) int64 point indices); missing neighbours
    have distance inf and index n (cKDTree's convention). Equal distances: smaller index first.
  """
  q = _centers(queries)
  m, k = q.shape[0], int(k)
  out_d = np.empty((m, k))
  out_i = np.empty((m, k), np.int64)
  md = float(max_distance)
  _knn_kernel(grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h, grid.dims, q, k,
              md * md if np.isfinite(md) else np.inf, out_d, out_i)
  return out_d, out_i


def knn_grid(points: np.ndarray, k: int = 8) -> Grid:
  """A grid whose occupied cells hold about k points each (good for `knn` with that k).

  Starts from cells of the bounding box's volume per point and refines while the occupied cells
  hold more than 2 k points on average (surface clouds fill few cells).
  """
  pts = np.ascontiguousarray(points, np.float64)
  n = max(pts.shape[0], 1)
  extent = np.ptp(pts, axis=0) if pts.shape[0] else np.ones(3)
  ext = np.maximum(extent, max(float(extent.max()), 1e-300) * 1e-3)
  h = float(np.prod(ext) / n * max(k, 1)) ** (1.0 / 3.0)
  if not np.isfinite(h) or h <= 0.0:
    h = 1.0
  for _ in range(4):
    grid = Grid(pts, h)
    occupied = int(np.count_nonzero(np.diff(grid.starts)))
    per_cell = n / max(occupied, 1)
    if per_cell <= 2 * max(k, 1):
      break
    h /= np.sqrt(per_cell / max(k, 1))
  return grid


@nb.njit(inline="always")
def nearest_moved(pts, slot_index, starts, origin, h, dims, p, rot, trans, max_d2, bd, bi):
  """The point p moved by (rot, trans) and the index of its nearest grid point within
  sqrt(max_d2) (`knn` with k = 1; the number of points when there is none), its squared
  distance in bd[0]: the pairing step of every ICP kernel."""
  qx = rot[0, 0] * p[0] + rot[0, 1] * p[1] + rot[0, 2] * p[2] + trans[0]
  qy = rot[1, 0] * p[0] + rot[1, 1] * p[1] + rot[1, 2] * p[2] + trans[1]
  qz = rot[2, 0] * p[0] + rot[2, 1] * p[1] + rot[2, 2] * p[2] + trans[2]
  _knn_query(pts, slot_index, starts, origin, h, dims, qx, qy, qz, 1, max_d2, bd, bi)
  return qx, qy, qz, bi[0]


@nb.njit(parallel=True, cache=True)
def _icp_sums(pts, slot_index, starts, origin, h, dims, target, source, rot, trans, c0, max_d2,
              partial):
  """Per block of source points: the sums of one ICP step over the pairs (moved source point,
  its nearest target point within sqrt(max_d2), as `knn`), coordinates relative to c0."""
  m = source.shape[0]
  n = pts.shape[1]
  for blk in nb.prange(partial.shape[0]):
    bd = np.empty(1)
    bi = np.empty(1, np.int64)
    acc = partial[blk]
    acc[:] = 0.0
    for i in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      qx, qy, qz, j = nearest_moved(pts, slot_index, starts, origin, h, dims, source[i], rot,
                                    trans, max_d2, bd, bi)
      if j >= n:
        continue
      a0, a1, a2 = qx - c0[0], qy - c0[1], qz - c0[2]
      b0, b1, b2 = target[j, 0] - c0[0], target[j, 1] - c0[1], target[j, 2] - c0[2]
      acc[0] += 1.0
      acc[1] += bd[0]
      acc[2] += a0
      acc[3] += a1
      acc[4] += a2
      acc[5] += b0
      acc[6] += b1
      acc[7] += b2
      acc[8] += a0 * b0
      acc[9] += a0 * b1
      acc[10] += a0 * b2
      acc[11] += a1 * b0
      acc[12] += a1 * b1
      acc[13] += a1 * b2
      acc[14] += a2 * b0
      acc[15] += a2 * b1
      acc[16] += a2 * b2


def icp_sums(grid: Grid, source: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
             max_distance: float, center: np.ndarray
             ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray]:
  """One ICP step's statistics without materialising the pairs.

  Each source point s is moved to a = R s + t and paired with its nearest grid point b within
  `max_distance` (ties: the smaller index, as `knn`); unpaired points are left out.

  Args:
    grid: `Grid` of the target cloud (any cell size).
    source: (n, 3) source points.
    rotation: (3, 3) R.
    translation: (3,) t.
    max_distance: pairing distance (cloud units).
    center: (3,) the sums are taken of a - center and b - center (pick a point near the clouds:
      it keeps the float64 sums well conditioned).

  Returns:
    (pairs, sum of squared pair distances, sum_a (3,), sum_b (3,), sum of a bᵀ (3, 3)).
  """
  src = _centers(source)
  r = float(max_distance)
  nblock = max(1, (len(src) + _BLOCK - 1) // _BLOCK)
  partial = np.empty((nblock, 17))
  _icp_sums(grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h, grid.dims, grid.points,
            src, np.ascontiguousarray(rotation, np.float64),
            np.ascontiguousarray(translation, np.float64),
            np.ascontiguousarray(center, np.float64), r * r if np.isfinite(r) else np.inf,
            partial)
  acc = partial.sum(axis=0)
  return int(acc[0]), float(acc[1]), acc[2:5], acc[5:8], acc[8:17].reshape(3, 3)


@nb.njit(parallel=True, cache=True)
def _any_within(pts, starts, origin, h, dims, queries, r, reach):
  m = queries.shape[0]
  out = np.zeros(m, np.bool_)
  r2 = r * r
  ncol = (2 * reach + 1) ** 2
  nblock = (m + _BLOCK - 1) // _BLOCK
  for blk in nb.prange(nblock):
    js = np.empty(ncol, np.int64)
    je = np.empty(ncol, np.int64)
    for i in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      cx, cy, cz = queries[i, 0], queries[i, 1], queries[i, 2]
      nr = _columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
      found = False
      for q in range(nr):
        for j in range(starts[js[q]], starts[je[q]]):
          dx = pts[0, j] - cx
          dy = pts[1, j] - cy
          dz = pts[2, j] - cz
          if dx * dx + dy * dy + dz * dz <= r2:
            found = True
            break
        if found:
          break
      out[i] = found
  return out


def any_within(grid: Grid, queries: np.ndarray, radius: float) -> np.ndarray:
  """(m,) bool: whether any grid point lies within `radius` of each query (stops at the first)."""
  r = float(radius)
  return _any_within(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, _centers(queries), r,
                     _reach(grid, r))


@nb.njit(parallel=True, cache=True)
def _ball_fill(pts, slot_index, starts, origin, h, dims, centers, order, r, reach, kin2, kout2,
               ptr, out):
  """The in-ball point indices of each centre (as `_ball_counts` counts them) into out[ptr[i]:],
  centres visited in `order`."""
  m = centers.shape[0]
  r2 = r * r
  ncol = (2 * reach + 1) ** 2
  nblock = (m + _BLOCK - 1) // _BLOCK
  for blk in nb.prange(nblock):
    js = np.empty(ncol, np.int64)
    je = np.empty(ncol, np.int64)
    for t in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      i = order[t]
      cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
      nr = _columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
      w = ptr[i]
      for q in range(nr):
        for j in range(starts[js[q]], starts[je[q]]):
          dx = pts[0, j] - cx
          dy = pts[1, j] - cy
          dz = pts[2, j] - cz
          d2 = dx * dx + dy * dy + dz * dz
          if d2 <= r2 and (d2 <= kin2 or d2 > kout2):
            out[w] = slot_index[j]
            w += 1


def ball_lists(grid: Grid, centers: np.ndarray, radius: float,
               shells: tuple[float, float] | None = None, with_counts: bool = False
               ) -> tuple[np.ndarray, ...]:
  """Every grid point within `radius` of each centre, as compressed rows.

  Args:
    grid: a `Grid` of the cloud.
    centers: (m, 3) ball centres.
    radius: r.
    shells: (a, b): keep only the points within a * r or beyond b * r (as `ball_counts`).
    with_counts: also return the number of points within `radius` of each centre (all of them,
      whatever `shells`), counted in the same pass.

  Returns:
    (ptr (m + 1,) int64, indices (ptr[-1],) int64): the point indices of ball i are
    indices[ptr[i]:ptr[i + 1]], in the grid's slot order (cell, then rank); with `with_counts`,
    (ptr, indices, counts (m,) int64).
  """
  c = _centers(centers)
  r = float(radius)
  order, reach, keep = query_order(grid, c), _reach(grid, r), _keep(r, shells)
  full, counts = _ball_counts(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, c, order, r,
                              reach, *keep)
  ptr = np.zeros(len(c) + 1, np.int64)
  np.cumsum(counts, out=ptr[1:])
  out = np.empty(int(ptr[-1]), np.int64)
  _ball_fill(grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h, grid.dims, c, order, r,
             reach, *keep, ptr, out)
  return (ptr, out, full) if with_counts else (ptr, out)


# ---------------------------------------------------------------------------------------------
# Mesh neighbourhoods.


@nb.njit(parallel=True, cache=True)
def _incident_faces(ball_ptr, ball, vf_ptr, vf, n_faces, n_threads, count_only, out_ptr, out):
  m = ball_ptr.shape[0] - 1
  stamp = np.full((n_threads, max(n_faces, 1)), -1, np.int64)
  for i in nb.prange(m):
    t = nb.get_thread_id()
    c = 0
    w = 0 if count_only else out_ptr[i]
    for e in range(ball_ptr[i], ball_ptr[i + 1]):
      v = ball[e]
      for q in range(vf_ptr[v], vf_ptr[v + 1]):
        f = vf[q]
        if stamp[t, f] != i:
          stamp[t, f] = i
          if not count_only:
            out[w + c] = f
          c += 1
    if count_only:
      out_ptr[i + 1] = c
    else:
      out[w:w + c].sort()


def incident_faces(ball_ptr: np.ndarray, ball: np.ndarray, vf_ptr: np.ndarray, vf: np.ndarray,
                   n_faces: int) -> tuple[np.ndarray, np.ndarray]:
  """The faces incident to any vertex of each ball, each once, sorted by face index.

  Args:
    ball_ptr, ball: compressed rows of vertex indices (as `ball_lists` returns).
    vf_ptr, vf: compressed rows vertex -> incident face indices.
    n_faces: number of faces.

  Returns:
    (ptr (m + 1,), faces (ptr[-1],) int64): the faces of ball i are faces[ptr[i]:ptr[i + 1]].
  """
  bp = np.ascontiguousarray(ball_ptr, np.int64)
  b = np.ascontiguousarray(ball, np.int64)
  fp = np.ascontiguousarray(vf_ptr, np.int64)
  f = np.ascontiguousarray(vf, np.int64)
  ptr = np.zeros(len(bp), np.int64)
  threads = nb.get_num_threads()
  _incident_faces(bp, b, fp, f, int(n_faces), threads, True, ptr, np.zeros(0, np.int64))
  np.cumsum(ptr, out=ptr)
  out = np.empty(int(ptr[-1]), np.int64)
  _incident_faces(bp, b, fp, f, int(n_faces), threads, False, ptr, out)
  return ptr, out


@nb.njit(parallel=True, cache=True)
def _fill_triangles(points, faces, centers, rows, slots, face_ids, width, tri, mask, ids):
  for e in nb.prange(rows.shape[0]):
    i, s, t = rows[e], slots[e], face_ids[e]
    for a in range(3):
      v = faces[t, a]
      for d in range(3):
        tri[i, s, a, d] = points[v, d] - centers[i, d]
    mask[i, s] = True
    ids[i, s] = t


def fill_triangles(points: np.ndarray, faces: np.ndarray, centers: np.ndarray, rows: np.ndarray,
                   slots: np.ndarray, face_ids: np.ndarray, width: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Padded triangle patches: tri[i, s] = the vertices of face face_ids[e] minus centers[i] for
  each entry e = (rows[e] = i, slots[e] = s).

  Returns:
    (tri (m, width, 3, 3) float32, mask (m, width) bool, ids (m, width) int64, -1 in padding).
  """
  m = len(centers)
  tri = np.zeros((m, width, 3, 3), np.float32)
  mask = np.zeros((m, width), bool)
  ids = np.full((m, width), -1, np.int64)
  _fill_triangles(np.ascontiguousarray(points, np.float64), np.ascontiguousarray(faces, np.int64),
                  np.ascontiguousarray(centers, np.float64), np.asarray(rows, np.int64),
                  np.asarray(slots, np.int64), np.asarray(face_ids, np.int64), int(width), tri,
                  mask, ids)
  return tri, mask, ids
