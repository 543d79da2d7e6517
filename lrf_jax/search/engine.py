"""The compiled neighborhood engine: uniform-grid radius and nearest-neighbor search (numba).

This module is the engine's interface, one namespace for its callers (`from lrf_jax.search import
engine`); the kernels are in `grid.py` (the `Grid`, threads), `balls.py` (ball counts, moment
statistics, the patch kernel), `ball_lists.py` (ball lists, any-within) and `nearest.py` (k
nearest neighbors).
Every radius and nearest-neighbor query of `compute_frames`, training, the descriptors and
`register` goes through it; the evaluation's ground-truth pairs and the tests' references use
scipy's cKDTree. Host code, compiled once by numba (`cache=True`: the machine code is stored on
disk and reused by later processes) and multi-threaded over query points (`run_blocks`);
results do not depend on the thread count or the search order.
"""

from __future__ import annotations

from lrf_jax.search.ball_lists import any_within, ball_lists
from lrf_jax.search.balls import (NO_MOMENTS, add_moment, ball_counts, ball_stats, patches,
                                  store_moments)
from lrf_jax.search.grid import Grid, num_threads, query_order, run_blocks, set_num_threads
from lrf_jax.search.nearest import knn, knn_grid, nearest_moved

__all__ = [
    "Grid", "NO_MOMENTS", "add_moment", "any_within", "ball_counts", "ball_lists", "ball_stats",
    "knn", "knn_grid", "nearest_moved", "num_threads", "patches", "query_order", "run_blocks",
    "set_num_threads", "store_moments",
]
