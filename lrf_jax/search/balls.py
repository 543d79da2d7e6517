"""The compiled engine's ball queries: counts, moment statistics, patches (the ball lists and
any-within are in `ball_lists.py`).

* A ball query of radius r visits the columns (x cell, y cell) within ceil(r / h) cells whose
  box comes within r of the centre, and in each column only the run of consecutive z cells the
  ball's slice can reach (`ball_columns`); every point there is tested with cKDTree's rule:
  float64 squared distance, summed over x, y, z in that order, `<= r * r`. Cells whose box lies
  inside the ball (with a margin) count whole without a test (`_column_runs`).
* The patch kernel writes `Patches` directly: the ball's count, the float64 statistics of the
  inner ball (z_ratio * r: count, centroid, covariance about the centroid) and the K in-ball
  points of smallest rank, sorted by rank. Only the ranks below a limit that the K smallest lie
  under but for about one ball in 10^4 are collected (a cell's scan stops there; a ball the
  limit misses is collected again without it), then bucket-sorted by rank. The subsample is
  therefore exactly the one of `neighborhoods.hash_priority`: the same indices whatever the
  search order, the thread count or the cloud's pose.

Threads: every kernel here is a serial compiled function over a span of the centres, run on
the engine's threads by `grid.run_blocks` (it releases the GIL), not a `parallel=True` kernel:
numba's parallel passes cost each kernel 1-3 s of a first compile. The helpers are inlined
(`inline="always"`): outside a parallel kernel that costs little compile, and without them the
ball lists, normals and k-NN queries run 1.3-5x slower.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

import numba as nb
import numpy as np

from lrf_jax.search.grid import (PRUNE_MARGIN, Grid, as_points, cell_reach, query_order,
                                 run_blocks, task_jit, unclamped_cell)

if TYPE_CHECKING:
  from typing import TypedDict

  import numpy.typing as npt

  class PatchFields(TypedDict):
    """What `patches` returns: the fields of `neighborhoods.Patches` (see there)."""

    offsets: np.ndarray
    mask: np.ndarray
    indices: np.ndarray
    count: np.ndarray
    z_count: np.ndarray | None  # the three None when `patches` is given the counts
    z_mean: np.ndarray | None
    z_cov: np.ndarray | None

_SHELL_SLACK = 1e-5


@nb.njit(inline="always")
def ball_columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je):
  """Cell ranges [js, je) (consecutive cell ids) that may hold points within r of (cx, cy, cz).

  For each column (x cell, y cell) within `reach` cells whose box comes within r of the centre,
  the z cells that the ball's slice through that column can reach; the slots of cells js..je-1
  are starts[js]..starts[je]. Returns the number of ranges.

  The grid's `origin` (3,), cell side `h`, `dims` (3,) and `starts` (cells + 1,) as a `Grid`
  holds them; `reach` = `grid.cell_reach(grid, r)`; js, je: int64 scratch of at least
  (2 reach + 1)^2 entries, the ranges written to their first entries.
  """
  return _column_runs(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, False, js, je)


@nb.njit(inline="always")
def squared_distance(pts, j, cx, cy, cz):
  """The squared distance of slot j (`pts` (3, n)) from (cx, cy, cz) by cKDTree's rule: float64,
  summed over x, y, z in that order."""
  dx = pts[0, j] - cx
  dy = pts[1, j] - cy
  dz = pts[2, j] - cz
  return dx * dx + dy * dy + dz * dz


@nb.njit(inline="always")
def _span(i, reach, dim):
  """The cells [lo, hi) within `reach` of cell i, on an axis of `dim` cells."""
  return max(i - reach, 0), min(i + reach, dim - 1) + 1


@nb.njit(inline="always")
def _gap2(c, lo, h):
  """The squared distance from c to the interval [lo, lo + h] (0 inside it)."""
  d = lo - c if c < lo else (c - lo - h if c > lo + h else 0.0)
  return d * d


@nb.njit(inline="always")
def _far(c, lo, h, e):
  """The largest distance from c to the interval [lo - e, lo + h + e]."""
  return max(c - lo + e, lo + h + e - c)


@nb.njit(inline="always")
def _column_runs(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, inner, ji, jk):
  """`ball_columns`; with `inner`, also the cells [ji, jk) of each range whose whole box lies
  inside the ball, with a margin (relative 1e-9 of r, and of the coordinates' size) that keeps
  every point binned to them within r by cKDTree's float64 rule (ji = jk: none)."""
  rp = r * (1.0 + PRUNE_MARGIN)
  rp2 = rp * rp
  e = 1e-9 * h + 1e-12 * (abs(cx) + abs(cy) + abs(cz) + abs(origin[0]) + abs(origin[1])
                          + abs(origin[2]))
  ri2 = (r * (1.0 - 1e-9)) ** 2
  ix = unclamped_cell(cx, origin[0], h)
  iy = unclamped_cell(cy, origin[1], h)
  a0, a1 = _span(ix, reach, dims[0])
  b0, b1 = _span(iy, reach, dims[1])
  n = 0
  for a in range(a0, a1):
    lox = origin[0] + a * h
    rx = rp2 - _gap2(cx, lox, h)
    if rx < 0.0:
      continue
    for b in range(b0, b1):
      lo = origin[1] + b * h
      rem = rx - _gap2(cy, lo, h)
      if rem < 0.0:
        continue
      t = np.sqrt(rem)
      z0 = max(unclamped_cell(cz - t, origin[2], h), 0)
      z1 = min(unclamped_cell(cz + t, origin[2], h), dims[2] - 1)
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
    c += squared_distance(pts, j, cx, cy, cz) <= r2
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
      d2 = squared_distance(pts, j, cx, cy, cz)
      inside = d2 <= r2
      c += inside
      ck += inside & ((d2 <= kin2) | (d2 > kout2))  # no branches: balls are random
  return c, ck


def full_and_kept_counts(pts, starts, origin, h, dims, centers, order, r, reach, kin2, kout2):
  """(points within r of each centre, those of them within sqrt(kin2) or beyond sqrt(kout2)),
  each (m,) int64, for the m `centers` (m, 3) on a grid's arrays (`pts` its `xyz`, `starts`,
  `origin`, `h`, `dims`); centres visited in `order` (m,), `reach` = `grid.cell_reach(grid, r)`,
  (kin2, kout2) from `kept_shells`; on the engine's threads (`_counts_block`,
  `grid.run_blocks`). The counts of `ball_counts` and, with the lists, of `ball_lists`."""
  m = centers.shape[0]
  full = np.zeros(m, np.int64)
  out = np.zeros(m, np.int64)
  ncol = (2 * reach + 1) ** 2
  run_blocks(lambda lo, hi: _counts_block(pts, starts, origin, h, dims, centers, order, r, reach,
                                          kin2, kout2, full, out, lo, hi,
                                          np.empty(ncol, np.int64), np.empty(ncol, np.int64)), m)
  return full, out


@task_jit  # a span of `full_and_kept_counts`' centres (see `grid.task_jit`)
def _counts_block(pts, starts, origin, h, dims, centers, order, r, reach, kin2, kout2, full, out,
                  lo, hi, js, je):
  """Centres order[lo:hi] of `full_and_kept_counts` (js, je: column scratch)."""
  r2 = r * r
  for t in range(lo, hi):
    i = order[t]
    cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
    nr = ball_columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
    full[i], out[i] = _count_ball(pts, starts, cx, cy, cz, r2, kin2, kout2, nr, js, je)


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


def _ball_stats(pts, starts, origin, h, dims, centers, r, reach):
  """Count, centroid offset and covariance (about the centroid) of each ball, float64, on the
  engine's threads (`_stats_span`, `grid.run_blocks`)."""
  m = centers.shape[0]
  count = np.zeros(m, np.int64)
  mean = np.zeros((m, 3))
  cov = np.zeros((m, 3, 3))
  run_blocks(lambda lo, hi: _stats_span(pts, starts, origin, h, dims, centers, r, reach, count,
                                        mean, cov, lo, hi), m)
  return count, mean, cov


# Allocates (scratch that grows with the balls): numba's reference counting stays on.
@nb.njit(cache=True, nogil=True)
def _stats_span(pts, starts, origin, h, dims, centers, r, reach, count, mean, cov, lo, hi):
  """Balls lo..hi-1 of `_ball_stats`."""
  ncol = (2 * reach + 1) ** 2
  js = np.empty(ncol, np.int64)
  je = np.empty(ncol, np.int64)
  off = np.empty((3, 256))
  for i in range(lo, hi):
    cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
    nr = ball_columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
    off = _room(off, _scanned(starts, nr, js, je))
    count[i] = _stats_one(pts, starts, cx, cy, cz, r * r, nr, js, je, mean[i], cov[i], off)


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


def _patch_kernel(pts, slot_index, slot_rank, starts, origin, h, dims, centers, order, r, rz, k,
                  n_rank, reach, reach_in, kin2, kout2, known, offsets, mask, indices, count,
                  z_count, z_mean, z_cov):
  """`_patch_span` over every centre, in spans on the engine's threads (`grid.run_blocks`)."""
  run_blocks(lambda lo, hi: _patch_span(pts, slot_index, slot_rank, starts, origin, h, dims,
                                        centers, order, r, rz, k, n_rank, reach, reach_in, kin2,
                                        kout2, known, offsets, mask, indices, count, z_count,
                                        z_mean, z_cov, lo, hi), centers.shape[0])


# Allocates (scratch that grows with the balls): numba's reference counting stays on.
@nb.njit(cache=True, nogil=True)
def _patch_span(pts, slot_index, slot_rank, starts, origin, h, dims, centers, order, r, rz, k,
                n_rank, reach, reach_in, kin2, kout2, known, offsets, mask, indices, count,
                z_count, z_mean, z_cov, lo, hi):
  """Patches of the K points of smallest rank within r (of those within sqrt(kin2) or beyond
  sqrt(kout2): all of them when kin2 >= r * r), plus the inner-ball statistics; the centres are
  visited in the order `order` (`query_order`): order[lo:hi], each written whole to its own row
  (padding included: the outputs may start uninitialised). With `known`, count holds the
  in-ball counts already (no shells) and neither they nor the statistics are computed."""
  r2 = r * r
  ncol = (2 * max(reach, reach_in) + 1) ** 2  # the inner radius may exceed r
  js = np.empty(ncol, np.int64)
  je = np.empty(ncol, np.int64)
  ji = np.empty(ncol, np.int64)
  jk = np.empty(ncol, np.int64)
  off = np.empty((3, 256))
  cap = 1024
  buf = np.empty(cap, np.int64)
  out = np.empty(cap, np.int64)
  cnt = np.empty(_pow2(cap) + 1, np.int64)
  for t in range(lo, hi):
    i = order[t]
    cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
    if not known:
      nr = ball_columns(cx, cy, cz, origin, h, dims, starts, rz, reach_in, js, je)
      off = _room(off, _scanned(starts, nr, js, je))
      z_count[i] = _stats_one(pts, starts, cx, cy, cz, rz * rz, nr, js, je, z_mean[i],
                                     z_cov[i], off)
    whole = not known and kin2 >= r2  # no shells: cells inside the ball count whole
    nr = _column_runs(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, whole, ji,
                             jk)
    if known:  # every in-ball point is a candidate (no shells)
      c = count[i]
    elif whole:
      c = count[i] = _count_runs(pts, starts, cx, cy, cz, r2, nr, js, je, ji, jk)
    else:
      count[i], c = _count_ball(pts, starts, cx, cy, cz, r2, kin2, kout2, nr, js, je)
    if c >= cap:  # room for the c in-ball keys and one overwritten trailing write
      cap = 2 * c + 2
      buf = np.empty(cap, np.int64)
      out = np.empty(cap, np.int64)
      cnt = np.empty(_pow2(cap) + 1, np.int64)
    limit = _rank_limit(k, c, n_rank)
    got = _collect(pts, slot_rank, starts, cx, cy, cz, r2, kin2, kout2, limit, nr, js, je,
                          buf)
    if got < min(c, k):  # not enough under the limit: every candidate
      limit = np.int64(1) << 62
      got = _collect(pts, slot_rank, starts, cx, cy, cz, r2, kin2, kout2, limit, nr, js,
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


def kept_shells(radius: float, shells: tuple[float, float] | None) -> tuple[float, float]:
  """(kin2, kout2) squared radii (floats, cloud units squared) of the kept shells, a ball of
  `radius` keeping its points within sqrt(kin2) or beyond sqrt(kout2) (everything when `shells`
  is None; (a, b): within a * radius or beyond b * radius), widened by `_SHELL_SLACK` so that
  a float32 test of the same thresholds downstream finds every point it would find in a full
  patch."""
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
  kin2, kout2 = kept_shells(r, shells)
  c = as_points(centers)
  return full_and_kept_counts(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, c,
                              query_order(grid, c), r, cell_reach(grid, r), kin2, kout2)[1]


def ball_stats(grid: Grid, centers: np.ndarray, radius: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Float64 statistics of every ball of `radius` around `centers` (m, 3).

  Returns:
    (count (m,) int64, centroid offset (m, 3), covariance about the centroid (m, 3, 3)), the
    offsets taken relative to the centre (numerically stable far from the origin); zeros for an
    empty ball.
  """
  r = float(radius)
  return _ball_stats(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, as_points(centers),
                     r, cell_reach(grid, r))


def patches(grid: Grid, centers: np.ndarray, radius: float, k: int, inner_radius: float,
            shells: tuple[float, float] | None = None,
            into: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
            count: npt.ArrayLike | None = None) -> PatchFields:
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
  c = as_points(centers)
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
  out: PatchFields = dict(
      offsets=into[0],
      mask=into[1],
      indices=into[2],
      count=cast("np.ndarray", count) if known else np.zeros(m, np.int64),  # converted above
      z_count=None if known else np.zeros(m, np.int64),
      z_mean=None if known else np.zeros((m, 3)),
      z_cov=None if known else np.zeros((m, 3, 3)),
  )
  z = ((np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))) if known else
       (out["z_count"], out["z_mean"], out["z_cov"]))
  r, rz = float(radius), float(inner_radius)
  _patch_kernel(grid.xyz, grid.slot_index, grid.slot_rank, grid.starts, grid.origin, grid.h,
                grid.dims, c, query_order(grid, c), r, rz, k, n, cell_reach(grid, r),
                cell_reach(grid, rz), *kept_shells(r, shells), known, out["offsets"],
                out["mask"], out["indices"], out["count"], *z)
  return out
