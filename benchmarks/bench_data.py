"""Data-layer benchmark: time and peak memory to load BR and to build the training keypoints.

    LRF_DATA=/path/to/data python benchmarks/bench_data.py [--repeats 3]

Each stage runs in a fresh child process (so caches and peak RSS start empty; imports are done
before the clock starts): once per timed repeat and once under tracemalloc for the peak of
Python/numpy allocations. Baselines, measured in the same run: reading the same PLY files with
plain `plyfile.PlyData.read` (slow: about 25 s each; timed once, or skipped with
--skip-baselines). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import resource
import tempfile
import time
import tracemalloc

import numpy as np


def _stage_plyfile_br(root: str) -> int:
  import plyfile
  from lrf_jax.datasets import BR_MODELS, bologna
  files = [bologna.br_model_path(m, root) for m in BR_MODELS]
  folder = files[0].parents[2] / "scenes"
  files += sorted(folder.glob("Scene*_0.[135].ply"))
  for f in files:
    ply = plyfile.PlyData.read(str(f))
    v = ply["vertex"].data
    np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    np.stack(ply["face"].data["vertex_indices"])
  return len(files)


def _stage_read_ply_br(root: str) -> int:
  from lrf_jax import io
  from lrf_jax.datasets import BR_MODELS, bologna
  files = [bologna.br_model_path(m, root) for m in BR_MODELS]
  files += sorted((files[0].parents[2] / "scenes").glob("Scene*_0.[135].ply"))
  for f in files:
    io.read_ply(f)
  return len(files)


def _stage_load_br_all(root: str) -> int:
  from lrf_jax import datasets as ds
  return sum(len(ds.load_br(root, level)) for level in ds.BR_NOISE_LEVELS)


def _stage_load_br_warm(root: str) -> int:
  from lrf_jax import datasets as ds
  ds.load_br(root, 0.0)  # parse the models (not timed separately: see the cold row)
  start = time.perf_counter()
  n = sum(len(ds.load_br(root, level)) for level in ds.BR_NOISE_LEVELS)
  return n, time.perf_counter() - start


def _stage_plyfile_bunny(root: str) -> int:
  import plyfile
  from lrf_jax.datasets import dataset_dir
  files = sorted(dataset_dir("stanford_bunny_scans", root).glob("*.ply"))
  for f in files:
    plyfile.PlyData.read(str(f))
  return len(files)


def _stage_read_ply_bunny(root: str) -> int:
  from lrf_jax import io
  from lrf_jax.datasets import dataset_dir
  files = sorted(dataset_dir("stanford_bunny_scans", root).glob("*.ply"))
  for f in files:
    io.read_ply(f)
  return len(files)


def _stage_training_cold(root: str, cache: str) -> int:
  from lrf_jax import datasets as ds
  return len(ds.build_training_set(root, n_keypoints=20000, cache_dir=cache, use_cache=False))


def _stage_training_cached(root: str, cache: str) -> int:
  from lrf_jax import datasets as ds
  ds.build_training_set(root, n_keypoints=20000, cache_dir=cache)  # make sure it exists
  ds.clear_cache()
  start = time.perf_counter()
  n = len(ds.build_training_set(root, n_keypoints=20000, cache_dir=cache))
  assert ds.cache_info().misses == 0, "the cached build parsed a PLY"
  return n, time.perf_counter() - start


def _child(stage, args, trace, queue):
  import warnings

  import plyfile  # noqa: F401  (imports are not part of the measured time)

  import lrf_jax.datasets  # noqa: F401
  warnings.simplefilter("ignore", UserWarning)  # plyfile's "loadtxt: input contained no data"
  if trace:
    tracemalloc.start()
  start = time.perf_counter()
  out = stage(*args)
  elapsed = time.perf_counter() - start
  if isinstance(out, tuple):  # the stage timed its own part
    out, elapsed = out
  peak = tracemalloc.get_traced_memory()[1] if trace else 0
  rss_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
  queue.put((out, elapsed, peak, rss_kib))


def _run(stage, args, trace):
  ctx = mp.get_context("spawn")
  queue = ctx.Queue()
  proc = ctx.Process(target=_child, args=(stage, args, trace, queue))
  proc.start()
  result = queue.get()
  proc.join()
  return result


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--repeats", type=int, default=3, help="timed runs per stage (best kept)")
  parser.add_argument("--skip-baselines", action="store_true", help="skip the plyfile rows")
  args = parser.parse_args()
  from lrf_jax.datasets import find_data_root
  root = str(find_data_root(dataset="bologna_retrieval"))
  cache = tempfile.mkdtemp(prefix="lrf_bench_cache_")
  stages = [
      ("BR: 60 PLYs (6 models + 54 scenes), plain plyfile [baseline]", _stage_plyfile_br,
       (root,)),
      ("BR: the same 60 PLYs, lrf_jax.io.read_ply", _stage_read_ply_br, (root,)),
      ("BR: all 6 noise levels = 108 Pairs, cold process", _stage_load_br_all, (root,)),
      ("BR: 108 Pairs again, models cached in-process", _stage_load_br_warm, (root,)),
      ("bunny: 10 ascii scans, plain plyfile [baseline]", _stage_plyfile_bunny, (root,)),
      ("bunny: 10 ascii scans, lrf_jax.io.read_ply", _stage_read_ply_bunny, (root,)),
      ("training set, 20000 keypoints, no npz cache", _stage_training_cold, (root, cache)),
      ("training set, 20000 keypoints, from npz cache", _stage_training_cached, (root, cache)),
  ]
  if args.skip_baselines:
    stages = [s for s in stages if "[baseline]" not in s[0]]
  rows = []
  for name, stage, stage_args in stages:
    repeats = 1 if "[baseline]" in name else args.repeats
    times = [_run(stage, stage_args, False) for _ in range(repeats)]
    count, _, _, rss = min(times, key=lambda t: t[1])
    _, _, peak, _ = _run(stage, stage_args, True)
    rows.append((name, count, min(t[1] for t in times), peak / 2**20, rss / 2**10))
  print(f"\nMachine: {platform.platform()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, numpy {np.__version__}; data: {root}\n")
  print(f"| stage | items | time (s, best of {args.repeats}; baselines 1) | peak traced alloc "
        "(MiB) | peak RSS (MiB) |")
  print("|---|---:|---:|---:|---:|")
  for name, count, seconds, peak, rss in rows:
    print(f"| {name} | {count} | {seconds:.3f} | {peak:.0f} | {rss:.0f} |")
  if not args.skip_baselines:
    t = [r[2] for r in rows]
    print(f"\nread_ply vs plyfile: BR binary x{t[0] / t[1]:.1f}, bunny ascii x{t[4] / t[5]:.1f} "
          "faster.")


if __name__ == "__main__":
  main()
