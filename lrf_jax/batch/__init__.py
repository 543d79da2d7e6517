"""Data-set jobs: frames of every scan and registrations of every listed pair, on this machine or
a Ray cluster, resumable, every file written atomically (`lrf-batch`).

    from lrf_jax.batch import run_register
    result = run_register("pairs.tsv", "out/", engine="ray")   # or engine="local"
    result.exit_code, result.rows[0]["success"]

`jobs` holds the job layer (items, records, results.tsv), `items` the work of one item,
`engines` the local and Ray engines.
"""

from lrf_jax.batch.engines import ENGINES, LocalEngine, Outcome, RayEngine, make_engine
from lrf_jax.batch.jobs import (FRAMES_COLUMNS, REGISTER_COLUMNS, JobResult, read_pairs,
                                run_frames, run_register)

__all__ = ["ENGINES", "FRAMES_COLUMNS", "JobResult", "LocalEngine", "Outcome",
           "REGISTER_COLUMNS", "RayEngine", "make_engine", "read_pairs", "run_frames",
           "run_register"]
