"""LRF-Net frames per second, neighbor search included, against the plain numpy implementation.

    LRF_DATA=/path/to/data python benchmarks/bench_frames.py [--model bunny] [--counts 1000 10000]

Both are measured in the same run on the same BR model at r = 15 mr (mean edge length). The numpy
baseline (tests.reference_numpy, one keypoint at a time) is timed on a subset of keypoints
(`--numpy-max`) and reported as a rate; it is far too slow for 10k keypoints. The JAX time is
the second call (the first one compiles), split into host search and jitted frame computation.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import sys

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lrf_jax  # noqa: E402
from lrf_jax.search.neighborhoods import build_patches  # noqa: E402
from tests.reference_numpy import reference_frames  # noqa: E402
from tests.lrf_testing import load_br_model  # noqa: E402


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA", "data"))
  ap.add_argument("--model", default="bunny")
  ap.add_argument("--counts", type=int, nargs="+", default=[1000, 10000])
  ap.add_argument("--numpy-max", type=int, default=300)
  ap.add_argument("--k", type=int, default=256)
  args = ap.parse_args()

  pts, _, mr, _ = load_br_model(Path(args.data), args.model)
  r = 15 * mr
  params = lrf_jax.default_params()
  rng = np.random.default_rng(0)
  print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__} on {jax.devices()[0].platform}; BR {args.model} "
        f"({len(pts)} points), r = 15 mr, K = {args.k}\n")
  print("| keypoints | lrf_jax frames/s (total) | search s | jitted s | numpy frames/s | speed-up |")
  print("|---:|---:|---:|---:|---:|---:|")
  for m in args.counts:
    kp = rng.choice(len(pts), m, replace=m > len(pts))
    lrf_jax.compute_frames(pts, kp, r, params=params, k=args.k)[0].block_until_ready()  # compile
    t0 = time.perf_counter()
    f, _ = lrf_jax.compute_frames(pts, kp, r, params=params, k=args.k)
    f.block_until_ready()
    total = time.perf_counter() - t0
    t0 = time.perf_counter()
    p = build_patches(pts, kp, r, args.k)
    search = time.perf_counter() - t0
    fn = jax.jit(lrf_jax.lrf_net_frames)
    jp = jax.tree.map(jnp.asarray, p)
    fn(params, jp)[0].block_until_ready()
    t0 = time.perf_counter()
    fn(params, jp)[0].block_until_ready()
    jitted = time.perf_counter() - t0
    nm = min(m, args.numpy_max)
    t0 = time.perf_counter()
    reference_frames(pts, kp[:nm], r, weights="lrf_net", params=params, k=args.k)
    np_rate = nm / (time.perf_counter() - t0)
    print(f"| {m} | {m / total:,.0f} | {search:.3f} | {jitted:.3f} | {np_rate:,.0f} "
          f"(on {nm}) | {m / total / np_rate:.1f}x |")


if __name__ == "__main__":
  main()
