"""Full-density fused fragments made from depth frames, the way 3DMatch made its fragments.

    from benchmarks._fused_fragments import fused_fragments
    frags = fused_fragments("/path/to/livingroom1_clean_micro", cache="out/fused")

The input is a folder of 640 x 480 depth PNGs (`depth/00000.png`, ..., millimetres) with their
camera trajectory (`test_scene/trajectory.log`, Redwood's log format: a header line and a 4 x 4
camera-to-world pose per frame), as in Open3D's reconstruction-system test data
(`examples/test_data/reconstruction_system/livingroom1_clean_micro` in the Open3D repository:
211 frames of the synthetic ICL-NUIM living room, noise-free depth, PrimeSense intrinsics).
Consecutive runs of `FRAMES` frames are fused by Open3D 0.20's TSDF (`VoxelBlockGrid`, 6 mm
voxels, depth cut at 3 m) and each surface extracted as a point cloud in the frame of its run's
first camera: 242k-300k points at 3.0-4.1 mm spacing (3DMatch's fragments, TSDF fusion of 50
frames: 25k-314k points). Ground truth of a pair (i, j): inv(pose_j) pose_i, the fragments' first cameras.
A voxelized copy of each (`voxel_down_sample(0.025)`) is the 2.5 cm version the benchmarks use.
Needs open3d (a benchmark dependency); the fragments are cached as .npy under `cache`.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from lrf_jax.io.atomic import atomic_path

FRAMES = 40  # frames per fragment (the last run takes the remainder)
VOXEL = 0.006  # TSDF voxel (m)
DEPTH_MAX = 3.0  # m
INTRINSIC = ((525.0, 0.0, 319.5), (0.0, 525.0, 239.5), (0.0, 0.0, 1.0))  # PrimeSense default


def read_log(path: Path) -> list[np.ndarray]:
  """The 4 x 4 camera-to-world poses of a Redwood trajectory .log file."""
  lines = [line for line in Path(path).read_text().splitlines() if line.strip()]
  return [np.array([[float(x) for x in lines[5 * k + i].split()] for i in range(1, 5)])
          for k in range(len(lines) // 5)]


def _fuse(folder: Path, poses: list[np.ndarray], first: int, last: int) -> np.ndarray:
  import open3d as o3d
  import open3d.core as o3c
  grid = o3d.t.geometry.VoxelBlockGrid(
      attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
      attr_channels=((1), (1)), voxel_size=VOXEL, block_resolution=16, block_count=60000,
      device=o3c.Device("CPU:0"))
  K = o3c.Tensor(np.array(INTRINSIC), o3c.float64)
  for k in range(first, last):
    depth = o3d.t.io.read_image(str(folder / "depth" / f"{k:05d}.png"))
    world_to_camera = np.linalg.inv(np.linalg.inv(poses[first]) @ poses[k])
    ext = o3c.Tensor(world_to_camera, o3c.float64)
    blocks = grid.compute_unique_block_coordinates(depth, K, ext, 1000.0, DEPTH_MAX)
    grid.integrate(blocks, depth, K, ext, 1000.0, DEPTH_MAX)
  return np.asarray(grid.extract_point_cloud().point.positions.numpy(), np.float64)


def fused_fragments(folder: str | Path, cache: str | Path) -> list[dict]:
  """The fragments of `folder`: a list of dict(full=(n, 3), coarse=(m, 3), pose=(4, 4)), each
  pose the fragment frame's camera-to-world transform."""
  import open3d as o3d
  folder, cache = Path(folder), Path(cache)
  poses = read_log(folder / "test_scene" / "trajectory.log")
  n = min(len(poses), len(list((folder / "depth").glob("*.png"))))
  starts = list(range(0, n - FRAMES // 2, FRAMES))
  # The cache is keyed by the input folder and every setting of the fusion.
  key = hashlib.sha256(f"{folder.resolve()} {FRAMES} {VOXEL} {DEPTH_MAX} {INTRINSIC}".encode())
  cache = cache / key.hexdigest()[:16]
  cache.mkdir(parents=True, exist_ok=True)
  out = []
  for f, first in enumerate(starts):
    last = starts[f + 1] if f + 1 < len(starts) else n
    path = cache / f"fragment_{f}_{first}_{last}.npy"
    if not path.exists():
      with atomic_path(path) as tmp:  # a temporary name beside it, renamed into place
        np.save(tmp, _fuse(folder, poses, first, last))
    full = np.load(path)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(full))
    coarse = np.asarray(cloud.voxel_down_sample(0.025).points)
    out.append(dict(full=full, coarse=coarse, pose=poses[first]))
  return out
