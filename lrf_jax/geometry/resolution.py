"""Mesh resolution (mr), the length unit of support radii and noise levels.

For a mesh, mr is the mean length of its unique edges (the Bologna convention: BR's noise sigma
is 0.1/0.3/0.5 of it). For a cloud, mr is the mean distance from each point to its nearest other
point. On the BR meshes the nearest-neighbor spacing is about 1/1.42-1/1.59 of the edge length,
so the two definitions are *not* interchangeable; every dataset records which one it used.

`working_resolution` is the unit `compute_frames` measures radii in: `mesh_resolution`'s, except
on an uneven cloud (a raw LiDAR sweep), where the area-weighted median spacing stands for the
cloud as a whole. `registration_resolution`, the unit of `register` and `register_all`, is the
same but never finer than a fixed fraction of the cloud's extent (a full-density fragment);
`pair_resolution` picks one for a pair of clouds.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
from lrf_jax.search import engine

MrDefinition = Literal["mean_edge_length", "mean_nn_distance"]


def unique_edges(faces: np.ndarray) -> np.ndarray:
  """The undirected edges of a triangle mesh, each once.

  Args:
    faces: (f, 3) integer vertex indices.

  Returns:
    (e, 2) int64 edges with e[:, 0] < e[:, 1], sorted.
  """
  f = np.asarray(faces, dtype=np.int64)
  e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
  e.sort(axis=1)
  e = e[e[:, 0] != e[:, 1]]  # degenerate faces contribute no zero-length edge
  n = int(f.max()) + 1 if f.size else 1
  keys = np.unique(e[:, 0] * n + e[:, 1])
  return np.stack([keys // n, keys % n], axis=1)


def mesh_resolution(points: np.ndarray, faces: np.ndarray | None = None, *,
                    name: str = "points") -> tuple[float, MrDefinition]:
  """Mesh resolution of a mesh (mean unique-edge length) or a cloud (mean NN distance).

  Args:
    points: (n, 3) coordinates, n >= 2.
    faces: (f, 3) triangles, or None for a cloud.

  Returns:
    (mr, definition): mr in the points' units, and "mean_edge_length" (mesh) or
    "mean_nn_distance" (cloud).

  Raises:
    ValueError: fewer than 2 points, an empty face array, or a cloud without spacing (mr 0:
      all points coincide, or every point has a duplicate); the message starts with `name`.
  """
  pts = np.asarray(points, dtype=np.float64)
  if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
    raise ValueError(f"points: expected an (n, 3) array with n >= 2, found shape {pts.shape}")
  if faces is not None:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
      raise ValueError(f"faces: expected a non-empty (f, 3) array, found shape {faces.shape}")
    e = unique_edges(faces)
    mr = float(np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1).mean())
    if mr == 0.0:
      raise ValueError(f"{name}: the mesh has no spacing (mean edge length 0): its edges join "
                       "coinciding vertices")
    return mr, "mean_edge_length"
  d, _ = engine.knn(engine.knn_grid(pts, 2), pts, 2)  # the point itself, then its nearest
  mr = float(d[:, 1].mean())
  if mr == 0.0:
    distinct = len(np.unique(pts, axis=0))
    what = (f"all {len(pts)} points coincide" if distinct == 1 else
            f"every point is duplicated ({distinct} distinct positions among {len(pts)} points)")
    raise ValueError(f"{name}: the cloud has no spacing (mean nearest-neighbor distance 0): "
                     f"{what}")
  return mr, "mean_nn_distance"


# A cloud whose area-weighted median spacing exceeds its mean spacing by this factor is uneven
# (a raw LiDAR sweep: dense near the sensor, sparse far away). Measured on the dev data: 0.96-1.42
# on clean scans, fragments and meshes' vertices (Stanford bunny scans, UWA3M views, UWAOR and BR
# scenes, 3DMatch fragments); 6.7-7.2 on raw KITTI sweeps.
UNEVEN_RATIO = 3.0
# A pair's working resolution is the coarser cloud's where one cloud's is this many times the
# other's (or one cloud is uneven); otherwise the source's, as before.
PAIR_RATIO = 2.0
# Clouds whose working resolutions differ by more than this are not in the same units.
UNITS_RATIO = 100.0
# register's finest resolution relative to a cloud's extent (`cloud_extent`): a cloud sampled
# more finely than extent / MAX_EXTENT_MR is registered coarser (`capped_extent_ratio`, below)
# and thinned to it.
# extent / mean spacing, measured: 3DMatch fragments at 2.5 cm 162-183, Stanford bunny scans
# 183-212, UWA3M views 176-286 (chef 271-286), raw KITTI sweeps 77-100 at their area-weighted
# spacing; full-density TSDF fragments (6 mm voxels) 465-612, a UWAOR full scene 646.
MAX_EXTENT_MR = 300.0
# A cloud capped by MAX_EXTENT_MR is oversampled (a fusion's output, a mesh's vertices sampled
# for rendering): its extra points add time, not evidence. One `ratio` times finer than the cap
# is registered at extent / `capped_extent_ratio(ratio)`: MAX_EXTENT_MR**2 / ratio, so a cloud k
# times finer than the cap works k times coarser than it, down to extent / CAPPED_MIN_RATIO.
# Continuous at the cap (a cloud just over it keeps about its own spacing); the floor, half the
# cap, lies below the 3DMatch fragments' 162-183 and above the fused fragments at 2.5 cm (103).
CAPPED_MIN_RATIO = 150.0
# registration_resolution measures a cloud's spacing on SPACING_SAMPLE seeded query points
# first; where that sample's working resolution (clearly even or uneven: area spacing under, or
# over, UNEVEN_RATIO mean spacings by this margin) is under SAMPLED_CAP_MARGIN times the cap's
# spacing, the cloud is capped on the sample's word (the sample mean's standard error is well
# under 1 % of it; a few far points the sample misses, which could have made the whole cloud's
# area-weighted spacing uneven, are not looked for), and its spacings are the sample's. Every
# other cloud is measured on all its points.
SPACING_SAMPLE = 8192
SAMPLED_CAP_MARGIN = 0.8
# A capped cloud is thinned to its working resolution where its mean spacing is under this
# fraction of it; closer to it, thinning would remove few points and its voxel (scaled so that
# the centroids come out mr apart) would overshoot, leaving a denser cloud sparser than mr.
CAPPED_THIN_RATIO = 0.8


@dataclasses.dataclass(frozen=True)
class Resolution:
  """A cloud's (or mesh's) resolution, measured.

  Attributes:
    mr: the working resolution (cloud units): `mean_spacing`, for an uneven cloud
      `area_spacing`, for a cloud `registration_resolution` capped its extent /
      `capped_extent_ratio` of its extent / own working resolution.
    mean_spacing: `mesh_resolution`'s value: the mean edge length of a mesh, the mean
      nearest-neighbor distance of a cloud (of a capped one, possibly `sampled_spacings`').
    area_spacing: the area-weighted median nearest-neighbor distance (each point weighted by
      the area it stands for, its spacing squared): the spacing at which half the surface is
      sampled; `mean_spacing` for a mesh.
    definition: "mean_edge_length", "mean_nn_distance", "area_median_nn_distance" (uneven) or
      "extent_fraction" (capped).
  """
  mr: float
  mean_spacing: float
  area_spacing: float
  definition: str

  @property
  def uneven(self) -> bool:
    """Whether the working resolution is the area-weighted one (a range-dependent density)."""
    return self.definition == "area_median_nn_distance"

  @property
  def capped(self) -> bool:
    """Whether the working resolution is `registration_resolution`'s fraction of the extent
    (a cloud sampled more finely than register works)."""
    return self.definition == "extent_fraction"


def area_median(spacings: np.ndarray) -> float:
  """The area-weighted median of nearest-neighbor distances (weights d**2; zeros left out)."""
  d = np.sort(spacings[spacings > 0])
  if len(d) == 0:
    return 0.0
  c = np.cumsum(d * d)
  return float(d[np.searchsorted(c, 0.5 * c[-1])])


def working_resolution(points: np.ndarray, faces: np.ndarray | None = None, *,
                       name: str = "points") -> Resolution:
  """The resolution lengths are measured in: `mesh_resolution`'s, unless the cloud is uneven.

  A cloud's mean nearest-neighbor distance is dominated by its densest part: on a raw LiDAR sweep
  (3 cm near the sensor, 1-2 m far away) it gives a few cm, and every length derived from it
  (support radius, inlier and ICP distances) comes out too small for most of the scene. Weighting
  each point by the area it stands for (its spacing squared) gives the spacing at which half the
  surface is sampled (`area_median`); where that exceeds the mean spacing `UNEVEN_RATIO` times,
  it is the working resolution. Clean scans and fragments (ratios 0.96-1.42) keep the mean
  spacing exactly; meshes keep their mean edge length. No length or count is built in: scaling
  the cloud by k scales every figure by k.

  Args:
    points: (n, 3) coordinates, n >= 2.
    faces: (f, 3) triangles, or None for a cloud.
    name: how errors name the cloud.

  Returns:
    A `Resolution`.

  Raises:
    ValueError: as `mesh_resolution`.
  """
  if faces is not None:
    mr, definition = mesh_resolution(points, faces, name=name)
    return Resolution(mr, mr, mr, definition)
  pts = np.asarray(points, dtype=np.float64)
  if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
    mesh_resolution(pts)  # its ValueError
  return _cloud_resolution(pts, engine.knn_grid(pts, 2), name)


def _cloud_resolution(pts: np.ndarray, grid: engine.Grid, name: str) -> Resolution:
  """`working_resolution` of a checked cloud, given a `engine.knn_grid` of it."""
  d, _ = engine.knn(grid, pts, 2)  # as mesh_resolution: the same mean
  mean = float(d[:, 1].mean())
  if mean == 0.0:
    mesh_resolution(pts, name=name)  # its ValueError: the cloud has no spacing
  area = area_median(d[:, 1])
  if mean > 0 and area > UNEVEN_RATIO * mean:
    return Resolution(area, mean, area, "area_median_nn_distance")
  return Resolution(mean, mean, area, "mean_nn_distance")


def cloud_extent(points: np.ndarray) -> float:
  """Twice the root-mean-square distance of the points from their centroid (cloud units): a
  size that moves with the cloud and scales with it (stray points raise it: 1 % of the points
  at ten times the RMS distance, about 1.4-fold).

  Args:
    points: (n, 3) coordinates, n >= 1.

  Returns:
    The extent, >= 0.
  """
  pts = np.asarray(points, np.float64)
  if len(pts) == 0:
    return float("nan")
  square = 0.0
  for j in range(pts.shape[1]):  # per column: numpy's axis-0 reductions of an (n, 3) array are slow
    d = pts[:, j] - pts[:, j].mean()
    square += float(np.dot(d, d))
  return 2.0 * float(np.sqrt(square / len(pts)))


def registration_resolution(points: np.ndarray, faces: np.ndarray | None = None, *,
                            name: str = "points") -> Resolution:
  """`working_resolution`, but for a cloud (a mesh keeps its mean edge length) never finer than
  `cloud_extent` / `MAX_EXTENT_MR`: a cloud sampled `ratio` = extent / its working resolution
  more finely than that (a full-density fragment: 6 mm TSDF voxels across a room) is registered
  at extent / `capped_extent_ratio(ratio)`, its support radius (15 mr) covering 5-10 % of its
  extent, as on the clean scans and fragments the defaults were measured on; every cloud
  sampled no more finely keeps `working_resolution`'s figure.

  A cloud whose working resolution on `SPACING_SAMPLE` seeded query points
  (`sampled_spacings`: each one's nearest other point among all of them; clearly even or
  clearly uneven) is under `SAMPLED_CAP_MARGIN` times the cap's is capped on the sample's word,
  without measuring the rest: its `mean_spacing` and `area_spacing` are the sample's.

  Returns:
    A `Resolution`; `capped` (definition "extent_fraction") where the extent set it.

  Raises:
    ValueError: as `working_resolution`.
  """
  if faces is not None:
    return working_resolution(points, faces, name=name)
  pts = np.asarray(points, dtype=np.float64)
  if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
    mesh_resolution(pts)  # its ValueError
  extent = cloud_extent(pts)
  floor = extent / MAX_EXTENT_MR
  grid = engine.knn_grid(pts, 8)  # cheaper to build than knn_grid(pts, 2); the same distances
  if len(pts) > SPACING_SAMPLE:
    d = sampled_spacings(pts, grid)
    mean, area = float(d.mean()), area_median(d)
    # the sample's working resolution, where it is clearly even or clearly uneven
    work = (mean if area < SAMPLED_CAP_MARGIN * UNEVEN_RATIO * mean else
            area if SAMPLED_CAP_MARGIN * area > UNEVEN_RATIO * mean else 0.0)
    if 0 < work < SAMPLED_CAP_MARGIN * floor:
      return _capped(extent, work, mean, area)
  res = _cloud_resolution(pts, grid, name)
  return _capped(extent, res.mr, res.mean_spacing, res.area_spacing) if res.mr < floor else res


def _capped(extent: float, work: float, mean: float, area: float) -> Resolution:
  """The capped `Resolution` of a cloud of `extent` whose own working resolution is `work`."""
  return Resolution(extent / capped_extent_ratio(extent / work), mean, area, "extent_fraction")


def sampled_spacings(points: np.ndarray, grid: engine.Grid | None = None) -> np.ndarray:
  """The nearest-neighbor distances (cloud units) of `SPACING_SAMPLE` points drawn with seed 0
  (all of them in a cloud no larger), each to its nearest other point of the whole cloud.

  Args:
    points: (n, 3) float64 cloud, n >= 2.
    grid: an `engine.knn_grid` of it where built already.

  Returns:
    (min(n, SPACING_SAMPLE),) float64 distances.
  """
  grid = grid if grid is not None else engine.knn_grid(points, 2)
  rows = (np.sort(np.random.default_rng(0).choice(len(points), SPACING_SAMPLE, replace=False))
          if len(points) > SPACING_SAMPLE else slice(None))
  return engine.knn(grid, points[rows], 2)[0][:, 1]


def capped_extent_ratio(ratio: float) -> float:
  """The extent / working resolution `registration_resolution` registers a cloud at whose
  extent / own working resolution is `ratio` > `MAX_EXTENT_MR`: MAX_EXTENT_MR**2 / ratio, at
  least `CAPPED_MIN_RATIO` (non-monotone in the spacing: an oversampled cloud's extra points add
  time, not evidence; continuous at the cap).

  Args:
    ratio: the cloud's extent over its working resolution (> 0).

  Returns:
    The ratio its working resolution is taken at, in [CAPPED_MIN_RATIO, MAX_EXTENT_MR].
  """
  return float(min(MAX_EXTENT_MR, max(MAX_EXTENT_MR * MAX_EXTENT_MR / ratio, CAPPED_MIN_RATIO)))


def pair_resolution(source: Resolution, target: Resolution, names=("source", "target")) -> float:
  """One working resolution for a pair: the source's, as for a single cloud, unless one cloud
  is uneven or capped (`registration_resolution`) or the two differ by more than `PAIR_RATIO`:
  then the coarser one (a raw fragment against a voxelized one is measured at the voxelized
  one's resolution; the denser cloud is then thinned to it, `thinning_voxel`).

  Raises:
    ValueError: the two differ by more than `UNITS_RATIO` (e.g. millimetres against metres),
      naming both figures and the fix.
  """
  lo, hi = sorted((source.mr, target.mr))
  if lo > 0 and hi > UNITS_RATIO * lo:
    raise ValueError(
        f"{names[0]} and {names[1]}: point spacings of {source.mr:.4g} and {target.mr:.4g} "
        f"(cloud units) differ {hi / lo:.0f}-fold, more than any two sensors do: are they in "
        "the same units? Scale one of them (e.g. millimetres to metres: multiply by 0.001) "
        "before registering")
  if source.uneven or target.uneven or source.capped or target.capped or hi > PAIR_RATIO * lo:
    return hi
  return source.mr


def thinning_voxel(res: Resolution, mr: float) -> float | None:
  """The voxel edge that thins a cloud to the working resolution `mr` where it is far denser
  (its mean spacing under mr / `PAIR_RATIO`, or for a cloud `registration_resolution` capped
  under `CAPPED_THIN_RATIO` mr): `mr`; None where it is not (nothing to do; also a capped
  cloud measured at a given mr no coarser than its spacing)."""
  limit = CAPPED_THIN_RATIO if res.capped else 1.0 / PAIR_RATIO
  return mr if res.mean_spacing < limit * mr else None

