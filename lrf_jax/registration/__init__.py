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

The names below are this package's interface (they were `lrf_jax.registration`'s, a module,
before 0.7). The old module's other names still resolve here, with a `DeprecationWarning`, until
the next release; import them from their module.
"""

from __future__ import annotations

from typing import Any

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

_SUBMODULES = frozenset({"errors", "estimators", "evidence", "graph", "host", "icp_host",
                         "multiway", "multiway_figures", "pipeline", "pose_graph"})
_warned = False


def __getattr__(name: str) -> Any:
  """The pre-0.7 module's other names (deprecated), forwarded to the module that has them now."""
  global _warned
  missing = AttributeError(f"module 'lrf_jax.registration' has no attribute {name!r}")
  if name in _SUBMODULES or name.startswith("__"):  # before any import: no recursion
    raise missing
  # pylint: disable=import-outside-toplevel
  from lrf_jax.registration import errors, estimators, evidence, icp_host, pipeline
  home = next((m for m in (evidence, estimators, errors, icp_host, pipeline)  # homes first
               if hasattr(m, name)), None)
  if home is None:
    raise missing
  if not _warned:
    _warned = True
    from lrf_jax import _deprecated
    _deprecated.warn_moved(f"lrf_jax.registration.{name}", home.__name__, stacklevel=2)
  return getattr(home, name)
