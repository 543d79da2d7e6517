"""Bounded memory at scale: LRF-Net frames of 100k keypoints of a 1M-point cloud, peak RSS.

    LRF_DATA=/path/to/data python benchmarks/bench_scale.py [--points 1000000] [--keypoints 100000]
        [--method lrf_net] [--rows both|mesh|cloud] [--search auto|host|device]
        [--chunk-size 4096] [--repeat 0]

The cloud is sampled uniformly on the BR dragon's triangles (a real surface at about 10x the
mesh's density); r = 15 mr of the original mesh, so a ball holds about 10x as many points as on
the mesh (K = 256 are kept). The baseline in the same run is the mesh's own 100k vertices with
the same keypoint count. Each configuration runs in a fresh subprocess so that its peak RSS
(jax runtime included) is its own. The reported time is that process's first call (compilation
included); with `--repeat N` the same process then times N more calls (the median of them is the
"warm" column: a job that computes frames of many clouds of one size pays the first call once).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def dragon_cloud(n_points: int, data: str | None, rng: Any) -> tuple[Any, float, Any]:
  """(the BR dragon mesh, its mr, a cloud): the mesh's vertices with `n_points` <= 0, else
  `n_points` points drawn uniformly on its triangles (area-weighted) with the numpy `rng`."""
  import numpy as np

  sys.path.insert(0, str(REPO))
  from lrf_jax import datasets

  mesh = datasets.load_br_model("dragon", data)
  mr, _ = datasets.mesh_resolution(mesh.points, mesh.faces)
  if n_points <= 0:
    return mesh, mr, mesh.points
  tri = mesh.points[mesh.faces]
  area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
  f = rng.choice(len(tri), n_points, p=area / area.sum())
  a, b = rng.random((2, n_points))
  flip = a + b > 1
  a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
  return mesh, mr, tri[f, 0] + a[:, None] * (tri[f, 1] - tri[f, 0]) + b[:, None] * (
      tri[f, 2] - tri[f, 0])


def _child(n_points: int, n_keypoints: int, data: str | None, method: str, lut: int,
           search: str = "auto", chunk_size: int = 4096, repeat: int = 0) -> None:
  import resource
  import time

  import jax
  import numpy as np

  sys.path.insert(0, str(REPO))
  import lrf_jax

  rng = np.random.default_rng(0)
  mesh, mr, pts = dragon_cloud(n_points, data, rng)
  kp = rng.choice(len(pts), n_keypoints, replace=n_keypoints > len(pts))
  spec = lrf_jax.METHODS[method]
  faces = mesh.faces if n_points <= 0 and spec.needs_mesh else None  # mesh methods: the mesh row
  opts = {"lut": lut} if lut and spec.needs_params else {}
  times = []
  for i in range(1 + repeat):
    t0 = time.perf_counter()
    frames, valid = lrf_jax.compute_frames(pts, kp, 15 * mr, method, progress=i == 0,
                                           faces=faces, search=search, chunk_size=chunk_size,
                                           **opts)
    frames.block_until_ready()
    times.append(time.perf_counter() - t0)
  warm = float(np.median(times[1:])) if repeat else float("nan")
  print(json.dumps({"points": len(pts), "keypoints": n_keypoints, "seconds": times[0],
                    "frames_per_s": n_keypoints / times[0], "warm_seconds": warm,
                    "warm_frames_per_s": n_keypoints / warm, "valid": float(np.mean(valid)),
                    "backend": jax.default_backend(),
                    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--points", type=int, default=1_000_000)
  ap.add_argument("--keypoints", type=int, default=100_000)
  ap.add_argument("--method", default="lrf_net")
  ap.add_argument("--lut", type=int, default=257)
  ap.add_argument("--rows", choices=("both", "mesh", "cloud"), default="both",
                  help="the mesh row, the sampled-cloud row or both (mesh methods: mesh only)")
  ap.add_argument("--search", choices=("auto", "host", "device"), default="auto",
                  help="compute_frames(search=...): auto is the device search on a GPU")
  ap.add_argument("--chunk-size", type=int, default=4096, help="compute_frames(chunk_size=...)")
  ap.add_argument("--repeat", type=int, default=0,
                  help="timed calls after the first, in the same process (the warm column)")
  ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
  args = ap.parse_args()
  if args.child is not None:
    _child(args.child, args.keypoints, args.data, args.method, args.lut, args.search,
           args.chunk_size, args.repeat)
    return
  print("| cloud | points | keypoints | frames/s | seconds | warm frames/s | valid | peak RSS MB |")
  print("|---|---:|---:|---:|---:|---:|---:|---:|")
  rows = [("BR dragon vertices (baseline)", 0), ("dragon surface samples", args.points)]
  rows = {"both": rows, "mesh": rows[:1], "cloud": rows[1:]}[args.rows]
  print(f"method {args.method}, search {args.search}, chunk_size {args.chunk_size}")
  for label, n in rows:
    cmd = [sys.executable, __file__, "--child", str(n), "--keypoints", str(args.keypoints),
           "--method", args.method, "--lut", str(args.lut), "--search", args.search,
           "--chunk-size", str(args.chunk_size), "--repeat", str(args.repeat)] + (
               ["--data", args.data] if args.data else [])
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    r = json.loads(out.strip().splitlines()[-1])
    print(f"| {label} | {r['points']:,} | {r['keypoints']:,} | {r['frames_per_s']:,.0f} | "
          f"{r['seconds']:.1f} | {r['warm_frames_per_s']:,.0f} | {r['valid']:.3f} | "
          f"{r['peak_rss_mb']:,.0f} |", flush=True)


if __name__ == "__main__":
  main()
