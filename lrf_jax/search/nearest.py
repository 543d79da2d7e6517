"""The compiled engine's nearest-neighbor queries (`knn`, and the ICP kernels' pairing step).

Nearest-neighbor queries (ICP pairs, mesh areas, the normal-orientation graph) grow the scanned
cube of cells ring by ring around the query's cell until the k-th distance found (or the bound)
is within the ring's guaranteed radius.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax.search.grid import (PRUNE_MARGIN, Grid, as_points, run_blocks, task_jit,
                                 unclamped_cell)


@nb.njit(inline="always")
def insert_sorted(bd, bi, k, d2, j):
  """Insert (d2, j) into the ascending arrays bd, bi of length k (ties: smaller j first); shared
  by the k-NN kernels here and the descriptor matching kernel."""
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
      insert_sorted(bd, bi, k, d2, slot_index[j])


@nb.njit(inline="always")
def _gap(q, o, h, c, d):
  """The distance from coordinate q to cell c's slab [o + c h, o + (c + 1) h) along one axis; the
  first and last cells reach to infinity (the binning clamps coordinates into them)."""
  lo = o + c * h
  if c > 0 and q < lo:
    return lo - q
  hi = lo + h
  if c < d - 1 and q > hi:
    return q - hi
  return 0.0


@nb.njit(inline="always")
def _beyond(gap2, kth_d2, max_d2, slack):
  """Whether a cell whose box lies sqrt(gap2) from the query can hold no point within the k-th
  distance found so far (or the bound): pruned with a margin (`slack` plus `PRUNE_MARGIN` of
  the distance) that covers the rounding of the cell boundaries, so that no point as near as the
  k-th (a tie included) is skipped."""
  bound2 = min(kth_d2, max_d2)
  if not bound2 < np.inf:
    return False
  reach = np.sqrt(bound2) * (1.0 + PRUNE_MARGIN) + slack
  return gap2 > reach * reach


@nb.njit(inline="always")
def _knn_query(pts, slot_index, starts, origin, h, dims, qx, qy, qz, k, max_d2, bd, bi):
  """The k nearest grid points of one query into bd, bi (ascending; inf / n where missing), by
  growing cubes of cells around the query's cell."""
  n = pts.shape[1]
  for t in range(k):
    bd[t] = np.inf
    bi[t] = n
  ix = unclamped_cell(qx, origin[0], h)
  iy = unclamped_cell(qy, origin[1], h)
  iz = unclamped_cell(qz, origin[2], h)
  # Start at the first ring that reaches the grid (a query may lie far outside it).
  ring = max(_outside(ix, dims[0]), max(_outside(iy, dims[1]), _outside(iz, dims[2])))
  slack = PRUNE_MARGIN * h
  while True:
    for a in range(max(ix - ring, 0), min(ix + ring, dims[0] - 1) + 1):
      gx = _gap(qx, origin[0], h, a, dims[0])
      for b in range(max(iy - ring, 0), min(iy + ring, dims[1] - 1) + 1):
        gy = _gap(qy, origin[1], h, b, dims[1])
        if _beyond(gx * gx + gy * gy, bd[k - 1], max_d2, slack):
          continue  # the whole column lies farther than the k-th point found
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
    g = g * (1.0 - PRUNE_MARGIN)
    if g > 0.0 and (g * g >= bd[k - 1] or g * g >= max_d2):
      break
    if (ix - ring <= 0 and ix + ring >= dims[0] - 1 and iy - ring <= 0
        and iy + ring >= dims[1] - 1 and iz - ring <= 0 and iz + ring >= dims[2] - 1):
      break  # the cube holds the whole grid
    ring += 1


# Every ICP pairing step (`nearest_moved`) calls the query instead of inlining it: compiled once
# instead of once per ICP kernel (the point-to-plane sums' first compile measured 18.6 -> 6.8 s,
# the same warm time), without reference counting (`task_jit`: no atomic counts contended by the
# threads at every call).
_knn_query_called = task_jit(_knn_query.py_func)


@task_jit
def _knn_block(pts, slot_index, starts, origin, h, dims, queries, k, max_d2, out_d, out_i, lo,
               hi, bd, bi):
  """Queries lo..hi-1 of `knn` into out_d, out_i (bd, bi: scratch of length k); the engine's
  threads run it on spans of the queries (`grid.run_blocks`)."""
  for i in range(lo, hi):
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
    k: neighbors per query (>= 1).
    max_distance: neighbors farther than this are not returned.

  Returns:
    (distances (m, k) float64 ascending, indices (m, k) int64 point indices); missing neighbors
    have distance inf and index n (cKDTree's convention). Equal distances: smaller index first.
  """
  q = as_points(queries)
  m, k = q.shape[0], int(k)
  out_d = np.empty((m, k))
  out_i = np.empty((m, k), np.int64)
  md = float(max_distance)
  args = (grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h, grid.dims, q, k,
          md * md if np.isfinite(md) else np.inf, out_d, out_i)
  run_blocks(lambda lo, hi: _knn_block(*args, lo, hi, np.empty(k), np.empty(k, np.int64)), m)
  return out_d, out_i


def knn_grid(points: np.ndarray, k: int = 8) -> Grid:
  """A grid whose occupied cells hold about k points each (good for `knn` with that k).

  Starts from cells of the bounding box's volume per point and refines while the occupied cells
  hold more than 2 k points on average (surface clouds fill few cells).
  """
  pts = np.ascontiguousarray(points, np.float64)
  n = max(pts.shape[0], 1)
  # per column: numpy's axis-0 reductions of an (n, 3) array are about 50x slower
  extent = np.array([np.ptp(pts[:, j]) for j in range(3)]) if pts.shape[0] else np.ones(3)
  ext = np.maximum(extent, max(float(extent.max()), 1e-300) * 1e-3)
  h = float(np.prod(ext) / n * max(k, 1)) ** (1.0 / 3.0)
  if not np.isfinite(h) or h <= 0.0:
    h = 1.0
  for _ in range(4):
    grid = Grid(pts, h)
    if grid.h > h * (1.0 + 1e-3):  # the cell count bound enlarged the cells: none finer
      break
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
  _knn_query_called(pts, slot_index, starts, origin, h, dims, qx, qy, qz, 1, max_d2, bd, bi)
  return qx, qy, qz, bi[0]
