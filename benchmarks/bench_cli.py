"""`lrf-register` as a fresh process against the Open3D script a user would write instead.

    LRF_DATA=/path/to/data python benchmarks/bench_cli.py [--pair bun000 bun045] [--runs 2]

Both read the two Stanford bunny scans from their PLY files and write nothing but the matrix:
`lrf-register SRC TGT --out T.txt` (its defaults) and a child Python process running Open3D
0.20's tutorial pipeline (read, 3 mm voxel, FPFH, RANSAC, point-to-point ICP at 5 mr). Each is
run `--runs` times in a row; the first run of `lrf-register` on a machine also compiles (numba
and JAX caches on disk), so the figure compared is the last run's wall time.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

OPEN3D_SCRIPT = r"""
import sys, numpy as np, open3d as o3d
src, tgt, out = sys.argv[1:4]
voxel = 0.003
reg = o3d.pipelines.registration
o3d.utility.random.seed(0)
clouds = [o3d.io.read_point_cloud(p) for p in (src, tgt)]
mr = float(np.mean(clouds[0].compute_nearest_neighbor_distance()))
feats = []
for pc in clouds:
  down = pc.voxel_down_sample(voxel)
  down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
  feats.append((down, reg.compute_fpfh_feature(
      down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))))
(ds, fs), (dt, ft) = feats
dist = 1.5 * voxel
res = reg.registration_ransac_based_on_feature_matching(
    ds, dt, fs, ft, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
    [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
     reg.CorrespondenceCheckerBasedOnDistance(dist)],
    reg.RANSACConvergenceCriteria(100000, 0.999))
fine = reg.registration_icp(clouds[0], clouds[1], 5 * mr, res.transformation,
                            reg.TransformationEstimationPointToPoint(),
                            reg.ICPConvergenceCriteria(max_iteration=50))
np.savetxt(out, np.asarray(fine.transformation))
"""


def timed(cmd: list[str]) -> tuple[float, int]:
  t0 = time.perf_counter()
  rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
  return time.perf_counter() - t0, rc


def main() -> int:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--pair", nargs=2, default=["bun000", "bun045"])
  ap.add_argument("--runs", type=int, default=2)
  args = ap.parse_args()
  if not args.data:
    print("set LRF_DATA (or --data) to the folder holding stanford_bunny_scans/", file=sys.stderr)
    return 2
  scans = Path(args.data) / "stanford_bunny_scans"
  src, tgt = (str(scans / f"{name}.ply") for name in args.pair)
  exe = shutil.which("lrf-register") or "lrf-register"
  rows = []
  with tempfile.TemporaryDirectory() as tmp:
    script = Path(tmp) / "o3d_register.py"
    script.write_text(OPEN3D_SCRIPT)
    for label, cmd in (
        ("lrf-register (defaults)", [exe, src, tgt, "--out", f"{tmp}/ours.txt"]),
        ("Open3D 0.20 script", [sys.executable, str(script), src, tgt, f"{tmp}/o3d.txt"])):
      times = []
      for _ in range(args.runs):
        seconds, rc = timed(cmd)
        times.append(f"{seconds:.1f} s" + ("" if rc in (0, 3) else f" (rc {rc})"))
      rows.append((label, times, seconds))
  print(f"# lrf-register vs an Open3D script, fresh processes, {args.pair[0]} -> {args.pair[1]}")
  print(f"({os.cpu_count()} CPUs)\n")
  print("| program | " + " | ".join(f"run {i + 1}" for i in range(args.runs)) + " |")
  print("|---|" + "---:|" * args.runs)
  for label, times, _ in rows:
    print(f"| {label} | " + " | ".join(times) + " |")
  print(f"\nlast run: lrf-register / Open3D script = {rows[0][2] / rows[1][2]:.2f}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
