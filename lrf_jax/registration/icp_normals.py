"""The target normals of point-to-plane ICP (`icp_host`): unsigned PCA normals over the pairing
distance, capped at a few mean spacings of the target (`estimate_target_normals`), computed
where the pairs need them (`TargetNormals`), and the checks of normals a caller gives."""

from __future__ import annotations

import numpy as np

from lrf_jax.geometry.normals import pca_normals
from lrf_jax.search import engine

__all__ = ["NORMAL_RADIUS_RATIO", "NORMAL_RADIUS_SPACING", "TargetNormals", "check_normals",
           "estimate_target_normals", "normal_radius", "unit_normals"]

# Estimated target normals: a PCA radius of this many `max_distance`, at most this many mean
# nearest-neighbor spacings of the target (`estimate_target_normals`).
NORMAL_RADIUS_RATIO = 1.0
NORMAL_RADIUS_SPACING = 4.0


def check_normals(normals: object, m: int) -> np.ndarray:
  """`normals` as an (m, 3) float64 array.

  Raises:
    ValueError: naming `target_normals`, when it is not numeric of shape (m, 3).
  """
  try:
    nrm = np.asarray(normals, np.float64)
  except (TypeError, ValueError):
    raise ValueError("target_normals: expected an (m, 3) array of numbers, got "
                     f"{type(normals).__name__}") from None
  if nrm.shape != (m, 3):
    raise ValueError(f"target_normals: expected shape ({m}, 3), one normal per target point, "
                     f"got {nrm.shape}")
  return nrm


def unit_normals(normals: np.ndarray) -> np.ndarray:
  """(m, 3) float64 copies of `normals` scaled to unit length; NaN rows where a normal is zero or
  non-finite (such pairs are skipped)."""
  nrm = np.array(normals, np.float64).reshape(-1, 3)
  length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
  ok = np.isfinite(length) & (length > 0)
  nrm[ok] /= length[ok, None]
  nrm[~ok] = np.nan
  return nrm


def normal_radius(target: np.ndarray, max_distance: float, grid: engine.Grid, *,
                  spacings: float = NORMAL_RADIUS_SPACING, spacing: float | None = None) -> float:
  """The PCA radius of `estimate_target_normals`: min(`NORMAL_RADIUS_RATIO` x `max_distance`,
  `spacings` x the target's mean nearest-neighbor spacing) (cloud units).

  Args:
    target: (m, 3) float64 cloud, m >= 2.
    max_distance: the ICP pairing distance (cloud units, finite).
    grid: an `engine.Grid` of `target` (any cell size).
    spacings: the cap, in mean spacings.
    spacing: the target's mean nearest-neighbor spacing where the caller measured it already
      (`resolution.working_resolution`'s `mean_spacing`: the same figure); None measures it.
  """
  if spacing is None:  # the point itself, then its nearest
    spacing = float(engine.knn(grid, target, 2)[0][:, 1].mean())
  radius = NORMAL_RADIUS_RATIO * float(max_distance)
  return min(radius, float(spacings) * spacing) if spacing > 0 else radius


def estimate_target_normals(target: np.ndarray, max_distance: float,
                            grid: engine.Grid | None = None, *,
                            spacings: float = NORMAL_RADIUS_SPACING) -> np.ndarray:
  """Unsigned PCA normals of the target for point-to-plane ICP.

  The radius is `normal_radius`'s: min(`NORMAL_RADIUS_RATIO` x `max_distance`, `spacings` x the
  target's mean nearest-neighbor spacing): the pairing distance, capped so that a generous
  `max_distance` does not smooth the normals of a curved surface away.

  Args:
    target: (m, 3) float64 cloud.
    max_distance: the ICP pairing distance (cloud units, finite).
    grid: optional `engine.Grid` of `target` to reuse (any cell size).
    spacings: the cap, in mean spacings (default `NORMAL_RADIUS_SPACING`).

  Returns:
    (m, 3) float64 unit normals, NaN where fewer than 3 neighbors or a degenerate spectrum.
  """
  pts = np.ascontiguousarray(target, np.float64)
  if len(pts) < 3:
    return np.full((len(pts), 3), np.nan)
  grid = grid if grid is not None else engine.knn_grid(pts)
  return pca_normals(pts, normal_radius(pts, max_distance, grid, spacings=spacings), grid=grid)


class TargetNormals:
  """`estimate_target_normals` computed where ICP pairs: the unit normal of a target point (the
  same radius, grid and PCA, so the same figure) is computed the first time `require` names it.
  ICP pairs a target point only as the nearest of a moved source point: a few thousand source
  points against a dense target read the normals of a small part of it.

  Args:
    target: (m, 3) cloud.
    max_distance: the ICP pairing distance (cloud units, finite).
    grid: optional `engine.Grid` of `target` to reuse (any cell size).
    spacings: the radius cap in mean spacings (`normal_radius`).
    spacing: the target's mean nearest-neighbor spacing, where known (`normal_radius`).

  Attributes:
    points: (m, 3) float64, the target.
    grid: the `engine.Grid` the normals' neighbors are searched in.
    radius: the PCA radius (`normal_radius`, cloud units; 0 for fewer than 3 points).
    pca: (m, 3) float64 normals of the points computed so far, as `estimate_target_normals`
      gives them; NaN rows elsewhere and where a normal is undefined.
    unit: (m, 3) float64 `unit_normals` of `pca` (what the ICP kernels read).
    done: (m,) bool, the points whose normals were computed. `require` fills `pca`, `unit` and
      `done` in place.
  """

  def __init__(self, target: np.ndarray, max_distance: float, grid: engine.Grid | None = None,
               *, spacings: float = NORMAL_RADIUS_SPACING, spacing: float | None = None):
    self.points = np.ascontiguousarray(target, np.float64)
    self.grid = grid if grid is not None else engine.knn_grid(self.points)
    self.radius = (normal_radius(self.points, max_distance, self.grid, spacings=spacings,
                                 spacing=spacing) if len(self.points) >= 3 else 0.0)
    self.pca = np.full((len(self.points), 3), np.nan)
    self.unit = np.full((len(self.points), 3), np.nan)
    self.done = np.zeros(len(self.points), bool)

  def require(self, indices: np.ndarray) -> bool:
    """Computes the normals of the target rows `indices` (negative entries ignored) not
    computed yet; True when there were any."""
    idx = np.asarray(indices, np.int64)
    idx = idx[idx >= 0]
    new = np.unique(idx[~self.done[idx]])
    if len(new) == 0:
      return False
    self.done[new] = True
    if len(self.points) >= 3:
      self.pca[new] = pca_normals(self.points, self.radius, grid=self.grid, at=new)
      self.unit[new] = unit_normals(self.pca[new])
    return True
