"""Pose errors (paper eqs. `eq_err_r`, `eq_err_t`) and 4x4 transforms.

err_r = arccos(clip((trace(R_gtᵀ R) - 1) / 2)) in degrees, err_t = |t_gt - t| / mr.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def rotation_error_deg(r_est: np.ndarray, r_gt: np.ndarray) -> float:
  """err_r = arccos(clip((trace(R_gtᵀ R_est) - 1) / 2, -1, 1)) in degrees (paper eq. `eq_err_r`).

  Args:
    r_est: (3, 3) estimated rotation.
    r_gt: (3, 3) ground-truth rotation.

  Returns:
    The angle of R_gtᵀ R_est in degrees, in [0, 180].
  """
  r_est = np.asarray(r_est, np.float64)
  r_gt = np.asarray(r_gt, np.float64)
  c = (np.trace(r_gt.T @ r_est) - 1.0) / 2.0
  return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_errors(transform_est: np.ndarray, transform_gt: np.ndarray,
                mr: float) -> tuple[float, float]:
  """(err_r in degrees, err_t in mr) between two (4, 4) rigid transforms (paper eqs. `eq_err_r`,
  `eq_err_t`).

  Args:
    transform_est: (4, 4) estimate.
    transform_gt: (4, 4) ground truth.
    mr: mesh resolution (the unit of err_t).

  Returns:
    (err_r, err_t).
  """
  te = _check_transform(transform_est, "transform_est")
  tg = _check_transform(transform_gt, "transform_gt")
  if not mr > 0:
    raise ValueError(f"mr: expected a positive mesh resolution, got {mr!r}")
  return (rotation_error_deg(te[:3, :3], tg[:3, :3]),
          float(np.linalg.norm(tg[:3, 3] - te[:3, 3]) / mr))


def to_transform(rotation: Any, translation: Any) -> np.ndarray:
  """(4, 4) float64 [R t; 0 0 0 1] from a (3, 3) rotation and a (3,) translation."""
  out = np.eye(4)
  out[:3, :3] = np.asarray(rotation, np.float64)
  out[:3, 3] = np.asarray(translation, np.float64)
  return out


def _check_transform(t: Any, name: str) -> np.ndarray:
  a = np.asarray(t, np.float64)
  if a.shape != (4, 4) or not np.all(np.isfinite(a)):
    raise ValueError(f"{name}: expected a finite (4, 4) rigid transform, got shape {a.shape}")
  return a
