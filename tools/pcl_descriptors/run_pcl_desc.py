"""Run the PCL descriptor driver: (re)generate lrf_jax's descriptor fixtures, or compare live.

Build the driver once (needs `apt-get install libpcl-dev cmake g++`):

    cmake -S tools/pcl_descriptors -B tools/pcl_descriptors/build -DCMAKE_BUILD_TYPE=Release
    cmake --build tools/pcl_descriptors/build -j

Regenerate the CI fixture (tests/fixtures/pcl_desc_demo.npz; no data needed):

    python tools/pcl_descriptors/run_pcl_desc.py --fixtures

Compare live on the BR bunny (needs LRF_DATA) with LRF-Net frames, 1000 keypoints:

    LRF_DATA=/path/to/data python tools/pcl_descriptors/run_pcl_desc.py --compare-br 1000

The fixture is self-contained: a crop of the procedural demo blob (float32 points), the normals
fed to PCL (lrf_jax's default normals of the crop, float32), seeded interior keypoints, their
LRF-Net frames (external LRFs, float32), r = 15 mr, and PCL's SHOT352 and RoPS descriptors.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
DRIVER = HERE / "build" / "pcl_desc_driver"
FIXTURE = REPO / "tests" / "fixtures" / "pcl_desc_demo.npz"
RADIUS_MR = 15.0
CROP_MR = 36.0
N_KEYPOINTS = 64
SEED = 7


def driver_available() -> bool:
  return DRIVER.is_file() and os.access(DRIVER, os.X_OK)


def run_driver(points: np.ndarray, normals: np.ndarray, keypoints: np.ndarray, frames: np.ndarray,
               radius: float, *, methods: str = "shot,rops", repeat: int = 1) -> dict:
  """Run `pcl_desc_driver` and parse its output.

  Args:
    points: (n, 3) cloud (written as float32, exactly).
    normals: (n, 3) normals (NaN allowed).
    keypoints: (m,) indices.
    frames: (m, 3, 3) rows x, y, z.
    radius: r.
    methods: "shot", "rops" or "shot,rops".
    repeat: timing repetitions.

  Returns:
    {"shot": (m, 352), "rops": (m, 135), "timings": {name: seconds}} (the methods run).
  """
  if not driver_available():
    raise FileNotFoundError(f"{DRIVER} not built; see the module docstring")
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    np.savetxt(tmp / "cloud.txt", np.asarray(points, np.float32), fmt="%.9g")
    np.savetxt(tmp / "normals.txt", np.asarray(normals, np.float32), fmt="%.9g")
    np.savetxt(tmp / "kp.txt", np.asarray(keypoints, np.int64), fmt="%d")
    np.savetxt(tmp / "frames.txt", np.asarray(frames, np.float32).reshape(-1, 9), fmt="%.9g")
    cmd = [str(DRIVER), "--cloud", str(tmp / "cloud.txt"), "--normals", str(tmp / "normals.txt"),
           "--keypoints", str(tmp / "kp.txt"), "--frames", str(tmp / "frames.txt"),
           "--radius", repr(float(np.float32(radius))), "--out", str(tmp), "--methods", methods,
           "--repeat", str(repeat)]
    subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
    out = {}
    for name, dim in (("shot", 352), ("rops", 135)):
      if name in methods:
        out[name] = np.loadtxt(tmp / f"{name}.txt", ndmin=2).reshape(-1, dim)
    out["timings"] = {line.split()[0]: float(line.split()[1])
                      for line in (tmp / "timings.txt").read_text().splitlines() if line.strip()}
  return out


def ours(points, normals, keypoints, frames, radius):
  """lrf_jax's SHOT and RoPS for the same inputs: {"shot": (m, 352), "rops": (m, 135)}."""
  from lrf_jax.descriptors import compute_descriptors
  out = {}
  for name in ("shot", "rops"):
    opts = {"align_normals": False} if name == "shot" else {}  # PCL's SHOT uses normals as given
    d, v = compute_descriptors(points, keypoints, radius, frames, None, name, normals=normals,
                               **opts)
    out[name] = np.asarray(d)
    out[name + "_valid"] = np.asarray(v)
  return out


def agreement(a: np.ndarray, b: np.ndarray) -> dict:
  """Per-keypoint relative L2 difference |a - b| / |b| and summary statistics."""
  rel = np.linalg.norm(a - b, axis=1) / np.maximum(np.linalg.norm(b, axis=1), 1e-12)
  return {"median_rel": float(np.median(rel)), "max_rel": float(rel.max()),
          "frac_below_1e-4": float(np.mean(rel < 1e-4)), "max_abs": float(np.abs(a - b).max()),
          "rel": rel}


