"""Multiway registration at scale: `lrf-register SCANS... --out-dir D` on 50+ scans in one
process and on Ray clusters of 1 and 2 nodes of this machine, a node killed mid-job, the rerun,
foreign scans mixed in, and a projection to a 4,500-sweep sequence on 10 nodes.

    LRF_DATA=/path/to/data python benchmarks/bench_multiway_scale.py [--out out/bench_multiway_scale]
        [--variants 5] [--foreign 3] [--seed 0] [--skip-ray] [--skip-kill]

The scan set (written as PLY under --out/scans, float64): each of the 10 real Stanford bunny
scans (`stanford_bunny_scans`, bun.conf ground truth) gives `--variants` scans: the scan cut by a
plane (the points beyond a seeded random direction's 75th-95th percentile removed: a partial
view of the partial view) and moved by a seeded random rigid motion (any rotation, up to 10 cm);
the ground-truth pose of a variant is bun.conf's pose composed with the inverse motion. Among
them, at spread positions, `--foreign` views of another object (UWA3M T-rex views, mm -> m):
scans that must be left out. The scans are in bunny-sequence order (bun000's variants, then
bun045's, ...), so the candidate rule pairs each with the next one plus 3 loop-closure
candidates by D2 signature.

Every configuration runs as a fresh process (start-up, Ray nodes and the first compile of the
kernels they load from the cache included) with the kernel cache warm (a warm-up pair first):

* local: `lrf-register SCANS --out-dir D --quiet --no-figures` (this process, every core);
* ray-1: a Ray cluster of one node with 1 CPU (`ray.cluster_utils.Cluster` on 127.0.0.1), the
  same command with `--engine ray --address <head>`;
* ray-2: a head and a worker node of 1 CPU each;
* kill: ray-2 with the worker node killed (`remove_node(..., allow_graceful=False)`) when a
  third of the pairs have records; the job must finish with the local run's poses;
* rerun: the local command again into the kill run's folder: nothing registered or described.

Each run's poses (D/poses.txt) are compared with the ground truth (rotation error in degrees,
translation error in mm) and with the local run's; the report counts the scans described and
the pairs registered (the command's summary line), the candidate pairs for 50, 500 and 5,000
scans (`multiway.candidate_pairs` of random clouds), and projects a 4,500-sweep KITTI sequence
on 10 nodes from the per-scan and per-pair cost measured on the dev sweeps in this run. Writes
results.json, report.md and scale.png under --out and prints the report.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import platform
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

BUNNY = ("bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "chin", "ear_back", "top2",
         "top3")


# --- the scan set -----------------------------------------------------------------------------

def make_set(data: Path, out: Path, variants: int, foreign: int, seed: int
             ) -> tuple[list[Path], list[np.ndarray | None]]:
  """Write the scans; (paths in order, world-from-scan pose or None for a foreign scan)."""
  from lrf_jax import io
  from lrf_jax.datasets.stanford import bunny_poses
  rng = np.random.default_rng(seed)
  world = bunny_poses(data)
  folder = out / "scans"
  folder.mkdir(parents=True, exist_ok=True)
  scans: list[tuple[Path, np.ndarray | None]] = []
  for name in BUNNY:
    pts = io.read_cloud(data / "stanford_bunny_scans" / f"{name}.ply").points
    for v in range(variants):
      d = rng.normal(size=3)
      d /= np.linalg.norm(d)
      proj = pts @ d
      keep = proj <= np.quantile(proj, rng.uniform(0.75, 0.95))
      motion = np.eye(4)
      motion[:3, :3] = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
      motion[:3, 3] = rng.uniform(-0.1, 0.1, 3)
      moved = pts[keep] @ motion[:3, :3].T + motion[:3, 3]
      path = folder / f"{name}_v{v}.ply"
      io.write_ply(path, moved, dtype="float64")
      scans.append((path, world[name] @ np.linalg.inv(motion)))
  for k in range(foreign):
    with gzip.open(data / "uwa_3d_modeling_views" / f"T-rex_view{k + 1:03d}.txt.gz") as f:
      trex = np.loadtxt(f) / 1000.0
    path = folder / f"trex_view{k + 1}.ply"
    io.write_ply(path, trex, dtype="float64")
    at = (k + 1) * len(scans) // (foreign + 1)
    scans.insert(at, (path, None))
  return [p for p, _ in scans], [w for _, w in scans]


# --- one configuration in a fresh process -----------------------------------------------------

def child(config: str, scans: list[str], out: str, kill_at: int | None) -> int:
  """One configuration in this process; returns lrf-register's exit code."""
  from bench_batch import start_cluster  # this folder's: a cluster of 1-CPU nodes on 127.0.0.1

  from lrf_jax.cli.register import main as register_main
  argv = [*scans, "--out-dir", out, "--quiet", "--no-figures"]
  if config == "local":
    return register_main(argv)
  t0 = time.perf_counter()
  cluster, workers = start_cluster(int(config.split("-")[1]))
  print(f"# cluster ready in {time.perf_counter() - t0:.2f} s", file=sys.stderr)
  if kill_at is not None:
    def kill():
      pairs = Path(out) / ".lrf-multiway" / "pairs"
      while not pairs.is_dir() or len(list(pairs.glob("*.json"))) < kill_at:
        time.sleep(0.2)
      cluster.remove_node(workers[0], allow_graceful=False)
      print(f"# killed the worker node after {kill_at} pairs", file=sys.stderr)
    threading.Thread(target=kill, daemon=True).start()
  try:
    return register_main(argv + ["--engine", "ray", "--address", cluster.address])
  finally:
    import ray
    ray.shutdown()
    cluster.shutdown()


