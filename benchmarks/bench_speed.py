"""Frames per second, neighbor search included, for LRF-Net and hand-crafted LRFs at 1k, 10k and
100k keypoints (r = 15 mr) on a real BR model, with PCL 1.13's SHOT beside them in the same run
when the driver in tools/pcl_driver is built; peak resident memory of the whole run.

    LRF_DATA=/path/to/data python benchmarks/bench_speed.py [--model dragon] [--counts 1000 10000]

Keypoints are drawn with replacement when more are asked for than the model has points. Each
timing is the median of 3 calls after a compiling one (1 call above 10k keypoints), with the
normal and area caches cleared before each; PCL gets the same keypoints and radius, also 3 runs.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools" / "pcl_driver"))

import lrf_jax  # noqa: E402
from lrf_jax import datasets  # noqa: E402
from lrf_jax.geometry import normals as normals_cache  # noqa: E402


def _rss_mb() -> float:
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _repeats(m: int) -> int:
  """Timed calls per cell (the median is reported): 3 up to 10k keypoints, else 1."""
  return 3 if m <= 10_000 else 1


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--model", default="dragon")
  ap.add_argument("--counts", type=int, nargs="+", default=[1000, 10000, 100000])
  ap.add_argument("--methods", nargs="+", default=["lrf_net", "lrf_net:lut", "toldi", "shot"],
                  help="registry names; NAME:lut reads the weights from a 257x257 table, "
                       "NAME:device searches on the default device (lrf_jax.search.device), "
                       "NAME:lut:device both, NAME:exact the network per point (lrf_net_plus "
                       "reads a table by default), NAME:mesh passes the faces")
  ap.add_argument("--no-pcl", action="store_true")
  args = ap.parse_args()
  mesh = datasets.load_br_model(args.model, args.data)
  pts, faces = mesh.points, mesh.faces
  mr, _ = datasets.mesh_resolution(pts, faces)
  r = 15 * mr
  rng = np.random.default_rng(0)
  print(f"machine: {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} on "
        f"{jax.devices()[0].platform} x{jax.device_count()}; BR {args.model} ({len(pts)} points), "
        f"r = 15 mr\n")
  print("| keypoints | method | frames/s | seconds | peak RSS MB |")
  print("|---:|---|---:|---:|---:|")
  pcl_ok = False
  if not args.no_pcl:
    try:
      from run_pcl import driver_available, run_driver
      pcl_ok = driver_available()
    except ImportError:
      pcl_ok = False
  for m in args.counts:
    kp = rng.choice(len(pts), m, replace=m > len(pts))
    for label in args.methods:
      method, *variants = label.split(":")
      opts = {"lut": 257} if "lut" in variants else {"lut": 0} if "exact" in variants else {}
      opts["search"] = "device" if "device" in variants else "host"
      if "mesh" in variants:  # give the mesh: lrf_net_plus then signs z by its oriented normals
        opts["faces"] = faces
      lrf_jax.compute_frames(pts, kp[:min(m, 4096)], r, method, progress=False, **opts)
      times = []
      for _ in range(_repeats(m)):
        normals_cache.CLOUD_CACHE.clear()  # estimated normals and areas count in the timing
        t0 = time.perf_counter()
        f, _ = lrf_jax.compute_frames(pts, kp, r, method, progress=False, **opts)
        f.block_until_ready()
        times.append(time.perf_counter() - t0)
      dt = float(np.median(times))
      print(f"| {m} | {label} | {m / dt:,.0f} | {dt:.2f} | {_rss_mb():,.0f} |", flush=True)
    if pcl_ok:
      dt = float(np.median([run_driver(pts, None, kp, r, methods=("shot",))["time_shot"]
                            for _ in range(_repeats(m))]))
      print(f"| {m} | PCL 1.13 SHOT (driver) | {m / dt:,.0f} | {dt:.2f} | (separate process) |",
            flush=True)
  if not pcl_ok:
    print("\n(PCL driver not built: see tools/pcl_driver/run_pcl.py)")


if __name__ == "__main__":
  main()
