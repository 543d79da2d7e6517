"""The compiled engine's grid: points binned in cubic cells, and the engine's threads.

The engine (`lrf_jax.search.engine` gathers its interface) is host code, compiled once by numba
(`cache=True`: the machine code is stored on disk and reused by later processes) and
multi-threaded over query points (`run_blocks`: spans of queries on a thread pool, each span one
call of a compiled function that releases the GIL). Its radius queries and patches are in
`balls.py`, its nearest-neighbor queries in `nearest.py`, both on the `Grid` of this module.

* A `Grid` bins the cloud into cubic cells of side h (the patch search uses h = r / 3) and
  stores the points sorted by (cell, rank) with a counting sort, O(n), one row per coordinate.
  `rank` is any permutation of the point indices; the patch search uses the seeded priority
  order of `hash_priority`, so that within every cell the points come in priority order.

Threads: `set_num_threads(n)` or the environment variable `LRF_JAX_NUM_THREADS` (read at import);
the default is every core numba sees. Results do not depend on the thread count: each query's
output is computed by one thread, in a fixed order.

Memory: the grid holds the cloud once more in float64 plus O(n + cells) int64; the number of
cells is bounded by `max(8 n, 4096)` (h grows past r when a tiny radius would need more), so a
far-flung cloud with a tiny radius costs time, never an unbounded table.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Any

import numba as nb
import numpy as np

from lrf_jax import compilation_cache

compilation_cache.announce_compiles()  # one stderr line when a kernel is compiled (a cache miss)

_ENV_THREADS = "LRF_JAX_NUM_THREADS"
# Cells are enlarged by this factor over the requested side (a cell side is a speed setting:
# ball queries prune columns with their own margin, `PRUNE_MARGIN`).
_CELL_MARGIN = 1e-6
BLOCK = 32  # queries per block: `run_blocks` hands out spans of whole blocks

# A kernel's task (a span of queries, run by `run_blocks`), compiled on its own: cached once per
# machine, releasing the GIL, and without numba's reference counting, so a task allocates
# nothing (its scratch comes from the caller); with reference counting a task ran 2x slower
# (the shared arrays' counts are atomics, contended between the threads). A task that must
# allocate (scratch that grows with a ball) keeps the counting: `nb.njit(cache=True,
# nogil=True)`. numba's stubs omit `_nrt`.
task_jit = nb.njit(cache=True, _nrt=False, nogil=True)  # type: ignore[call-overload]
# Columns are pruned with a radius enlarged by this factor: a point's cell comes from a rounded
# division, its column's box from a rounded product; the margin keeps every in-ball point
# (read by the ball and nearest-neighbor kernels of `balls.py` and `nearest.py`).
PRUNE_MARGIN = 1e-5


def num_threads() -> int:
  """The number of threads the engine's kernels use."""
  return int(nb.get_num_threads())


_POOL: dict[str, Any] = {"helpers": 0, "pool": None}  # the helper threads of `run_blocks`
_POOL_LOCK = threading.Lock()


