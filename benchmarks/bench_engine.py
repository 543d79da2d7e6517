"""The neighborhood engine: patches/s against the cKDTree search it replaced, and frames/s of the
default `compute_frames` call of every method beside PCL 1.13's same LRF, in one run.

    LRF_DATA=/path/to/data python benchmarks/bench_engine.py [--cases bunny:10000 dragon:10000]
        [--cases kitti:100000]  (raw KITTI sweep 000000, 124,668 points, r = 15 mean NN spacings)
        [--methods lrf_net shot ...] [--repeat 3]

Patches: `lrf_jax.build_patches(points, kp, r, 256)` on the BR bunny (34,834 vertices), 10,000
seeded keypoints, r = 15 mr, a fresh index on every call (index build and r/3 statistics
included), against `benchmarks/_ckdtree_patches.py` (the previous cKDTree implementation,
identical output, checked here).

Frames: the default call (`compute_frames(points, kp, r, method)`, plus `faces=` for the mesh
methods), search and normals included: every timed call gets the cloud under a fresh seeded rigid
motion (rotation and translation, applied outside the timing), so that nothing kept for a cloud
(normals, their orientation, areas, k-NN) skips work, and the caches are cleared before it too.
The first call (compilation) is excluded; each figure is the median of `--repeat` calls.
PCL (tools/pcl_driver, 2 threads where PCL has them): SHOT LRF (the faster of
`SHOTLocalReferenceFrameEstimation` and its OMP class with 2 threads), BOARD and FLARE (plus PCL's
`NormalEstimationOMP` over every point with 2 threads, the normals they need), RoPS; every other
method is set beside PCL's SHOT.
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
sys.path.insert(0, str(REPO / "benchmarks"))

import lrf_jax  # noqa: E402
from lrf_jax import datasets  # noqa: E402
from lrf_jax.search import engine  # noqa: E402
from lrf_jax.geometry import normals as normals_cache  # noqa: E402

# PCL's implementation of the same LRF, where it has one.
PCL_SAME = {"shot": "shot_omp", "board": "board", "flare": "flare", "rops": "rops"}


def _median_time(fn, repeat: int, moved: np.ndarray | None = None) -> float:
  """Median seconds of `repeat` calls of `fn()`, or of `fn(cloud)` with `moved` given: each
  call then on `moved` under its own seeded rigid motion (made before the clock starts)."""
  times = []
  for i in range(repeat):
    args = () if moved is None else (_moved(moved, i),)
    normals_cache.CLOUD_CACHE.clear()
    t0 = time.perf_counter()
    fn(*args)
    times.append(time.perf_counter() - t0)
  return float(np.median(times))


def _moved(points: np.ndarray, i: int) -> np.ndarray:
  """`points` under the seeded rigid motion number i (a rotation and a translation of about the
  cloud's size)."""
  motion = datasets.random_rigid_motion(1000 + i, scale=float(np.ptp(points, 0).max()))
  return np.asarray(points, np.float64) @ motion[:3, :3].T + motion[:3, 3]


def bench_patches(data: str | None, repeat: int) -> None:
  from _ckdtree_patches import ckdtree_build_patches
  mesh = datasets.load_br_model("bunny", data)
  pts = mesh.points
  r = 15 * datasets.mesh_resolution(pts, mesh.faces)[0]
  kp = np.random.default_rng(0).choice(len(pts), 10_000, replace=False)
  new = lrf_jax.build_patches(pts, kp, r, 256)
  old = ckdtree_build_patches(pts, kp, r, 256)
  same = all(np.array_equal(getattr(new, f), getattr(old, f))
             for f in ("indices", "mask", "count", "z_count", "offsets"))
  t_new = _median_time(lambda: lrf_jax.build_patches(pts, kp, r, 256), repeat)
  t_old = _median_time(lambda: ckdtree_build_patches(pts, kp, r, 256), repeat)
  print(f"### build_patches, BR bunny ({len(pts):,} points), 10,000 keypoints, K = 256, "
        f"index build included ({engine.num_threads()} threads)\n")
  print("| search | keypoints/s | ratio |\n|---|---:|---:|")
  print(f"| engine (lrf_jax.build_patches) | {1e4 / t_new:,.0f} | {t_old / t_new:.1f} |")
  print(f"| cKDTree (previous implementation) | {1e4 / t_old:,.0f} | 1.0 |")
  print(f"\nidentical indices, mask, count, z_count, offsets: {same}\n")


def _case_cloud(model: str, data: str | None) -> tuple[np.ndarray, np.ndarray | None]:
  """A BR model's (points, faces), or with model "kitti" raw KITTI sweep 000000 (no faces)."""
  if model == "kitti":
    root = Path(data or "") / "lidar_kitti00" / "000000.bin"
    return np.asarray(lrf_jax.io.read_cloud(root).points, np.float64), None
  mesh = datasets.load_br_model(model, data)
  return mesh.points, mesh.faces


def bench_frames(data: str | None, cases: list[tuple[str, int]], methods: list[str],
                 repeat: int, use_pcl: bool) -> None:
  pcl = None
  if use_pcl:
    try:
      from run_pcl import driver_available, run_driver
      pcl = run_driver if driver_available() else None
    except ImportError:
      pcl = None
  print("### Frames/s of the default call, search and normals included\n")
  print("| cloud | keypoints | method | lrf_jax /s | PCL | PCL /s | ratio |")
  print("|---|---:|---|---:|---|---:|---:|")
  for model, m in cases:
    pts, faces = _case_cloud(model, data)
    r = 15 * datasets.mesh_resolution(pts, faces)[0]
    kp = np.random.default_rng(0).choice(len(pts), m, replace=m > len(pts))
    pcl_rate = {}
    if pcl is not None:
      # Only the PCL methods some requested method is set beside.
      names = ["shot", "shot_omp"] + [p for p in ("board", "flare", "rops") if p in methods]
      names += ["normals_omp"] if {"board", "flare"} & set(methods) else []
      res = [pcl(pts, faces, kp, r, methods=names, repeat=1)
             for _ in range(repeat if m <= 10_000 else 1)]
      t = {k: float(np.median([x[f"time_{k}"] for x in res])) for k in names}
      # PCL's SHOT LRF: the faster of its single-threaded and OpenMP (2 threads) classes.
      pcl_rate = {"shot_omp": m / min(t["shot"], t["shot_omp"])}
      if "rops" in t:
        pcl_rate["rops"] = m / t["rops"]
      for p in ("board", "flare"):
        if p in t:
          pcl_rate[p] = m / (t[p] + t["normals_omp"])
    for method in methods:
      if lrf_jax.METHODS[method].needs_mesh and faces is None:
        continue  # a sweep has no mesh
      kw = {"faces": faces} if lrf_jax.METHODS[method].needs_mesh else {}
      call = lambda cloud: lrf_jax.compute_frames(  # noqa: E731
          cloud, kp, r, method, progress=False,  # noqa: B023 (called in this iteration)
          **kw)[0].block_until_ready()  # noqa: B023
      lrf_jax.compute_frames(pts, kp[:min(m, 4096)], r, method, progress=False, **kw)
      dt = _median_time(call, repeat if m <= 10_000 else 1, moved=pts)
      peer = PCL_SAME.get(method, "shot_omp")
      name = {"shot_omp": "SHOT", "board": "BOARD + normals",
              "flare": "FLARE + normals", "rops": "RoPS"}[peer]
      if peer != PCL_SAME.get(method):
        name = f"({name})"
      rate = pcl_rate.get(peer)
      cells = (f"{rate:,.0f} | {m / dt / rate:.2f}" if rate else "n/a | n/a")
      print(f"| {model} ({len(pts):,}) | {m:,} | {method} | {m / dt:,.0f} | {name} | {cells} |",
            flush=True)
  if pcl is None:
    print("\n(PCL driver not built: see tools/pcl_driver/run_pcl.py)")


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--cases", nargs="+", default=["bunny:10000", "dragon:10000", "dragon:100000"])
  ap.add_argument("--methods", nargs="+",
                  default=[m for m in lrf_jax.METHODS if m != "lrf_net_variant"])
  ap.add_argument("--repeat", type=int, default=3)
  ap.add_argument("--no-pcl", action="store_true")
  ap.add_argument("--skip-patches", action="store_true")
  args = ap.parse_args()
  print(f"machine: {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} on "
        f"{jax.devices()[0].platform}; engine threads {engine.num_threads()}\n")
  if not args.skip_patches:
    bench_patches(args.data, args.repeat)
  cases = [(c.split(":")[0], int(c.split(":")[1])) for c in args.cases]
  bench_frames(args.data, cases, args.methods, args.repeat, not args.no_pcl)


if __name__ == "__main__":
  main()
