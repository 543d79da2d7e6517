"""Bounded memory at scale: LRF-Net frames of 100k keypoints of a 1M-point cloud, peak RSS.

    LRF_DATA=/path/to/data python benchmarks/bench_scale.py [--points 1000000] [--keypoints 100000]
        [--method lrf_net] [--rows both|mesh|cloud]

The cloud is sampled uniformly on the BR dragon's triangles (a real surface at about 10x the
mesh's density); r = 15 mr of the original mesh, so a ball holds about 10x as many points as on
the mesh (K = 256 are kept). The baseline in the same run is the mesh's own 100k vertices with
the same keypoint count. Each configuration runs in a fresh subprocess so that its peak RSS
(jax runtime included) is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _child(n_points: int, n_keypoints: int, data: str | None, method: str, lut: int) -> None:
  import resource
  import time

  import numpy as np

  sys.path.insert(0, str(REPO))
  import lrf_jax
  from lrf_jax import datasets

  mesh = datasets.load_br_model("dragon", data)
  mr, _ = datasets.mesh_resolution(mesh.points, mesh.faces)
  rng = np.random.default_rng(0)
  if n_points <= 0:
    pts = mesh.points
  else:
    tri = mesh.points[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(tri), n_points, p=area / area.sum())
    a, b = rng.random((2, n_points))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    pts = tri[f, 0] + a[:, None] * (tri[f, 1] - tri[f, 0]) + b[:, None] * (tri[f, 2] - tri[f, 0])
  kp = rng.choice(len(pts), n_keypoints, replace=n_keypoints > len(pts))
  spec = lrf_jax.METHODS[method]
  faces = mesh.faces if n_points <= 0 and spec.needs_mesh else None  # mesh methods: the mesh row
  t0 = time.perf_counter()
  frames, valid = lrf_jax.compute_frames(pts, kp, 15 * mr, method, progress=True, faces=faces,
                                         **({"lut": lut} if lut and spec.needs_params else {}))
  frames.block_until_ready()
  dt = time.perf_counter() - t0
  print(json.dumps({"points": len(pts), "keypoints": n_keypoints, "seconds": dt,
                    "frames_per_s": n_keypoints / dt, "valid": float(np.mean(valid)),
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
  ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
  args = ap.parse_args()
  if args.child is not None:
    _child(args.child, args.keypoints, args.data, args.method, args.lut)
    return
  print("| cloud | points | keypoints | frames/s | seconds | valid | peak RSS MB |")
  print("|---|---:|---:|---:|---:|---:|---:|")
  rows = [("BR dragon vertices (baseline)", 0), ("dragon surface samples", args.points)]
  rows = {"both": rows, "mesh": rows[:1], "cloud": rows[1:]}[args.rows]
  print(f"method {args.method}")
  for label, n in rows:
    cmd = [sys.executable, __file__, "--child", str(n), "--keypoints", str(args.keypoints),
           "--method", args.method, "--lut", str(args.lut)] + (
               ["--data", args.data] if args.data else [])
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    r = json.loads(out.strip().splitlines()[-1])
    print(f"| {label} | {r['points']:,} | {r['keypoints']:,} | {r['frames_per_s']:,.0f} | "
          f"{r['seconds']:.1f} | {r['valid']:.3f} | {r['peak_rss_mb']:,.0f} |", flush=True)


if __name__ == "__main__":
  main()
