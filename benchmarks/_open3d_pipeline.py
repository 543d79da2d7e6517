"""Open3D 0.20's global registration pipeline (its tutorial), shared by the benchmarks.

    from benchmarks._open3d_pipeline import global_registration
    out = global_registration(source, target, voxel=0.05, seed=0)   # out["final"]: (4, 4)

The steps and settings of Open3D's "Global registration" tutorial
(`docs/tutorial/pipelines/global_registration.ipynb`): voxel downsampling at `voxel`; normals
from a hybrid search (radius 2 voxel, 30 neighbors); FPFH (radius 5 voxel, 100 neighbors);
`registration_ransac_based_on_feature_matching` with mutual filtering, point-to-point
estimation, 3 points per hypothesis, the edge-length (0.9) and distance (1.5 voxel) checkers and
`RANSACConvergenceCriteria(100000, 0.999)`; then `registration_icp` on the full clouds, either
point-to-plane at the tutorial's 0.4 voxel (target normals estimated on the full target, radius
2 voxel, 30 neighbors) or point-to-point at a caller-given distance.
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np

Refine = Literal["point_to_plane", "point_to_point"]


def have_open3d() -> bool:
  """Whether open3d can be imported."""
  try:
    import open3d  # noqa: F401
  except ImportError:
    return False
  return True


def global_registration(source: np.ndarray, target: np.ndarray, *, voxel: float, seed: int = 0,
                        refine: Refine = "point_to_plane", icp_distance: float | None = None,
                        icp_iterations: int = 30) -> dict:
  """FPFH + RANSAC at `voxel`, then ICP, as Open3D's global registration tutorial does.

  Args:
    source: (n, 3) points (cloud units).
    target: (m, 3) points, same units.
    voxel: voxel size of the downsampling, in cloud units (FPFH and RANSAC distances follow it).
    seed: Open3D's random seed (`open3d.utility.random.seed`); the same seed gives the same
      result.
    refine: "point_to_plane" (the tutorial's refinement) or "point_to_point".
    icp_distance: ICP pairing distance in cloud units (None: the tutorial's 0.4 voxel).
    icp_iterations: ICP iteration cap (Open3D's default 30).

  Returns:
    {"coarse": (4, 4) RANSAC estimate, "final": (4, 4) after ICP, "seconds": wall time of the
    whole call, "seconds_coarse": up to the end of RANSAC, "n_points": (downsampled source,
    downsampled target), "fitness": Open3D's ICP fitness, "inlier_rmse": its RMSE}; transforms
    map the source onto the target.

  Raises:
    ValueError: a non-positive voxel or ICP distance, or an unknown `refine`.
    ImportError: open3d is not installed.
  """
  if not voxel > 0:
    raise ValueError(f"voxel: expected a positive size, found {voxel!r}")
  if refine not in ("point_to_plane", "point_to_point"):
    raise ValueError(f"refine: expected 'point_to_plane' or 'point_to_point', found {refine!r}")
  distance = 0.4 * voxel if icp_distance is None else icp_distance
  if not distance > 0:
    raise ValueError(f"icp_distance: expected a positive distance, found {icp_distance!r}")
  import open3d as o3d
  reg = o3d.pipelines.registration
  o3d.utility.random.seed(seed)
  t0 = time.perf_counter()
  feats = []
  for pts in (source, target):
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(pts, np.float64)))
    down = pc.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = reg.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    feats.append((pc, down, fpfh))
  (pc_s, down_s, f_s), (pc_t, down_t, f_t) = feats
  dist = 1.5 * voxel
  coarse = reg.registration_ransac_based_on_feature_matching(
      down_s, down_t, f_s, f_t, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
      [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
       reg.CorrespondenceCheckerBasedOnDistance(dist)],
      reg.RANSACConvergenceCriteria(100000, 0.999))
  t_coarse = time.perf_counter() - t0
  if refine == "point_to_plane":
    pc_t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    estimation = reg.TransformationEstimationPointToPlane()
  else:
    estimation = reg.TransformationEstimationPointToPoint()
  fine = reg.registration_icp(pc_s, pc_t, distance, coarse.transformation, estimation,
                              reg.ICPConvergenceCriteria(max_iteration=icp_iterations))
  return {"coarse": np.array(coarse.transformation), "final": np.array(fine.transformation),
          "seconds_coarse": t_coarse, "seconds": time.perf_counter() - t0,
          "n_points": (len(down_s.points), len(down_t.points)), "fitness": float(fine.fitness),
          "inlier_rmse": float(fine.inlier_rmse)}