def run_child(config: str, scans: list[Path], out: Path, kill_at: int | None = None) -> dict:
  cmd = [sys.executable, __file__, "--child", config, "--job-out", str(out)]
  if kill_at is not None:
    cmd += ["--kill-at", str(kill_at)]
  cmd += ["--scans", *map(str, scans)]
  t0 = time.perf_counter()
  p = subprocess.run(cmd, capture_output=True, text=True)
  seconds = time.perf_counter() - t0
  work = re.search(r"# (\d+) pairs registered, (\d+) read from earlier runs' records; (\d+) "
                   r"scans described", p.stderr)
  stages = re.search(r"# seconds: (.*)", p.stderr)
  timings = {} if not stages else {k: float(v) for k, v in (
      item.rsplit(" ", 1) for item in stages[1].split(", "))}
  res = dict(config=config, seconds=seconds, rc=p.returncode, timings=timings,
             killed="killed the worker node" in p.stderr,
             registered=int(work[1]) if work else None, resumed=int(work[2]) if work else None,
             described=int(work[3]) if work else None)
  if p.returncode not in (0, 3):
    print(p.stderr[-3000:], file=sys.stderr)
  print(f"# {config}: {res}", file=sys.stderr, flush=True)
  return res


# --- checks -----------------------------------------------------------------------------------

def read_poses(out: Path) -> np.ndarray:
  rows = np.loadtxt(out / "poses.txt", ndmin=2)
  poses = np.tile(np.eye(4), (len(rows), 1, 1))
  poses[:, :3, :] = rows.reshape(-1, 3, 4)
  return poses


def errors(poses: np.ndarray, world: list[np.ndarray | None]) -> dict:
  """Per scan of the object: rotation (deg) and translation (mm) errors against the ground
  truth, in the first scan's frame; foreign scans placed (they must not be)."""
  ref = world[0]
  err_r, err_t, missing = [], [], 0
  for pose, w in zip(poses, world):
    if w is None:
      continue
    if np.isnan(pose).any():
      missing += 1
      continue
    gt = np.linalg.inv(ref) @ w
    d = np.linalg.inv(gt) @ pose
    err_r.append(float(np.degrees(Rotation.from_matrix(d[:3, :3]).magnitude())))
    err_t.append(float(np.linalg.norm(pose[:3, 3] - gt[:3, 3]) * 1000))
  foreign_placed = sum(1 for pose, w in zip(poses, world) if w is None and not np.isnan(pose).any())
  return dict(err_r=err_r, err_t=err_t, missing=missing, foreign_placed=foreign_placed)


def candidate_counts(sizes=(50, 500, 5000)) -> dict:
  from lrf_jax import multiway
  rng = np.random.default_rng(0)
  out = {}
  for n in sizes:
    clouds = [rng.normal(size=(64, 3)) * (1 + rng.random(3)) for _ in range(n)]
    t = time.perf_counter()
    out[n] = dict(pairs=len(multiway.candidate_pairs(clouds)), seconds=time.perf_counter() - t)
  return out


