"""Stage "icp" of `register`: point-to-plane ICP from the coarse pose (or `register`'s `init`),
in two passes (the second at an adaptive gate on the overlap's points), then a pass on the input
points of a pair thinned by default.

References:
  Besl & McKay, "A method for registration of 3-D shapes", TPAMI 1992 (ICP).
  Chen & Medioni, "Object modelling by registration of multiple range images", IVC 1992
  (point-to-plane ICP).
  Zhang, "Iterative point matching for registration of free-form curves and surfaces", IJCV
  1994 (an adaptive pairing distance).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from lrf_jax.registration import icp_host, icp_normals
from lrf_jax.io.validation import check_rigid
from lrf_jax.registration.icp_host import icp
from lrf_jax.registration.options import IcpOptions
from lrf_jax.registration.rivals import overlap_constraints
from lrf_jax.registration.stages import Prepared, StageTimer, Verified
from lrf_jax.search import engine
from lrf_jax.search.grid import serial_blas

# Source points ICP pairs per iteration (a seeded subset of larger clouds; in the second pass,
# of the part within the overlap distance, `overlap_points`); fitness and rmse are measured on
# the first subset.
ICP_POINTS = 5000


# The second ICP pass (`fine_distance`): its gate in median residuals and its floor in mr.
ICP_FINE_FACTOR = 1.5
ICP_FINE_MIN_MR = 1.0

# The last pass on the input points of a cloud thinned by default (`raw_pass`; not of an
# oversampled one, `stages.prepare`): source points
# drawn, the target normals' radius (at most RAW_NORMAL_MR mr and RAW_NORMAL_SPACINGS mean input
# spacings, `icp_normals.estimate_target_normals`), the gates (mr), and how far it may move a source
# point (mr) before its pose is refused (the verdict was reached on the thinned clouds' pose).
# A raw sweep's mean spacing is its near field's: at 4 spacings its far points get no normal and
# the yaw rests on the ground near the sensor (twice the rotation error on the dev sweeps).
RAW_ICP_POINTS = 20_000
RAW_NORMAL_MR = 2.0
RAW_NORMAL_SPACINGS = 8.0
RAW_GATES_MR = (1.0, 0.3)
RAW_MAX_SHIFT_MR = 1.0


# An init whose rotation block is within this of orthonormal (|RᵀR - I|, max entry) is projected
# to the nearest rotation: published ground truths are printed with a few digits (3DMatch's
# gt.log reaches 5e-4).
INIT_PROJECT = 1e-2


def check_init(t: Any, name: str = "init") -> np.ndarray:
  """`t` as a (4, 4) rigid transform (`lrf_jax.io.validation.check_rigid`): a rotation block
  within `INIT_PROJECT` of orthonormal is projected to the nearest rotation, with a
  `ProjectedRotation` warning giving the figure.

  Raises:
    ValueError: not a (4, 4) finite rigid transform; the message gives the figure.
  """
  try:
    a = np.asarray(t, np.float64)
  except (TypeError, ValueError):
    raise ValueError(f"{name}: expected a (4, 4) rigid transform, got {type(t).__name__}") from None
  return check_rigid(a, name, "matrix", project=INIT_PROJECT)


def icp_passes(source: np.ndarray, target: np.ndarray, init: np.ndarray, distance: float,
            fine: bool, mr: float, iterations: int, grid: engine.Grid | None,
            mode: str, pool: np.ndarray | None = None,
            rng: np.random.Generator | None = None, target_spacing: float | None = None
            ) -> tuple[np.ndarray, float, float]:
  """ICP at `distance`; then, with `fine`, again at the gate `fine_distance` of the first pass's
  residuals with the same target normals. Fitness and rmse are those at `distance` of the
  returned pose (what the verdict and `Registration.overlap` read), over `source`.

  With `pool` (the whole source cloud, of which `source` is a seeded subset) the second pass
  pairs up to `ICP_POINTS` points drawn by `rng` among the pool's points that lie within
  `distance` of the target at the first pass's pose (`overlap_points`): on a partial overlap
  all of them can pair, instead of the overlap's share of a uniform subset. `target_spacing`:
  the target's mean nearest-neighbor spacing where measured already (the target normals'
  radius cap, `icp_normals.normal_radius`)."""
  if not fine or iterations == 0:
    normals = None
    if mode == "point_to_plane":  # the grid point_to_plane_icp would build, built once
      grid = grid if grid is not None else engine.knn_grid(np.asarray(target, np.float64))
      normals = icp_normals.TargetNormals(target, distance, grid, spacing=target_spacing)
    return icp(source, target, init, max_distance=distance, iterations=iterations,
               target_grid=grid, target_normals=normals, mode=mode)
  target = np.asarray(target, np.float64)
  grid = grid if grid is not None else engine.Grid(target, distance)
  normals = (icp_normals.TargetNormals(target, distance, grid, spacing=target_spacing)
             if mode == "point_to_plane" else None)
  kw: dict[str, Any] = dict(target_grid=grid, target_normals=normals, mode=mode)
  coarse, _, _ = icp(source, target, init, max_distance=distance, iterations=iterations, **kw)
  gate = fine_distance(source, grid, coarse, distance, mr)
  fine_src = source
  if pool is not None and rng is not None:
    fine_src = overlap_points(pool, grid, coarse, distance, ICP_POINTS, rng, fallback=source)
  tr, _, _ = icp(fine_src, target, coarse, max_distance=gate, iterations=iterations, **kw)
  _, fitness, rmse = icp(source, target, tr, max_distance=distance, iterations=0, **kw)
  return tr, fitness, rmse


def overlap_points(points: np.ndarray, grid: engine.Grid, transform: np.ndarray,
                   distance: float, count: int, rng: np.random.Generator,
                   fallback: np.ndarray) -> np.ndarray:
  """Up to `count` of `points` (sorted by index, drawn by `rng`) whose image under `transform`
  has a grid point within `distance`: the source's part of the overlap, for `register`'s second
  ICP pass. `fallback` where fewer than `icp_host.MIN_PAIRS` points lie there.

  Args:
    points: (n, 3) source points (float64).
    grid: an `engine.Grid` of the target.
    transform: (4, 4) source -> target.
    distance: the overlap distance (cloud units).
    count: at most this many points.
    rng: the generator that draws them.
    fallback: (m, 3) returned when the overlap is too small.

  Returns:
    (k, 3) float64 points, k <= count.
  """
  moved = points @ transform[:3, :3].T + transform[:3, 3]
  near = np.flatnonzero(engine.any_within(grid, moved, distance))
  if len(near) < icp_host.MIN_PAIRS:
    return fallback
  if len(near) > count:
    near = np.sort(rng.choice(near, count, replace=False))
  return points[near]


def fine_distance(source: np.ndarray, grid: engine.Grid, transform: np.ndarray,
                  distance: float, mr: float) -> float:
  """The pairing distance of `register`'s second ICP pass (cloud units).

  `ICP_FINE_FACTOR` times the median distance from the moved source points to their nearest
  target point, over the pairs closer than `distance`; clipped to [ICP_FINE_MIN_MR mr,
  `distance`]. An adaptive gate in the spirit of Zhang's ICP (1994): a precise laser scan (median
  residual about 0.6 mr) is refined at 1 mr, a noisy RGB-D fragment (about 1.1 mr) at about
  1.7 mr, so the boundary of the overlap and the far tail of the noise stop pulling the pose.

  Args:
    source: (n, 3) source points (float64).
    grid: an `engine.Grid` of the target.
    transform: (4, 4) the first pass's source -> target transform.
    distance: the first pass's pairing distance (cloud units).
    mr: the mesh resolution (cloud units).

  Returns:
    The gate; `distance` when no pair is closer than `distance`.
  """
  moved = source @ transform[:3, :3].T + transform[:3, 3]
  d = engine.knn(grid, moved, 1, distance)[0][:, 0]
  d = d[np.isfinite(d)]
  if len(d) == 0:
    return float(distance)
  lo = min(ICP_FINE_MIN_MR * mr, distance)
  return float(np.clip(ICP_FINE_FACTOR * np.median(d), lo, distance))


def icp_subset(points: np.ndarray, rng: np.random.Generator, count: int = ICP_POINTS
               ) -> np.ndarray:
  """The source points ICP pairs: all of them, or `count` drawn by `rng` (sorted)."""
  if len(points) > count:
    return points[np.sort(rng.choice(len(points), count, replace=False))]
  return points


class Refined(NamedTuple):
  """Stage "icp": the final transform, its fitness (the fraction of the ICP subset within
  icp_mr mr of the target) and rmse (cloud units), and the overlap's constraints
  (`rivals.overlap_constraints`: degeneracy ratio and the free direction, if any)."""

  transform: np.ndarray
  fitness: float
  rmse: float
  degeneracy: float
  free_direction: Any
  icp_points: np.ndarray
  kept: str = ""  # register(init=): the note of `from_init.kept_init` where the init was kept


def refine(prepared: Prepared, verified: Verified, icp_opts: IcpOptions, timer: StageTimer
           ) -> Refined:
  """Stages "icp" (`icp_passes` from the coarse pose on up to `ICP_POINTS` seeded source
  points) and the overlap's constraints (`overlap_constraints`, timed as "verification"); for a
  pair thinned by default, then `raw_pass` on the input points of each side `prepare` kept them
  for (`Side.raw`: not an oversampled side) (its pose is the transform; the fitness, rmse and
  constraints, which the verdict reads, stay those of the thinned clouds)."""
  src_pts, dst_pts = prepared.sides[0].points, prepared.sides[1].points
  target = prepared.sides[1]  # the input's spacing is the working cloud's where not thinned
  dst_spacing = target.input_spacing if target.input_index is None else None
  with timer("icp"):
    icp_src = icp_subset(src_pts, prepared.rng)
    final, fitness, rmse = icp_passes(icp_src, dst_pts, verified.coarse.transform,
                                      verified.overlap_distance, icp_opts.icp_fine, prepared.mr,
                                      int(icp_opts.icp_iterations), verified.target_grid,
                                      icp_opts.icp_mode, pool=src_pts, rng=prepared.rng,
                                      target_spacing=dst_spacing)
  with timer("verification"), serial_blas():
    degeneracy, free = overlap_constraints(icp_src, dst_pts, verified.target_grid, final,
                                           verified.overlap_distance)
  if any(side.raw is not None for side in prepared.sides) and icp_opts.icp_iterations > 0:
    with timer("icp"):
      src_in, dst_in = (side.points if side.raw is None else side.raw for side in prepared.sides)
      # the input's spacing where the target's points are its input points (not a thinned
      # oversampled target's centroids)
      dst_spacing = (target.input_spacing if target.raw is not None or target.input_index is None
                     else None)
      final = raw_pass(src_in, dst_in, final, prepared.mr, icp_opts, prepared.seed, dst_spacing)
  return Refined(final, fitness, rmse, degeneracy, free, icp_src)


def raw_pass(source: np.ndarray, target: np.ndarray, pose: np.ndarray, mr: float,
             icp_opts: IcpOptions, seed: int, target_spacing: float | None = None
             ) -> np.ndarray:
  """The last ICP pass of a pair thinned by default: `icp_opts.icp_mode` ICP of up to
  `RAW_ICP_POINTS` input source points (drawn with `seed`) against the input target points
  (`icp_normals.estimate_target_normals` for a pairing distance of `RAW_NORMAL_MR` mr: a radius of
  at most `RAW_NORMAL_SPACINGS` mean input spacings, so their cost grows with the points, not
  with their density), from
  `pose`, at the gates `RAW_GATES_MR` mr in turn. The thinned clouds' voxel centroids stand a
  fraction of a voxel off the surface; the input points do not. Returns `pose` itself when the
  pass moves a drawn point by more than `RAW_MAX_SHIFT_MR` mr (the verdict was reached at
  `pose`), or pairs too few points.

  Args:
    source, target: (n, 3), (m, 3) the input clouds (a side not thinned: its working points).
    pose: (4, 4) the thinned clouds' ICP pose, source -> target.
    mr: the working resolution (cloud units).
    icp_opts: the ICP options (`icp_mode`, `icp_iterations`).
    seed: seeds the draw.
    target_spacing: the target's mean nearest-neighbor spacing where measured already
      (`Side.input_spacing`); None measures it.

  Returns:
    (4, 4) float64 source -> target.
  """
  src = icp_subset(np.asarray(source, np.float64), np.random.default_rng(seed), RAW_ICP_POINTS)
  dst = np.asarray(target, np.float64)
  grid = engine.knn_grid(dst)
  plane = icp_opts.icp_mode == "point_to_plane"
  normals = (icp_normals.TargetNormals(dst, RAW_NORMAL_MR * mr, grid, spacings=RAW_NORMAL_SPACINGS,
                                    spacing=target_spacing) if plane else None)
  tr, fitness = pose, 0.0
  for gate in RAW_GATES_MR:
    tr, fitness, _ = icp(src, dst, tr, max_distance=gate * mr,
                         iterations=int(icp_opts.icp_iterations), target_grid=grid,
                         target_normals=normals, mode=icp_opts.icp_mode)
  if fitness * len(src) < icp_host.MIN_PAIRS or not np.all(np.isfinite(tr)):
    return pose
  shift = np.linalg.norm(src @ (tr[:3, :3] - pose[:3, :3]).T + (tr[:3, 3] - pose[:3, 3]), axis=1)
  return tr if float(shift.max()) <= RAW_MAX_SHIFT_MR * mr else pose
