"""Many scans into one model: `lrf_jax.register_all` beside Open3D's multiway registration.

    LRF_DATA=/path/to/data python benchmarks/bench_multiway.py [--out out/bench_multiway]
        [--sets bunny shuffled intruder uwa] [--objects chef parasaurolophus T-rex] [--seed 0]

Sets (each run by both pipelines in the same process, after a warm-up registration so that
JAX compilation is not timed):

* bunny: the 10 Stanford bunny scans in alphabetical order (bun000 first), every pose against
  bun.conf (deg, mm), relative to the first scan;
* shuffled: the same scans in a seeded random order (errors relative to the new first scan);
* intruder: the bunny scans plus one scan of another object (UWA3M T-rex view 1, mm -> m), which
  must be left out of the model, not merged;
* uwa: the 10 UWA3M views of each object against `pseudo_gt_DERIVED.txt` (mm), and with a view
  of another object added as the intruder.

Open3D (0.20) runs its multiway-registration tutorial
(`docs/tutorial/pipelines/multiway_registration.ipynb`): voxel downsampling, normals (radius 2
voxel, 30 neighbors), every pair by point-to-plane ICP from the identity at 15 voxel then 1.5
voxel, the information matrix at 1.5 voxel, odometry edges between consecutive scans and
uncertain loop closures for the others, `global_optimization` (Levenberg-Marquardt, line process,
edge_prune_threshold 0.25, reference node 0). The tutorial's voxel (0.02 for its demo scans) is
set here in mr: `--o3d-voxel-mr` (2.5 mr, as `bench_scenes.py` sets Open3D's objects). Because
the tutorial's scans start roughly aligned and these do not, a second Open3D variant starts
every pairwise ICP from the FPFH + RANSAC estimate of Open3D's global registration tutorial
(`_open3d_pipeline.global_registration`, same voxel) and is otherwise identical. Open3D has no
notion of leaving a scan out: the intruder is always merged.

Writes results.json, report.md and our outputs (poses, merged.ply, edges.tsv, merged.png,
graph.png) per set under --out, and prints the report.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lrf_jax import compilation_cache  # noqa: E402
from lrf_jax import multiway  # noqa: E402
from lrf_jax.multiway import outputs as multiway_outputs  # noqa: E402
from lrf_jax.datasets.stanford import bunny_poses  # noqa: E402
from lrf_jax.datasets.uwa3m import PSEUDO_GT_FILE, read_pseudo_gt, uwa3m_views  # noqa: E402
from lrf_jax.io import read_cloud  # noqa: E402
from lrf_jax.registration import register, rotation_error_deg  # noqa: E402

from benchmarks._open3d_pipeline import global_registration, have_open3d  # noqa: E402

BUNNY = ("bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "chin", "ear_back", "top2",
         "top3")


def o3d_multiway(clouds: list[np.ndarray], mr: float, *, voxel_mr: float, init: str,
                 seed: int) -> dict:
  """Open3D's multiway tutorial on `clouds`; init "identity" (the tutorial) or "fpfh".
  Returns {"poses": (n, 4, 4) scan -> scan 0's frame, "seconds"}."""
  import open3d as o3d
  reg = o3d.pipelines.registration
  t0 = time.perf_counter()
  voxel = voxel_mr * mr
  coarse, fine = 15 * voxel, 1.5 * voxel
  pcds = []
  for c in clouds:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(c, np.float64)))
    down = pc.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    pcds.append(down)
  graph = reg.PoseGraph()
  odometry = np.eye(4)
  graph.nodes.append(reg.PoseGraphNode(odometry))
  n = len(pcds)
  for s in range(n):
    for t in range(s + 1, n):
      start = np.eye(4)
      if init == "fpfh":
        start = global_registration(clouds[s], clouds[t], voxel=voxel, seed=seed)["coarse"]
      icp_coarse = reg.registration_icp(pcds[s], pcds[t], coarse, start,
                                        reg.TransformationEstimationPointToPlane())
      icp_fine = reg.registration_icp(pcds[s], pcds[t], fine, icp_coarse.transformation,
                                      reg.TransformationEstimationPointToPlane())
      tr = icp_fine.transformation
      info = reg.get_information_matrix_from_point_clouds(pcds[s], pcds[t], fine, tr)
      if t == s + 1:
        odometry = tr @ odometry
        graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry)))
        graph.edges.append(reg.PoseGraphEdge(s, t, tr, info, uncertain=False))
      else:
        graph.edges.append(reg.PoseGraphEdge(s, t, tr, info, uncertain=True))
  option = reg.GlobalOptimizationOption(max_correspondence_distance=fine,
                                        edge_prune_threshold=0.25, reference_node=0)
  with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(), option)
  poses = np.stack([np.asarray(node.pose) for node in graph.nodes])
  return {"poses": poses, "seconds": time.perf_counter() - t0}


def errors(poses: np.ndarray, truth: list[np.ndarray], ref: int, unit: float) -> list:
  """(deg, translation / unit) of each pose vs inv(truth[ref]) @ truth[k]; None for NaN."""
  out = []
  for k, p in enumerate(poses):
    if not np.all(np.isfinite(p)):
      out.append(None)
      continue
    gt = np.linalg.inv(truth[ref]) @ truth[k]
    out.append((rotation_error_deg(p[:3, :3], gt[:3, :3]),
                float(np.linalg.norm(p[:3, 3] - gt[:3, 3]) / unit)))
  return out


