"""Descriptor matching (RPC), 6-DoF pose and scan registration, beside Open3D in the same run.

    LRF_DATA=/path/to/data python benchmarks/bench_registration.py [--out out/bench_registration]
        [--datasets BR@0.3 UWA3M UWAOR bunny] [--max-pairs N] [--keypoints 1000] [--skip-rpc]

Three parts, on the datasets found (BR at 0.3 mr noise, UWA3M consecutive views, UWAOR scene
rs1, the Stanford bunny's consecutive scans):

1. description: each descriptor (snapshots, SHOT, RoPS, TOLDI) on its original LRF and on
   LRF-Net, recall vs 1-precision (`lrf_jax.evaluation.description`), figures rpc_<dataset>.png;
2. pose: one-correspondence LRF RANSAC (100 iterations) vs 3-point RANSAC (1000) on the 100 best
   TOLDI + LRF-Net correspondences (`lrf_jax.evaluation.pose`), the paper's table beside ours;
3. registration of the consecutive bunny scans with `lrf_jax.register` (default settings) and
   with Open3D's FPFH + RANSAC (`registration_ransac_based_on_feature_matching`, the settings of
   Open3D's global registration tutorial with the voxel size `--voxel-mr` mr), each followed by
   ICP (ours: `registration.icp`; Open3D: point-to-point `registration_icp`, the same pairing
   distance, and the tutorial's own point-to-plane refinement within 0.4 voxel, both from
   `benchmarks/_open3d_pipeline.py`), accuracy (err_r deg, err_t mr, before and after ICP) and
   wall time per pair (after a warm-up pair, so JAX compilation is excluded; Open3D's time
   includes its voxel downsampling, normals and FPFH; ours includes the radius searches, frames
   and descriptors).

Open3D comes from benchmarks/requirements-bench.txt; without it part 3 runs ours only and says so.
Writes results.json and report.md to --out and prints the report.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Literal

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import jax  # noqa: E402

from lrf_jax import datasets, evaluation  # noqa: E402
from lrf_jax.evaluation.description import (description_report, plot_rpc,  # noqa: E402
                                            run_description)
from lrf_jax.evaluation.pose import pose_report, run_pose  # noqa: E402
from lrf_jax.registration import pose_errors, register  # noqa: E402

from benchmarks._open3d_pipeline import global_registration, have_open3d  # noqa: E402


def open3d_register(src: np.ndarray, dst: np.ndarray, mr: float, *, voxel: float,
                    icp_mr: float, seed: int,
                    refine: Literal["point_to_point", "point_to_plane"] = "point_to_point") -> dict:
  """Open3D FPFH + RANSAC (tutorial settings, voxel size `voxel` in cloud units) then ICP:
  point-to-point within icp_mr mr, or the tutorial's point-to-plane within 0.4 voxel
  (`_open3d_pipeline.global_registration`); returns transforms/time."""
  return global_registration(src, dst, voxel=voxel, seed=seed, refine=refine,
                             icp_distance=icp_mr * mr if refine == "point_to_point" else None,
                             icp_iterations=50)


def bunny_registration(root, args) -> tuple[list[dict], list[str]]:
  notes = []
  have_o3d = have_open3d()
  if not have_o3d:
    notes.append("open3d is not installed (pip install -r benchmarks/requirements-bench.txt): "
                 "the Open3D baseline was skipped")
  pairs = datasets.load_bunny_pairs(root)
  rows = []
  # Warm-up (JAX compilation) on the first pair, not timed.
  register(pairs[0].model_points, pairs[0].scene_points, seed=args.seed)
  for pair in pairs:
    reg = register(pair.model_points, pair.scene_points, seed=args.seed)
    row = {"pair": pair.name, "mr": pair.mr}
    row["ours_coarse"] = pose_errors(reg.coarse_transform, pair.transform, pair.mr)
    row["ours"] = pose_errors(reg.transform, pair.transform, pair.mr)
    row["ours_seconds"] = reg.seconds
    row["ours_inliers"] = reg.n_inliers
    row["ours_stages"] = dict(reg.timings)
    if have_o3d:
      voxel = args.voxel if args.voxel_mr is None else args.voxel_mr * pair.mr
      o3 = open3d_register(pair.model_points, pair.scene_points, pair.mr, voxel=voxel,
                           icp_mr=3.0, seed=args.seed)
      row["o3d_coarse"] = pose_errors(o3["coarse"], pair.transform, pair.mr)
      row["o3d"] = pose_errors(o3["final"], pair.transform, pair.mr)
      row["o3d_seconds"] = o3["seconds"]
      row["o3d_points"] = o3["n_points"]
      p2l = open3d_register(pair.model_points, pair.scene_points, pair.mr, voxel=voxel,
                            icp_mr=3.0, seed=args.seed, refine="point_to_plane")
      row["o3d_p2l_coarse"] = pose_errors(p2l["coarse"], pair.transform, pair.mr)
      row["o3d_p2l"] = pose_errors(p2l["final"], pair.transform, pair.mr)
      row["o3d_p2l_seconds"] = p2l["seconds"]
    rows.append(row)
    print(json.dumps(row), flush=True)
  return rows, notes


def registration_report(rows: list[dict]) -> str:
  have = "o3d" in rows[0] if rows else False
  head = ("| pair | ours coarse err_r / err_t | ours + ICP err_r / err_t | ours s |"
          + (" Open3D coarse | Open3D + ICP | Open3D s | Open3D + point-to-plane ICP |"
             " Open3D p2l s |" if have else ""))
  lines = ["## registration of consecutive bunny scans (err_r deg / err_t mr)", "", head,
           "|---|---:|---:|---:|" + ("---:|---:|---:|---:|---:|" if have else "")]
  fmt = lambda e: f"{e[0]:.2f} / {e[1]:.2f}"  # noqa: E731
  for r in rows:
    line = (f"| {r['pair']} | {fmt(r['ours_coarse'])} | {fmt(r['ours'])} | "
            f"{r['ours_seconds']:.1f} |")
    if have:
      line += f" {fmt(r['o3d_coarse'])} | {fmt(r['o3d'])} | {r['o3d_seconds']:.1f} |"
      line += f" {fmt(r['o3d_p2l'])} | {r['o3d_p2l_seconds']:.1f} |"
    lines.append(line)
  for key, name in (("ours", "ours"), ("o3d", "Open3D"),
                    ("o3d_p2l", "Open3D point-to-plane")):
    if rows and key in rows[0]:
      er = np.array([r[key][0] for r in rows])
      et = np.array([r[key][1] for r in rows])
      sec = np.array([r[f"{key}_seconds"] for r in rows])
      lines.append(f"\n{name} (+ ICP): {int((er < 5).sum())}/{len(rows)} pairs under 5 deg; "
                   f"median err_r {np.median(er):.3f} deg, max {er.max():.3f}; median err_t "
                   f"{np.median(et):.3f} mr; median time {np.median(sec):.2f} s per pair "
                   f"(mean {sec.mean():.2f})")
  if rows and "ours_stages" in rows[0]:
    stages = list(rows[0]["ours_stages"])
    lines += ["", "lrf_jax.register per stage (median seconds over the pairs):", "",
              "| " + " | ".join(stages) + " |", "|" + "---:|" * len(stages),
              "| " + " | ".join(f"{np.median([r['ours_stages'][k] for r in rows]):.3f}"
                                for k in stages) + " |"]
  return "\n".join(lines) + "\n"


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--out", default="out/bench_registration")
  ap.add_argument("--datasets", nargs="+", default=["BR@0.3", "UWA3M", "UWAOR", "bunny"])
  ap.add_argument("--max-pairs", type=int, default=None, help="at most N pairs per dataset")
  ap.add_argument("--keypoints", type=int, default=1000)
  ap.add_argument("--voxel", type=float, default=0.003,
                  help="Open3D voxel size in cloud units (0.003: 3 mm, its tutorial's)")
  ap.add_argument("--voxel-mr", type=float, default=None, help="Open3D voxel size in mr instead")
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--skip-rpc", action="store_true")
  ap.add_argument("--skip-pose", action="store_true")
  ap.add_argument("--skip-registration", action="store_true")
  args = ap.parse_args()

  out = Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  machine = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
             f"jax {jax.__version__} on {jax.default_backend()}")
  ok, notes = evaluation.available(args.datasets, args.data, evaluation.DATASETS)
  opts = evaluation.EvalOptions(data_root=args.data, n_keypoints=args.keypoints, seed=args.seed,
                                max_pairs=args.max_pairs)
  cache = evaluation.PatchCache()
  results: dict = {"machine": machine, "args": vars(args), "notes": notes}
  report = [f"# bench_registration ({machine})", ""] + [f"- {n}" for n in notes] + [""]
  t_all = time.perf_counter()
  if not args.skip_pose and ok:
    t0 = time.perf_counter()
    recs = list(run_pose(ok, opts, cache))
    results["pose"] = recs
    report.append(pose_report(recs))
    report.append(f"(pose part: {time.perf_counter() - t0:.0f} s)\n")
    print(pose_report(recs), flush=True)
  if not args.skip_rpc and ok:
    t0 = time.perf_counter()
    recs = []
    for rec in run_description(ok, opts, cache):
      recs.append(rec)
      print(rec["dataset"], rec["pair"], rec["method"], rec.get("recall_max"), flush=True)
    results["description"] = recs
    report.append(description_report(recs))
    report.append("Figures: " + ", ".join(p.name for p in plot_rpc(recs, out)))
    report.append(f"(description part: {time.perf_counter() - t0:.0f} s)\n")
  if not args.skip_registration and "bunny" in ok:
    rows, reg_notes = bunny_registration(args.data, args)
    results["registration"] = rows
    report += [f"- {n}" for n in reg_notes]
    report.append(registration_report(rows))
  report.append(f"Total {time.perf_counter() - t_all:.0f} s.")
  text = "\n".join(report)
  (out / "report.md").write_text(text)
  (out / "results.json").write_text(json.dumps(results, indent=1, default=lambda o: (
      o.tolist() if isinstance(o, np.ndarray) else str(o))))
  print(text)


if __name__ == "__main__":
  main()