def unit_costs(data: Path) -> dict:
  """Per-scan (describe) and per-pair (register from features) wall seconds on the six raw
  KITTI dev sweeps (defaults, this process, warm) and on bunny scans."""
  from lrf_jax.multiway import pipeline as multiway_pipeline
  from lrf_jax.registration import scan_features
  from lrf_jax.registration.options import DEFAULTS
  out = {}
  sets = {"kitti": sorted((data / "lidar_kitti00").glob("*.bin")),
          "bunny": [data / "stanford_bunny_scans" / f"{n}.ply" for n in BUNNY[:6]]}
  for label, paths in sets.items():
    clouds = multiway_pipeline.load_scans([str(p) for p in paths], [p.stem for p in paths])
    mr = multiway_pipeline.median_mr(clouds, [p.stem for p in paths])
    scan_features.describe_scan(clouds[0], DEFAULTS, mr=mr)  # warm
    t = time.perf_counter()
    feats = [scan_features.describe_scan(c, DEFAULTS, mr=mr) for c in clouds]
    t_d = (time.perf_counter() - t) / len(clouds)
    t = time.perf_counter()
    for a, b in zip(feats[:-1], feats[1:]):
      scan_features.register_scans(b, a, DEFAULTS)
    t_p = (time.perf_counter() - t) / (len(feats) - 1)
    out[label] = dict(describe_s=t_d, pair_s=t_p, points=int(np.mean([len(c.points)
                                                                     for c in clouds])))
  return out


# --- report -----------------------------------------------------------------------------------

def summary(e: dict) -> str:
  if not e["err_r"]:
    return "no pose"
  return (f"median {np.median(e['err_r']):.3f} deg / {np.median(e['err_t']):.2f} mm, worst "
          f"{max(e['err_r']):.3f} deg / {max(e['err_t']):.2f} mm")


def projection(costs: dict, counts: dict, driver_s: float, n_scans: int) -> dict:
  """A 4,500-sweep sequence on 10 nodes of 16 cores (one task per core): the candidate pairs at
  the measured rate per scan, describe and pair costs of the dev sweeps; the driver's graph and
  joint ICP scaled linearly from this run's (an assumption: stated)."""
  per_scan = counts[5000]["pairs"] / 5000
  n, cores = 4500, 10 * 16
  pairs = per_scan * n
  k = costs["kitti"]
  cpu = n * k["describe_s"] + pairs * k["pair_s"]
  return dict(sweeps=n, pairs=pairs, cpu_hours=cpu / 3600, engine_minutes=cpu / cores / 60,
              driver_minutes=driver_s * n / n_scans / 60,
              driver_memory_gb=n * k["points"] * 3 * 8 / 1e9)


def make_report(res: dict) -> str:
  lines = [f"# bench_multiway_scale ({res['date']}, {res['machine']})", "",
           f"{res['n_scans']} scans: {res['n_object']} bunny-derived (10 real scans x "
           f"{res['variants']} cut-and-moved variants), {res['n_foreign']} foreign (UWA3M T-rex "
           "views)", "",
           "| run | wall s | rc | scans described | pairs registered | read from records | "
           "poses vs ground truth | foreign placed | same poses as local |",
           "|---|---:|---:|---:|---:|---:|---|---:|---|"]
  for r in res["runs"]:
    lines.append(f"| {r['config']} | {r['seconds']:.1f} | {r['rc']} | {r['described']} | "
                 f"{r['registered']} | {r['resumed']} | {summary(r['errors'])} (missing "
                 f"{r['errors']['missing']}) | {r['errors']['foreign_placed']} | "
                 f"{r.get('same_as_local', '')} |")
  c = res["candidates"]
  lines += ["", "Candidate pairs (`multiway.candidate_pairs`, random clouds): " + ", ".join(
      f"{n} scans: {v['pairs']} ({v['pairs'] / n:.2f} per scan, {v['seconds']:.2f} s)"
      for n, v in c.items())]
  u = res["unit_costs"]
  lines += ["", "Unit costs (this process, warm): " + "; ".join(
      f"{k}: describe {v['describe_s']:.2f} s a scan ({v['points']} points), pair "
      f"{v['pair_s']:.2f} s" for k, v in u.items())]
  p = res["projection"]
  lines += ["", f"Projection, {p['sweeps']} raw KITTI sweeps on 10 nodes of 16 cores: "
                f"{p['pairs']:.0f} candidate pairs, {p['cpu_hours']:.1f} CPU hours, "
                f"{p['engine_minutes']:.1f} min on the engine, the driver's pose graph and "
                f"joint ICP {p['driver_minutes']:.1f} min (scaled linearly from this run), "
                f"the driver holding {p['driver_memory_gb']:.1f} GB of points."]
  return "\n".join(lines) + "\n"