def run_set(name: str, clouds, names, truth, unit: float, intruder: int | None, args,
            out: Path) -> dict:
  """Both pipelines on one set; truth: world-from-scan per scan (None for the intruder)."""
  print(f"== {name}: {len(clouds)} scans", flush=True)
  res = multiway.register_all(clouds, names=names, seed=args.seed, progress=True)
  multiway_outputs.write_outputs(res, clouds, out / name)
  ok = [k for k in range(len(clouds)) if k != intruder]
  ours_err = errors(res.poses[ok], [truth[k] for k in ok], ok.index(res.reference)
                    if res.reference in ok else 0, unit)
  row = {"set": name, "names": names, "intruder": None if intruder is None else names[intruder],
         "ours": {"errors": ours_err, "seconds": res.seconds, "timings": res.timings,
                  "left_out": res.left_out, "reference": names[res.reference],
                  "accepted": sum(e.accepted for e in res.edges), "edges": len(res.edges)}}
  if have_open3d() and not args.skip_open3d:
    for init in ("identity", "fpfh"):
      o3d = o3d_multiway(clouds, res.mr, voxel_mr=args.o3d_voxel_mr, init=init, seed=args.seed)
      row[f"o3d_{init}"] = {"errors": errors(o3d["poses"][ok], [truth[k] for k in ok], 0, unit),
                            "seconds": o3d["seconds"]}
  (out / f"{name}.json").write_text(json.dumps(row, indent=1, default=float))
  return row


def _fmt(e) -> str:
  return "left out" if e is None else f"{e[0]:.2f} / {e[1]:.2f}"


def report(rows: list[dict]) -> str:
  lines = [f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
           "errors are deg / mm (rotation / translation of each scan's pose in the "
           "first scan's frame vs the ground truth)", ""]
  for row in rows:
    methods = [m for m in ("ours", "o3d_identity", "o3d_fpfh") if m in row]
    lines.append(f"### {row['set']}" + (f" (intruder: {row['intruder']})" if row["intruder"]
                                         else ""))
    lines.append("")
    lines.append("| scan | " + " | ".join(methods) + " |")
    lines.append("|---|" + "---:|" * len(methods))
    names = [n for n in row["names"] if n != row["intruder"]]
    for k, n in enumerate(names):
      lines.append(f"| {n} | " + " | ".join(_fmt(row[m]["errors"][k]) for m in methods) + " |")
    lines += ["", "| pipeline | worst deg | worst mm | within 1 deg & 2 mm | seconds |",
              "|---|---:|---:|---:|---:|"]
    for m in methods:
      errs = [e for e in row[m]["errors"] if e is not None]
      worst = (max(e[0] for e in errs), max(e[1] for e in errs)) if errs else (np.nan, np.nan)
      within = sum(e is not None and e[0] < 1.0 and e[1] < 2.0 for e in row[m]["errors"])
      lines.append(f"| {m} | {worst[0]:.2f} | {worst[1]:.2f} | {within}/{len(names)} | "
                   f"{row[m]['seconds']:.1f} |")
    o = row["ours"]
    lines.append("")
    lines.append(f"ours: reference {o['reference']}, {o['accepted']}/{o['edges']} edges "
                 f"accepted, left out: {', '.join(o['left_out']) or 'none'}; stages "
                 + ", ".join(f"{k} {v:.1f} s" for k, v in o["timings"].items()))
    if row["intruder"]:
      lines.append(f"Open3D merges every scan: the intruder {row['intruder']} is in its model.")
    lines.append("")
  return "\n".join(lines)


def main() -> int:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--out", default="out/bench_multiway")
  ap.add_argument("--sets", nargs="+", default=["bunny", "shuffled", "intruder", "uwa"])
  ap.add_argument("--objects", nargs="+", default=["chef", "parasaurolophus", "T-rex"])
  ap.add_argument("--o3d-voxel-mr", type=float, default=2.5)
  ap.add_argument("--skip-open3d", action="store_true")
  ap.add_argument("--seed", type=int, default=0)
  args = ap.parse_args()
  root = Path(os.environ.get("LRF_DATA", REPO / "data"))
  out = Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  compilation_cache.enable()
  folder = root / "stanford_bunny_scans"
  world = bunny_poses(root)
  bunny = [read_cloud(folder / f"{n}.ply").points for n in BUNNY]
  truth = [world[n] for n in BUNNY]
  register(bunny[0], bunny[1], seed=args.seed)  # warm-up: JAX compilation, not timed
  rows = []
  t_rex = read_cloud(uwa3m_views("T-rex", root)[1]).points * 1e-3  # mm -> m
  if "bunny" in args.sets:
    rows.append(run_set("bunny", bunny, list(BUNNY), truth, 1e-3, None, args, out))
  if "shuffled" in args.sets:
    order = np.random.default_rng(args.seed + 1).permutation(len(BUNNY))
    rows.append(run_set("shuffled", [bunny[k] for k in order], [BUNNY[k] for k in order],
                        [truth[k] for k in order], 1e-3, None, args, out))
  if "intruder" in args.sets:
    rows.append(run_set("intruder", [*bunny[:5], t_rex, *bunny[5:]],
                        [*BUNNY[:5], "T-rex_view001", *BUNNY[5:]],
                        [*truth[:5], None, *truth[5:]], 1e-3, 5, args, out))
  if "uwa" in args.sets:
    gt = read_pseudo_gt(root / "uwa_3d_modeling_views" / PSEUDO_GT_FILE)
    for obj in args.objects:
      views = uwa3m_views(obj, root)
      clouds = [read_cloud(views[v]).points for v in sorted(views)]
      names = [f"{obj}_view{v:03d}" for v in sorted(views)]
      truth_v = [gt[(obj, v)].transform for v in sorted(views)]
      rows.append(run_set(f"uwa_{obj}", clouds, names, truth_v, 1.0, None, args, out))
  text = report(rows)
  (out / "report.md").write_text(text)
  (out / "results.json").write_text(json.dumps(rows, indent=1, default=float))
  print(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())
