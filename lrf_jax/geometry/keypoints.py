"""Intrinsic Shape Signatures (ISS) keypoints, as Open3D's `compute_iss_keypoints` defines them.

For every point p of the cloud:

1. the scatter matrix of its neighbors within the salient radius r_s (p itself included; a
   neighbor is within r when its float64 squared distance is <= r * r, cKDTree's rule): the
   plain covariance about the neighbors' centroid, divided by their count (Open3D's choice;
   PCL's `ISSKeypoint3D` takes the scatter about p itself and Zhong's paper weights each
   neighbor by the inverse of its own neighbor count);
2. its eigenvalues l1 >= l2 >= l3;
3. p is a *candidate* when it has at least `min_neighbors` neighbors within r_s,
   l2 / l1 < gamma_21, l3 / l2 < gamma_32 and l3 > 0; its saliency is l3 (0 for every other
   point). An l3 below 1e-12 l1 (the float64 rounding of a planar ball) counts as 0, so that a
   flat patch yields no keypoint whatever its pose;
4. a candidate is a *keypoint* when it has at least `min_neighbors` neighbors within the
   non-maximum radius r_n and no point within r_n has a larger saliency. Saliencies within a
   relative 1e-9 of each other count as equal and equal ones keep both, as Open3D keeps exact
   ties: two points with the same neighbor set have the same l3 but for the rounding of their
   sums, and both stay whatever the cloud's pose or point order.

The radii default to Open3D's: r_s = 6 mr and r_n = 4 mr, mr the cloud's mean nearest-neighbor
distance (`lrf_jax.geometry.resolution.mesh_resolution` without faces, Open3D's `ComputeModelResolution`).

Both ball searches run in the compiled engine (`engine.ball_stats` for the scatter matrices,
`engine.ball_lists` around the candidates for the suppression); `iss_saliency` is the per-point
rule of steps 2-3 in plain numpy.

References:
  Zhong, "Intrinsic shape signatures: A shape descriptor for 3D object recognition", ICCV
  Workshops 2009.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lrf_jax.search import engine
from lrf_jax.geometry.cloud import as_cloud
from lrf_jax.geometry.resolution import mesh_resolution

SALIENT_RADIUS_MR = 6.0
NON_MAX_RADIUS_MR = 4.0
# An l3 at or below this fraction of l1 is the rounding of a planar (or lower-dimensional) ball.
FLAT_TOLERANCE = 1e-12
# Saliencies this close (relative) are equal: the suppression does not depend on rounding.
TIE_RTOL = 1e-9


def iss_saliency(cov: np.ndarray, count: np.ndarray, *, gamma_21: float = 0.975,
                 gamma_32: float = 0.975, min_neighbors: int = 5) -> np.ndarray:
  """ISS saliency of each point from its ball's scatter matrix.

  Args:
    cov: (n, 3, 3) float64 covariance of each point's neighbors about their centroid.
    count: (n,) number of neighbors in each ball (the point included).
    gamma_21: upper bound (exclusive) on l2 / l1.
    gamma_32: upper bound (exclusive) on l3 / l2.
    min_neighbors: least neighbor count of a candidate.

  Returns:
    (n,) float64: l3 (the smallest eigenvalue, squared cloud units) where the point is a
    candidate, else 0.
  """
  cov = np.asarray(cov, np.float64)
  if len(cov) == 0:
    return np.zeros(0)
  lam = np.linalg.eigvalsh(cov)  # ascending: l3, l2, l1
  l3, l2, l1 = lam[:, 0], lam[:, 1], lam[:, 2]
  with np.errstate(divide="ignore", invalid="ignore"):
    candidate = ((np.asarray(count) >= min_neighbors) & (l1 > 0) & (l3 > FLAT_TOLERANCE * l1)
                 & (l2 / l1 < gamma_21) & (l3 / l2 < gamma_32))
  return np.where(candidate, l3, 0.0)


def _positive(value: Any, name: str, *, upper: float | None = None) -> float:
  try:
    v = float(value)
  except (TypeError, ValueError):
    raise ValueError(f"{name}: expected a positive number, got {value!r}") from None
  if not np.isfinite(v) or v <= 0 or (upper is not None and v > upper):
    expected = f"a number in (0, {upper:g}]" if upper is not None else "a finite number > 0"
    raise ValueError(f"{name}: expected {expected}, got {value!r}")
  return v


def _count(value: Any, name: str, least: int) -> int:
  if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
      or value < least:
    raise ValueError(f"{name}: expected an integer >= {least}, got {value!r}")
  return int(value)


def _radii(pts: np.ndarray, salient_radius, non_max_radius, mr) -> tuple[float, float]:
  """The two radii in cloud units, defaulting to multiples of mr (computed when needed)."""
  rs = None if salient_radius is None else _positive(salient_radius, "salient_radius")
  rn = None if non_max_radius is None else _positive(non_max_radius, "non_max_radius")
  if rs is None or rn is None:
    if mr is None:
      mr = mesh_resolution(pts)[0]
      if not mr > 0:
        raise ValueError("mr: the cloud's mean nearest-neighbor distance is 0 (every point has "
                         "a duplicate); pass mr or both radii")
    unit = _positive(mr, "mr")
    rs = SALIENT_RADIUS_MR * unit if rs is None else rs
    rn = NON_MAX_RADIUS_MR * unit if rn is None else rn
  return rs, rn


def iss_keypoints(points: Any, *, salient_radius: float | None = None,
                  non_max_radius: float | None = None, gamma_21: float = 0.975,
                  gamma_32: float = 0.975, min_neighbors: int = 5, mr: float | None = None,
                  max_keypoints: int | None = None) -> np.ndarray:
  """ISS keypoints of a cloud (the module docstring gives the definition).

  Args:
    points: (n, 3) cloud, or anything `lrf_jax.geometry.cloud.CheckedCloud` reads (a `Cloud`, a path, an
      Open3D `PointCloud`); faces are ignored.
    salient_radius: radius of the scatter-matrix balls, cloud units (default 6 mr).
    non_max_radius: radius of the non-maximum suppression, cloud units (default 4 mr).
    gamma_21: upper bound (exclusive) on l2 / l1, in (0, 1].
    gamma_32: upper bound (exclusive) on l3 / l2, in (0, 1].
    min_neighbors: least number of points (itself included) within each radius.
    mr: the unit of the default radii, cloud units (default: the mean nearest-neighbor
      distance); unused when both radii are given.
    max_keypoints: keep at most this many, those of largest l3 (equal l3: lower index first).

  Returns:
    (k,) int64 point indices of the keypoints, increasing.

  Raises:
    ValueError: a cloud that is not (n, 3) finite floats, a radius or mr that is not a finite
      number > 0, a gamma outside (0, 1], a `min_neighbors` below 1 or a negative
      `max_keypoints`.
  """
  pts = as_cloud(points, "points").points
  g21 = _positive(gamma_21, "gamma_21", upper=1.0)
  g32 = _positive(gamma_32, "gamma_32", upper=1.0)
  kmin = _count(min_neighbors, "min_neighbors", 1)
  cap = None if max_keypoints is None else _count(max_keypoints, "max_keypoints", 0)
  if len(pts) < 3:  # a ball of fewer than 3 points is flat
    return np.zeros(0, np.int64)
  rs, rn = _radii(pts, salient_radius, non_max_radius, mr)
  grid = engine.Grid(pts, min(rs, rn) / 2)
  count, _, cov = engine.ball_stats(grid, pts, rs)
  saliency = iss_saliency(cov, count, gamma_21=g21, gamma_32=g32, min_neighbors=kmin)
  cand = np.flatnonzero(saliency > 0)
  if len(cand):
    ptr, ball = engine.ball_lists(grid, pts[cand], rn)
    # Every ball holds its own centre, so no segment is empty.
    top = np.maximum.reduceat(saliency[ball], ptr[:-1])
    keep = (np.diff(ptr) >= kmin) & (saliency[cand] >= top * (1.0 - TIE_RTOL))
    cand = cand[keep]
  if cap is not None and len(cand) > cap:
    order = np.lexsort((cand, -saliency[cand]))
    cand = np.sort(cand[order[:cap]])
  return cand.astype(np.int64)