def plot(res: dict, out: Path) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
  runs = res["runs"]
  a.bar([r["config"] for r in runs], [r["seconds"] for r in runs], color="#4477aa")
  a.set_ylabel("wall seconds (fresh process)")
  a.set_title(f"{res['n_scans']} scans into one model")
  local = runs[0]["errors"]
  b.scatter(local["err_r"], local["err_t"], s=12)
  b.set_xlabel("rotation error (deg)")
  b.set_ylabel("translation error (mm)")
  b.set_title("poses against the ground truth (local run)")
  fig.tight_layout()
  fig.savefig(out / "scale.png", dpi=120)


def main() -> int:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--out", default="out/bench_multiway_scale")
  ap.add_argument("--variants", type=int, default=5)
  ap.add_argument("--foreign", type=int, default=3)
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--skip-ray", action="store_true")
  ap.add_argument("--skip-kill", action="store_true")
  ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
  ap.add_argument("--job-out", default=None, help=argparse.SUPPRESS)
  ap.add_argument("--kill-at", type=int, default=None, help=argparse.SUPPRESS)
  ap.add_argument("--scans", nargs="*", default=None, help=argparse.SUPPRESS)
  args = ap.parse_args()
  if args.child:
    return child(args.child, args.scans, args.job_out, args.kill_at)
  data = Path(os.environ.get("LRF_DATA", REPO / "data"))
  out = Path(args.out)
  paths, world = make_set(data, out, args.variants, args.foreign, args.seed)
  import lrf_jax
  lrf_jax.register(str(paths[0]), str(paths[1]))  # warm-up: the kernels in the on-disk cache
  configs = ["local"] + ([] if args.skip_ray else ["ray-1", "ray-2"])
  runs = []
  for config in configs:
    dest = out / "runs" / config
    if dest.exists():
      import shutil
      shutil.rmtree(dest)
    runs.append(run_child(config, paths, dest))
  if not args.skip_ray and not args.skip_kill:
    dest = out / "runs" / "kill"
    if dest.exists():
      import shutil
      shutil.rmtree(dest)
    n_pairs = runs[0]["registered"] or 150
    runs.append(run_child("ray-2", paths, dest, kill_at=n_pairs // 3) | {"config": "kill"})
    runs.append(run_child("local", paths, dest) | {"config": "rerun"})
  folders = {"rerun": "kill"}
  local_poses = read_poses(out / "runs" / "local")
  for r in runs:
    poses = read_poses(out / "runs" / folders.get(r["config"], r["config"]))
    r["errors"] = errors(poses, world)
    r["same_as_local"] = bool(np.allclose(poses, local_poses, atol=1e-9, equal_nan=True))
    r["max_diff_to_local"] = float(np.nanmax(np.abs(poses - local_poses)))
  res = dict(date=time.strftime("%Y-%m-%d"), machine=f"{platform.node()}, {os.cpu_count()} "
             "cores", n_scans=len(paths), n_object=sum(w is not None for w in world),
             n_foreign=sum(w is None for w in world), variants=args.variants, runs=runs,
             candidates=candidate_counts(), unit_costs=unit_costs(data))
  driver = sum(runs[0]["timings"].get(k, 0.0) for k in ("load", "graph", "refine"))
  res["projection"] = projection(res["unit_costs"], res["candidates"], driver, len(paths))
  report = make_report(res)
  (out / "results.json").write_text(json.dumps(res, indent=1, default=float))
  (out / "report.md").write_text(report)
  plot(res, out)
  print(report)
  return 0


if __name__ == "__main__":
  sys.exit(main())
