"""Run the PCL reference driver and (re)generate lrf_jax's PCL agreement fixtures.

Build the driver once (needs `apt-get install libpcl-dev cmake g++`):

    cmake -S tools/pcl_driver -B tools/pcl_driver/build -DCMAKE_BUILD_TYPE=Release
    cmake --build tools/pcl_driver/build -j

Regenerate the fixtures (tests/fixtures/pcl_lrf_{shot,board,flare,rops}.npz):

    LRF_DATA=/path/to/data python tools/pcl_driver/run_pcl.py --fixtures

The fixtures hold, per method: the BR bunny keypoint indices (seeded), the support radius r = 15 mr
(mr = the mesh's mean edge length), PCL's frames (rows x, y, z; NaN where PCL failed) and, for
BOARD and FLARE, the normals that were fed to PCL at the keypoints plus a digest of the full
normal array, so that the test can check that it regenerates and feeds the very same normals
(`lrf_jax.geometry.normals.estimate_normals` at 0.2 r, oriented by the faces' winding). Every fixture also
stores PCL's own `NormalEstimation` normals at the keypoints (radius 0.2 r) for comparison.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
DRIVER = HERE / "build" / "pcl_lrf_driver"
FIXTURES = REPO / "tests" / "fixtures"
METHODS = ("shot", "board", "flare", "rops")
N_KEYPOINTS = 300
SEED = 2024
RADIUS_MR = 15.0


def driver_available() -> bool:
  return DRIVER.is_file() and os.access(DRIVER, os.X_OK)


def normals_digest(normals: np.ndarray) -> str:
  """Digest of the float32 normals as written for the driver (NaN-stable)."""
  arr = np.ascontiguousarray(np.nan_to_num(np.asarray(normals, np.float32), nan=9.0))
  return hashlib.sha256(arr.tobytes()).hexdigest()


def run_driver(points: np.ndarray, faces: np.ndarray | None, keypoints: np.ndarray, radius: float,
               *, normals: np.ndarray | None = None, methods=METHODS, z_radius: float | None = None,
               normal_radius: float | None = None, repeat: int = 1,
               threads: int = 2) -> dict[str, np.ndarray]:
  """Run `pcl_lrf_driver` and parse its output.

  Args:
    points: (n, 3) cloud (written as float32 text, exactly representable).
    faces: (f, 3) triangles or None (RoPS is skipped without).
    keypoints: (m,) indices.
    radius: support radius r.
    normals: (n, 3) normals for BOARD/FLARE (None: PCL's NormalEstimation).
    methods: subset of METHODS.
    z_radius: BOARD/FLARE z radius (driver default r / 3).
    normal_radius: PCL NormalEstimation radius (driver default r / 5).
    repeat: timing repeats (the fastest is reported).

  Returns:
    {method: (m, 3, 3) float32 frames, "pcl_normals": (m, 3), "time_<name>": seconds}.
  """
  if not driver_available():
    raise FileNotFoundError(f"{DRIVER} not built; see {HERE / 'run_pcl.py'}")
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    np.savetxt(tmp / "cloud.xyz", np.asarray(points, np.float32), fmt="%.9g")
    np.savetxt(tmp / "kp.txt", np.asarray(keypoints, np.int64), fmt="%d")
    cmd = [str(DRIVER), "--cloud", str(tmp / "cloud.xyz"), "--keypoints", str(tmp / "kp.txt"),
           "--radius", repr(float(radius)), "--out", str(tmp), "--methods", ",".join(methods),
           "--repeat", str(repeat), "--threads", str(int(threads))]
    if faces is not None:
      np.savetxt(tmp / "faces.txt", np.asarray(faces, np.int64), fmt="%d")
      cmd += ["--faces", str(tmp / "faces.txt")]
    if normals is not None:
      np.savetxt(tmp / "normals.txt", np.asarray(normals, np.float32), fmt="%.9g")
      cmd += ["--normals", str(tmp / "normals.txt")]
    if z_radius is not None:
      cmd += ["--z-radius", repr(float(z_radius))]
    if normal_radius is not None:
      cmd += ["--normal-radius", repr(float(normal_radius))]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    out: dict[str, np.ndarray] = {}
    for m in methods:
      f = tmp / f"{m}.txt"
      if f.exists():
        out[m] = np.loadtxt(f, ndmin=2).reshape(-1, 3, 3).astype(np.float32)
    out["pcl_normals"] = np.loadtxt(tmp / "pcl_normals.txt", ndmin=2).astype(np.float32)
    for line in (tmp / "timings.txt").read_text().splitlines():
      name, sec = line.split()
      out[f"time_{name}"] = float(sec)
  return out


def bunny(data_root: Path):
  sys.path.insert(0, str(REPO))
  from tests.lrf_testing import load_br_model  # noqa: E402
  return load_br_model(data_root, "bunny")


def make_fixtures(data_root: Path) -> None:
  """Write tests/fixtures/pcl_lrf_*.npz (see the module docstring)."""
  sys.path.insert(0, str(REPO))
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals

  points, faces, mr, _ = bunny(data_root)
  radius = RADIUS_MR * mr
  keypoints = np.sort(np.random.default_rng(SEED).choice(points.shape[0], N_KEYPOINTS,
                                                          replace=False))
  normals = estimate_normals(points, NORMAL_RADIUS_RATIO * radius, faces).astype(np.float32)
  res = run_driver(points, faces, keypoints, radius, normals=normals,
                   normal_radius=NORMAL_RADIUS_RATIO * radius)
  FIXTURES.mkdir(parents=True, exist_ok=True)
  for m in METHODS:
    frames = res[m]
    extra = {}
    if m in ("board", "flare"):
      extra = {"kp_normals_fed": normals[keypoints], "normals_digest": normals_digest(normals)}
    np.savez_compressed(
        FIXTURES / f"pcl_lrf_{m}.npz", keypoints=keypoints.astype(np.int32),
        radius=np.float64(radius), mr=np.float64(mr), frames=frames,
        valid=np.isfinite(frames).all(axis=(1, 2)), pcl_normals=res["pcl_normals"],
        normal_radius=np.float64(NORMAL_RADIUS_RATIO * radius),
        z_radius=np.float64(radius / 3.0), source=np.str_("PCL 1.13 via tools/pcl_driver"),
        **extra)
    print(f"{m}: {np.isfinite(frames).all(axis=(1, 2)).sum()} / {len(frames)} finite frames "
          f"-> {FIXTURES / f'pcl_lrf_{m}.npz'}")


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  ap.add_argument("--fixtures", action="store_true", help="regenerate tests/fixtures/pcl_lrf_*.npz")
  ap.add_argument("--data", default=os.environ.get("LRF_DATA", str(REPO / "data")))
  args = ap.parse_args()
  if args.fixtures:
    make_fixtures(Path(args.data))
  else:
    ap.print_help()


if __name__ == "__main__":
  main()
