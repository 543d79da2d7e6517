"""KISS-Matcher (MIT-SPARK, `pip install kiss-matcher`) with an ICP after it, as its README pipes
it, shared by the benchmarks.

    from benchmarks._kiss_matcher_pipeline import kiss_registration
    out = kiss_registration(source, target, voxel=0.3)   # out["final"], out["valid"]

KISS-Matcher's Python API: `KISSMatcherConfig(voxel_size)`, `KISSMatcher(config).estimate(src,
tgt)` (voxel sampling, its faster PFH, ROBIN matching and the GNC solver) gives a rotation, a
translation and `valid`; its README calls a result with fewer than 5 final inliers a possible
failure. The estimate is then refined by Open3D's point-to-plane `registration_icp` on the
full clouds at 0.4 voxel (target normals: radius 2 voxel, 30 neighbours), as
`_open3d_pipeline.py` refines its own. "Claimed" here is `valid` with at least 5 final
inliers: KISS-Matcher's own word on its result.
"""

from __future__ import annotations

import time

import numpy as np

# The README's "registration might have failed" line: fewer final inliers than this.
MIN_INLIERS = 5


def have_kiss_matcher() -> bool:
  """Whether kiss_matcher and open3d (its ICP) can be imported."""
  try:
    import kiss_matcher  # noqa: F401
    import open3d  # noqa: F401
  except ImportError:
    return False
  return True


def kiss_registration(source: np.ndarray, target: np.ndarray, *, voxel: float,
                      icp_iterations: int = 30) -> dict:
  """KISS-Matcher at `voxel`, then point-to-plane ICP at 0.4 voxel.

  Args:
    source: (n, 3) points (cloud units).
    target: (m, 3) points, same units.
    voxel: KISS-Matcher's voxel size (cloud units; its default 0.3 is for LiDAR in metres).
    icp_iterations: ICP iteration cap (Open3D's default 30).

  Returns:
    {"coarse": (4, 4) KISS-Matcher's estimate, "final": (4, 4) after ICP, "valid": its
    `valid` and at least `MIN_INLIERS` final inliers, "inliers": the final inlier count,
    "seconds": wall time of the whole call}; transforms map the source onto the target.

  Raises:
    ValueError: a non-positive voxel.
    ImportError: kiss_matcher or open3d is not installed.
  """
  if not voxel > 0:
    raise ValueError(f"voxel: expected a positive size, found {voxel!r}")
  import kiss_matcher
  import open3d as o3d
  reg = o3d.pipelines.registration
  t0 = time.perf_counter()
  matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(float(voxel)))
  sol = matcher.estimate(np.asarray(source, np.float32), np.asarray(target, np.float32))
  coarse = np.eye(4)
  coarse[:3, :3] = np.asarray(sol.rotation, np.float64)
  coarse[:3, 3] = np.asarray(sol.translation, np.float64).ravel()
  inliers = int(matcher.get_num_final_inliers())
  pc_s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(source, np.float64)))
  pc_t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(target, np.float64)))
  pc_t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
  icp = reg.registration_icp(pc_s, pc_t, 0.4 * voxel, coarse,
                             reg.TransformationEstimationPointToPlane(),
                             reg.ICPConvergenceCriteria(max_iteration=icp_iterations))
  return {"coarse": coarse, "final": np.asarray(icp.transformation), "inliers": inliers,
          "valid": bool(sol.valid) and inliers >= MIN_INLIERS,
          "seconds": time.perf_counter() - t0}