def make_fixture() -> None:
  import lrf_jax
  from lrf_jax import datasets
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals

  pts, faces = datasets.make_demo_mesh("blob", 0)
  mr, _ = datasets.mesh_resolution(pts, faces)
  radius = RADIUS_MR * mr
  center = pts[0]
  keep = np.linalg.norm(pts - center, axis=1) <= CROP_MR * mr
  crop = pts[keep].astype(np.float32)
  crop64 = crop.astype(np.float64)
  normals = estimate_normals(crop64, NORMAL_RADIUS_RATIO * radius).astype(np.float32)
  inner = np.flatnonzero(np.linalg.norm(crop64 - center, axis=1) <= (CROP_MR - RADIUS_MR - 1) * mr)
  rng = np.random.default_rng(SEED)
  kp = np.sort(rng.choice(inner, N_KEYPOINTS, replace=False))
  frames, valid = lrf_jax.compute_frames(crop64, kp, radius, "lrf_net")
  frames = np.asarray(frames, np.float32)
  assert np.all(np.asarray(valid))
  pcl = run_driver(crop64, normals, kp, frames, radius)
  FIXTURE.parent.mkdir(parents=True, exist_ok=True)
  np.savez_compressed(FIXTURE, points=crop, normals=normals, keypoints=kp.astype(np.int32),
                      frames=frames, radius=np.float64(radius), shot=pcl["shot"].astype(np.float32),
                      rops=pcl["rops"].astype(np.float32))
  mine = ours(crop64, normals, kp, frames, radius)
  for name in ("shot", "rops"):
    s = agreement(mine[name], pcl[name])
    print(f"{name}: median rel {s['median_rel']:.2e}, max rel {s['max_rel']:.2e}, "
          f"fraction < 1e-4: {s['frac_below_1e-4']:.3f}")
  print(f"wrote {FIXTURE} ({FIXTURE.stat().st_size / 1024:.0f} KiB), {len(crop)} points, "
        f"{len(kp)} keypoints")


def compare_br(n: int) -> None:
  import lrf_jax
  from lrf_jax import datasets
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals

  model = datasets.load_br_model("bunny")
  pts, faces, mr = model.points, model.faces, model.mr
  radius = RADIUS_MR * mr
  normals = estimate_normals(pts, NORMAL_RADIUS_RATIO * radius, faces).astype(np.float32)
  kp = np.sort(np.random.default_rng(SEED).choice(len(pts), n, replace=False))
  pts32 = pts.astype(np.float32).astype(np.float64)  # what PCL sees
  frames, valid = lrf_jax.compute_frames(pts32, kp, radius, "lrf_net")
  frames = np.asarray(frames, np.float32)
  t0 = time.perf_counter()
  pcl = run_driver(pts32, normals, kp, frames, radius)
  t_pcl = time.perf_counter() - t0
  mine = ours(pts32, normals, kp, frames, radius)
  print(f"BR bunny, {n} keypoints, r = 15 mr, LRF-Net frames ({int(np.sum(valid))} valid); "
        f"PCL driver wall {t_pcl:.1f} s, {pcl['timings']}")
  for name in ("shot", "rops"):
    ok = np.all(np.isfinite(pcl[name]), axis=1)
    s = agreement(mine[name][ok], pcl[name][ok])
    worst = np.argsort(s["rel"])[-3:]
    print(f"{name}: {ok.sum()} finite in PCL, ours valid {mine[name + '_valid'].sum()}; "
          f"median rel {s['median_rel']:.2e}, max rel {s['max_rel']:.2e}, "
          f"fraction < 1e-4: {s['frac_below_1e-4']:.4f}, fraction < 1e-2: "
          f"{np.mean(s['rel'] < 1e-2):.4f}; worst rel {s['rel'][worst]}")


def main(argv=None) -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--fixtures", action="store_true", help=f"write {FIXTURE.name}")
  ap.add_argument("--compare-br", type=int, default=0, metavar="N",
                  help="compare on N BR bunny keypoints (needs LRF_DATA)")
  args = ap.parse_args(argv)
  if not (args.fixtures or args.compare_br):
    ap.error("nothing to do: pass --fixtures and/or --compare-br N")
  if args.fixtures:
    make_fixture()
  if args.compare_br:
    compare_br(args.compare_br)


if __name__ == "__main__":
  sys.path.insert(0, str(REPO))
  main()
