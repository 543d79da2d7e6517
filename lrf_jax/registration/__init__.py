"""Registration: a rigid transform between two (or many) scans from their LRFs.

  pipeline.py          `register`: keypoints, frames, descriptors, matches, hypotheses, the
                       verdict, ICP; pose errors, one-correspondence LRF RANSAC, 3-point RANSAC
  graph.py             the compatibility-graph estimator (distances and LRF poses that agree)
  host.py              hypotheses and inlier counts on the host (numpy, numba)
  icp_host.py          point-to-plane ICP (numba sums, damped Gauss-Newton step)
  multiway.py          `register_all`: every pair of many scans, then the pose graph
  pose_graph.py        the multiway pose graph (robust least squares)
  multiway_figures.py  its figures

The names below are this package's interface (they were `lrf_jax.registration`'s, a module,
before 0.7). The old module's other names still resolve here, with a `DeprecationWarning`, until
the next release; import them from their module.
"""

from __future__ import annotations

from typing import Any

from lrf_jax.registration.pipeline import (RansacResult, Registration, frame_point_triplets, icp,
                                           lrf_ransac, overlap_scores, pose_errors,
                                           pose_from_correspondence, ransac_3point, register,
                                           rotation_error_deg, to_transform)

__all__ = [
    "RansacResult", "Registration", "frame_point_triplets", "icp", "lrf_ransac", "overlap_scores",
    "pose_errors", "pose_from_correspondence", "ransac_3point", "register", "rotation_error_deg",
    "to_transform",
]

_SUBMODULES = frozenset({"graph", "host", "icp_host", "multiway", "multiway_figures", "pipeline",
                         "pose_graph"})
_warned = False


def __getattr__(name: str) -> Any:
  """The pre-0.7 module's other names (deprecated), forwarded to the module that has them."""
  global _warned
  from lrf_jax.registration import pipeline  # pylint: disable=import-outside-toplevel
  if name in _SUBMODULES or name.startswith("__") or not hasattr(pipeline, name):
    raise AttributeError(f"module 'lrf_jax.registration' has no attribute {name!r}")
  if not _warned:
    _warned = True
    from lrf_jax import _deprecated  # pylint: disable=import-outside-toplevel
    _deprecated.warn_moved(f"lrf_jax.registration.{name}", "lrf_jax.registration.pipeline",
                           stacklevel=2)
  return getattr(pipeline, name)
