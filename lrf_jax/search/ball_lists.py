"""The compiled engine's ball queries that return lists: every point within r of each centre
(`ball_lists`, compressed rows) and "any point within r" (`any_within`, overlap scores), which
visits the ball's columns and stops at the first point found. Both visit the columns of
`balls.ball_columns` and test with cKDTree's rule, as every ball query of the engine does.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax.search.balls import (ball_columns, full_and_kept_counts, kept_shells,
                                  squared_distance)
from lrf_jax.search.grid import (BLOCK, Grid, as_points, cell_reach, query_order, run_blocks,
                                 task_jit)

@nb.njit(parallel=True, cache=True)
def _any_within(pts, starts, origin, h, dims, queries, r, reach):
  m = queries.shape[0]
  out = np.zeros(m, np.bool_)
  r2 = r * r
  ncol = (2 * reach + 1) ** 2
  nblock = (m + BLOCK - 1) // BLOCK
  for blk in nb.prange(nblock):
    js = np.empty(ncol, np.int64)
    je = np.empty(ncol, np.int64)
    for i in range(blk * BLOCK, min(m, (blk + 1) * BLOCK)):
      cx, cy, cz = queries[i, 0], queries[i, 1], queries[i, 2]
      nr = ball_columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
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
  return _any_within(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, as_points(queries),
                     r, cell_reach(grid, r))


@task_jit  # a span of `ball_lists`' centres (see `grid.task_jit`)
def _ball_fill(pts, slot_index, starts, origin, h, dims, centers, order, r, reach, kin2, kout2,
               ptr, out, lo, hi, js, je):
  """The in-ball point indices of centres order[lo:hi] (as `full_and_kept_counts` counts them)
  into out[ptr[i]:] (js, je: column scratch)."""
  r2 = r * r
  for t in range(lo, hi):
    i = order[t]
    cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
    nr = ball_columns(cx, cy, cz, origin, h, dims, starts, r, reach, js, je)
    w = ptr[i]
    for q in range(nr):
      for j in range(starts[js[q]], starts[je[q]]):
        d2 = squared_distance(pts, j, cx, cy, cz)
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
  c = as_points(centers)
  r = float(radius)
  order, reach, keep = query_order(grid, c), cell_reach(grid, r), kept_shells(r, shells)
  full, counts = full_and_kept_counts(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, c,
                                      order, r, reach, *keep)
  ptr = np.zeros(len(c) + 1, np.int64)
  np.cumsum(counts, out=ptr[1:])
  out = np.empty(int(ptr[-1]), np.int64)
  ncol = (2 * reach + 1) ** 2
  run_blocks(lambda lo, hi: _ball_fill(grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h,
                                       grid.dims, c, order, r, reach, *keep, ptr, out, lo, hi,
                                       np.empty(ncol, np.int64), np.empty(ncol, np.int64)),
             len(c))
  return (ptr, out, full) if with_counts else (ptr, out)
