"""Hand-crafted LRFs per second (neighbor search included), beside PCL 1.13 in the same run.

    LRF_DATA=/path/to/data python benchmarks/bench_handcrafted.py [--keypoints 1000] [--repeat 3]

Every method of `lrf_jax.METHODS` except the learned ones runs through `compute_frames` on the BR
bunny at r = 15 mr (mean edge length) for the same seeded keypoints; the first call (compilation)
is excluded and the fastest of `--repeat` timed calls is reported. Normals are computed once
beforehand (`lrf_jax.geometry.normals.estimate_normals`) and fed to both sides, so neither timing includes
normal estimation; their cost is reported on its own line. Per-mesh quantities that lrf_jax caches
across calls (GFrames' mean curvature, the vertex -> face map) are computed in the warm-up call.

When the PCL driver is built (tools/pcl_driver, see run_pcl.py) its SHOT, BOARD, FLARE and RoPS
timings for the same keypoints are measured in the same run (single-threaded C++, kd-tree build
and radius searches included, fastest of `--repeat`).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools" / "pcl_driver"))

import lrf_jax  # noqa: E402
from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals, pca_normals  # noqa: E402
from tests.lrf_testing import load_br_model  # noqa: E402

HANDCRAFTED = ("toldi", "mian", "shot", "rops", "board", "flare", "ps", "gframes")


def _time(fn, repeat: int) -> float:
  best = float("inf")
  for _ in range(repeat):
    t0 = time.perf_counter()
    fn()
    best = min(best, time.perf_counter() - t0)
  return best


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA", str(REPO / "data")))
  ap.add_argument("--keypoints", type=int, default=1000)
  ap.add_argument("--repeat", type=int, default=3)
  ap.add_argument("--methods", nargs="+", default=list(HANDCRAFTED))
  args = ap.parse_args()

  pts, faces, mr, _ = load_br_model(Path(args.data), "bunny")
  r = 15.0 * mr
  kp = np.random.default_rng(0).choice(len(pts), args.keypoints, replace=False)
  rn = NORMAL_RADIUS_RATIO * r

  t0 = time.perf_counter()
  normals = estimate_normals(pts, rn, faces).astype(np.float32)
  t_normals = time.perf_counter() - t0
  t_pca = _time(lambda: pca_normals(pts, rn), args.repeat)

  pcl = None
  try:
    from run_pcl import driver_available, run_driver
    if driver_available():
      pcl = run_driver(pts, faces, kp, r, normals=normals, normal_radius=rn, repeat=args.repeat)
  except Exception as e:  # noqa: BLE001 - the benchmark still reports lrf_jax alone
    print(f"(PCL driver failed: {e})")

  print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__} on {jax.devices()[0].platform}; BR bunny ({len(pts)} points, "
        f"{len(faces)} faces), r = 15 mr, {args.keypoints} keypoints, best of {args.repeat}\n")
  print("| method | lrf_jax keypoints/s | lrf_jax s | PCL 1.13 keypoints/s | PCL s "
        "| lrf_jax / PCL |")
  print("|---|---:|---:|---:|---:|---:|")
  for m in args.methods:
    def run(m=m):
      f, _ = lrf_jax.compute_frames(pts, kp, r, m, faces=faces, normals=normals)
      f.block_until_ready()
    run()  # warm-up: compilation and per-mesh caches
    t = _time(run, args.repeat)
    row = f"| {m} | {args.keypoints / t:,.0f} | {t:.3f} |"
    if pcl is not None and f"time_{m}" in pcl:
      tp = pcl[f"time_{m}"]
      row += f" {args.keypoints / tp:,.0f} | {tp:.3f} | {tp / t:.2f}x |"
    else:
      row += " - | - | - |"
    print(row)
  line = (f"\nnormals for the whole cloud ({len(pts)} points, radius 0.2 r): lrf_jax PCA "
          f"{t_pca:.3f} s (estimate_normals incl. orientation, first call: {t_normals:.3f} s)")
  if pcl is not None:
    line += f"; PCL NormalEstimation {pcl['time_normals_all_points']:.3f} s"
  print(line)


if __name__ == "__main__":
  main()
