"""Registration: a rigid transform between two (or many) scans from their LRFs.

  pipeline.py          `register`: the stages, then the verdict
  options.py           `RegisterOptions`: every option of `register` and its default, once
  stages.py            prepare, describe, match, hypothesize, verify (typed results)
  rivals.py            the verdict's counts: chance level, rivals, the overlap's constraints
  refine.py            the ICP stage, and `register(..., init=T)`
  result.py            `Registration`, what `register` returns
  errors.py            pose errors (the paper's err_r, err_t), 4x4 transforms
  estimators.py        the minimal solvers, one-correspondence LRF RANSAC, 3-point RANSAC
  graph.py             the compatibility-graph estimator (distances and LRF poses that agree)
  host.py              hypotheses and inlier counts on the host (numpy, numba)
  evidence.py          whether a registration is believed: the evidence and the verdict
  icp_host.py          ICP: point-to-point and point-to-plane (numba sums, Gauss-Newton step)
  scan_features.py     one scan's features described once, two scans' features registered

Many scans into one model (`register_all`) are `lrf_jax.multiway`, above this package.

The names below are this package's interface; every other name is imported from its module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
  from lrf_jax.registration.errors import pose_errors, rotation_error_deg, to_transform
  from lrf_jax.registration.estimators import (RansacResult, frame_point_triplets, lrf_ransac,
                                               pose_from_correspondence, ransac_3point)
  from lrf_jax.registration.icp_host import icp
  from lrf_jax.registration.options import RegisterOptions
  from lrf_jax.registration.pipeline import Registration, overlap_scores, register

# name -> its module; loaded on first use, so that the options (and the command lines' --help,
# which read them) load no registration code.
_HOMES = {
    "pose_errors": "errors", "rotation_error_deg": "errors", "to_transform": "errors",
    "RansacResult": "estimators", "frame_point_triplets": "estimators",
    "lrf_ransac": "estimators", "pose_from_correspondence": "estimators",
    "ransac_3point": "estimators", "icp": "icp_host", "RegisterOptions": "options",
    "Registration": "pipeline", "overlap_scores": "pipeline", "register": "pipeline",
}
__all__ = [
    "RansacResult", "RegisterOptions", "Registration", "frame_point_triplets", "icp", "lrf_ransac",
    "overlap_scores", "pose_errors", "pose_from_correspondence", "ransac_3point", "register",
    "rotation_error_deg", "to_transform",
]


def __getattr__(name: str) -> Any:
  home = _HOMES.get(name)
  if home == "errors":
    from lrf_jax.registration import errors
    return getattr(errors, name)
  if home == "estimators":
    from lrf_jax.registration import estimators
    return getattr(estimators, name)
  if home == "icp_host":
    from lrf_jax.registration import icp_host
    return getattr(icp_host, name)
  if home == "options":
    from lrf_jax.registration import options
    return getattr(options, name)
  if home == "pipeline":
    from lrf_jax.registration import pipeline
    return getattr(pipeline, name)
  raise AttributeError(f"module 'lrf_jax.registration' has no attribute {name!r}")