def _spans(m: int, block: int, threads: int) -> list[tuple[int, int]]:
  """[0, m) cut into spans of whole blocks, largest first: each span holds 1 / (2 threads) of
  the blocks still left (at least one block), so the threads end together within a block
  (guided scheduling: few calls, a short tail)."""
  nblock = -(-m // block)
  out, start = [], 0
  while start < nblock:
    size = max(1, (nblock - start) // (2 * threads))
    out.append((start * block, min(m, (start + size) * block)))
    start += size
  return out


def run_blocks(task: Callable[[int, int], object], m: int, block: int = BLOCK) -> None:
  """Call `task(lo, hi)` over the query range [0, m) in spans of whole blocks (`block` queries:
  lo is a multiple of it) on the engine's threads (`num_threads`: the calling thread and
  helpers of a pool kept for the process); every query lies in exactly one call.

  The task is a compiled function that releases the GIL (`task_jit`): the threads run it at
  once, each taking the next span (`_spans`) until none is left. A kernel threaded this way
  compiles without `parallel=True`, whose own passes cost each kernel 1-3 s of compile; its
  output does not depend on the thread count (each query is computed by one call, in a fixed
  order)."""
  threads = num_threads()
  if threads <= 1 or m <= block:
    if m > 0:
      task(0, m)
    return
  spans = _spans(m, block, threads)
  lock = threading.Lock()
  left = list(reversed(spans))

  def work() -> None:
    while True:
      with lock:
        if not left:
          return
        lo, hi = left.pop()
      task(lo, hi)

  helpers = min(threads, len(spans)) - 1
  with _POOL_LOCK:  # callers on several threads share the pool; a smaller one is dropped (its
    if _POOL["helpers"] < helpers:  # threads end once it is collected), never shut under them
      _POOL.update(helpers=helpers, pool=ThreadPoolExecutor(helpers, "lrf_jax-engine"))
    futures = [_POOL["pool"].submit(work) for _ in range(helpers)]
  try:
    work()
  finally:
    wait(futures)
  for f in futures:
    f.result()  # a helper's error


def serial_blas() -> contextlib.AbstractContextManager:
  """numpy's BLAS on one thread inside the `with` block. For numpy products between the engine's
  kernels: BLAS threads that wait by spinning and numba's threads slow each other down (on 2
  cores, 1000 x 1000 matrix-vector products took 1.6 ms threaded and 0.08 ms on one thread; the
  learned weight table, 257^2 evaluations of a small network, 0.5-3.9 s threaded after a kernel
  had run and 0.15 s on one thread)."""
  from threadpoolctl import threadpool_limits
  return threadpool_limits(1, user_api="blas")


def set_num_threads(n: int | None = None) -> int:
  """Set the engine's thread count (None: every core numba sees); returns the count set.

  Raises:
    ValueError: `n` not a positive integer.
  """
  # numba.config sets its attributes from the environment at run time: no static declaration
  limit = int(nb.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
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
    pts = writable_float64(points)
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


@nb.njit(inline="always")
def unclamped_cell(x, o, h):
  """The cell index (int) of coordinate x on an axis whose cells start at o with side h (cloud
  units), not clamped to the grid (it may be negative or past the last cell) but bounded to
  +-2**40 so that it fits an int64."""
  return int(min(max(np.floor((x - o) / h), -1099511627776.0), 1099511627776.0))


def query_order(grid: Grid, centers: np.ndarray) -> np.ndarray:
  """A visiting order of `centers` (m, 3) by grid cell (m,) int64: consecutive queries then
  scan overlapping cells, which stay in the core's caches. Results never depend on it."""
  cell = np.floor((centers - grid.origin) / grid.h)
  cell = np.clip(np.nan_to_num(cell), 0, grid.dims - 1).astype(np.int64)
  return np.argsort((cell[:, 0] * grid.dims[1] + cell[:, 1]) * grid.dims[2] + cell[:, 2],
                    kind="stable")


def cell_reach(grid: Grid, radius: float) -> int:
  """The cells (int, >= 1) a ball of `radius` (cloud units) reaches each way from its centre's
  cell on `grid`: ceil(radius / grid.h), the `reach` of the ball kernels."""
  return max(int(np.ceil(float(radius) / grid.h)), 1)


def as_points(points: np.ndarray) -> np.ndarray:
  """Query points or centres (any array of 3 m numbers, e.g. (m, 3)) as the (m, 3) C-contiguous,
  writable float64 array the kernels take (`writable_float64`)."""
  return writable_float64(points).reshape(-1, 3)


def writable_float64(a: np.ndarray) -> np.ndarray:
  """`a` as a C-contiguous, writable float64 array (a copy only when it is not one already).

  numba compiles a kernel once per argument type, and a read-only array (a cache's view, a
  broadcast) is a type of its own: every array the engine's kernels read passes through here so
  that each kernel compiles one specialisation on a first run, not two."""
  out = np.ascontiguousarray(a, np.float64)
  return out if out.flags.writeable else out.copy()
