"""Registration: a rigid transform between two (or many) scans from their LRFs.

  pipeline.py          `register`: keypoints, frames, descriptors, matches, hypotheses, ICP
  errors.py            pose errors (the paper's err_r, err_t), 4x4 transforms
  estimators.py        the minimal solvers, one-correspondence LRF RANSAC, 3-point RANSAC
  graph.py             the compatibility-graph estimator (distances and LRF poses that agree)
  host.py              hypotheses and inlier counts on the host (numpy, numba)
  evidence.py          whether a registration is believed: the evidence and the verdict
  icp_host.py          ICP: point-to-point and point-to-plane (numba sums, Gauss-Newton step)
  multiway.py          `register_all`: every pair of many scans, then the pose graph
  pose_graph.py        the multiway pose graph (robust least squares)
  multiway_figures.py  its figures

The names below are this package's interface; every other name is imported from its module.
"""

from __future__ import annotations

from lrf_jax.registration.errors import pose_errors, rotation_error_deg, to_transform
from lrf_jax.registration.estimators import (RansacResult, frame_point_triplets, lrf_ransac,
                                             pose_from_correspondence, ransac_3point)
from lrf_jax.registration.icp_host import icp
from lrf_jax.registration.pipeline import Registration, overlap_scores, register

__all__ = [
    "RansacResult", "Registration", "frame_point_triplets", "icp", "lrf_ransac", "overlap_scores",
    "pose_errors", "pose_from_correspondence", "ransac_3point", "register", "rotation_error_deg",
    "to_transform",
]
