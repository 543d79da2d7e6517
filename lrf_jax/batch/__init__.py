"""Data-set jobs: frames of every scan and registrations of every listed pair, on this machine or
a Ray cluster, resumable, every file written atomically (`lrf-batch`).

    from lrf_jax.batch import run_register
    result = run_register("pairs.tsv", "out/", engine="ray")   # or engine="local"
    result.exit_code, result.rows[0]["success"]

`jobs` holds the job layer (items, records, results.tsv), `items` the work of one item,
`engines` the local and Ray engines.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
  from lrf_jax.batch.engines import ENGINES, LocalEngine, Outcome, RayEngine, make_engine
  from lrf_jax.batch.jobs import (FRAMES_COLUMNS, REGISTER_COLUMNS, JobResult, read_pairs,
                                  run_frames, run_register)

__all__ = ["ENGINES", "FRAMES_COLUMNS", "JobResult", "LocalEngine", "Outcome",
           "REGISTER_COLUMNS", "RayEngine", "make_engine", "read_pairs", "run_frames",
           "run_register"]
_ENGINE_NAMES = ("ENGINES", "LocalEngine", "Outcome", "RayEngine", "make_engine")


def __getattr__(name: str) -> Any:
  """The names above, loaded on first use: `lrf-frames` reads `scan_frames` without loading
  the job layer (and the registration it runs)."""
  if name in _ENGINE_NAMES:
    from lrf_jax.batch import engines
    return getattr(engines, name)
  if name in __all__:
    from lrf_jax.batch import jobs
    return getattr(jobs, name)
  raise AttributeError(f"module 'lrf_jax.batch' has no attribute {name!r}")
