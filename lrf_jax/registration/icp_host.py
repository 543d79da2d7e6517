"""Point-to-plane ICP on the host (numpy, numba, float64): the sums, the step and the loop.

`lrf_jax.registration.icp(..., mode="point_to_plane")` runs `point_to_plane_icp`. Each
iteration pairs every source point p (under the current pose) with its nearest target point q
within `max_distance` (the engine's nearest-neighbor query on the target's grid, as
`engine.knn`) and takes q's unit normal n. The linearised Gauss-Newton step of Chen & Medioni's
objective sum ((R p + t - q) · n)^2 over a small rotation ω about a centre c (the target's
centroid) and a translation t solves the 6 x 6 normal equations

    (Aᵀ A) x = Aᵀ b,  rows a = [(p - c) × n, n],  b = (q - p) · n,  x = [ω, t],

whose sums a numba kernel accumulates, in the same pass as the pairing, per fixed block of
`_BLOCK` source points; the blocks' sums are added in block order, so the result does not depend
on the thread count. The pose is then updated by the exact rotation exp(ω) (Rodrigues) about c
and the translation t.

Conditioning: the rotation unknowns are rescaled by the pairs' RMS lever arm L (length units,
the square root of the trace of Aᵀ A's rotation block over that of its translation block) so that
both blocks have the same trace, and a Levenberg damping λ = `DAMPING` · trace / 6 is added to
the diagonal. A direction the pairs do not constrain (a single plane: the two in-plane
translations and the rotation about the normal) then has a zero right-hand side and a zero step
instead of a singular solve; a well-conditioned step changes by about `DAMPING` relative, and
the fixed point not at all. Pairs whose target normal is zero or non-finite are left out of the
normal equations (they still count for the fitness and rmse, which are point distances as in
point-to-point ICP).

Target normals, when the caller has none (`icp_normals.estimate_target_normals`): PCA normals
(`normals.pca_normals`, PCL's rule) over the pairing distance, capped at 4 x the target's mean
nearest-neighbor spacing (about 50 neighbors on a surface), so that a generous pairing distance
does not smooth a curved surface's normals away; their sign is irrelevant to ((q - p) · n)^2, so
no orientation pass is run. They are computed where pairs need them (`icp_normals.TargetNormals`): the sums
kernel returns each source point's target index, the normals of target points paired for the
first time are computed, and the sums of the blocks that paired them are taken again; a point's
normal does not depend on which others were computed, so the steps are those of normals
computed everywhere.

References:
  Chen & Medioni, "Object modelling by registration of multiple range images", IVC 1992
  (ICRA 1991). Low, "Linear least-squares optimization for point-to-plane ICP surface
  registration", UNC TR04-004, 2004.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from lrf_jax.search import engine
from lrf_jax.search.grid import Grid, writable_float64
from lrf_jax.search.nearest import nearest_moved  # the engine's ICP pairing step (inlined)
from lrf_jax.registration.icp_normals import TargetNormals, check_normals, unit_normals
from lrf_jax.registration.errors import to_transform
from lrf_jax.registration.host import proper_rotation

# Source points per parallel task of the sums kernel (a fixed partition: deterministic sums).
_BLOCK = 256
# Source points per block of the point-to-point sums (summed in block order: deterministic).
_SUMS_BLOCK = 32
# Relative Levenberg damping of the rescaled 6 x 6 normal equations.
DAMPING = 1e-6
# Fewest pairs with a usable normal for a step (six unknowns).
MIN_PAIRS = 6
# Layout of one block's sums: pairs, squared distances, pairs with a normal, Aᵀ b (6), Aᵀ A
# (upper triangle, row by row: 21).
_N_SUMS = 30


class PlaneSums(NamedTuple):
  """One point-to-plane step's statistics.

  Attributes:
    pairs: source points paired within `max_distance` (with or without a usable normal).
    sq_distance: sum of their squared point-to-point distances (cloud units²).
    plane_pairs: pairs whose target normal is usable (finite, non-zero).
    hessian: (6, 6) Aᵀ A over those pairs (unknowns ω (3), t (3); coordinates relative to the
      centre).
    gradient: (6,) Aᵀ b.
  """

  pairs: int
  sq_distance: float
  plane_pairs: int
  hessian: np.ndarray
  gradient: np.ndarray


@nb.njit(parallel=True, cache=True)
def _plane_sums(pts, slot_index, starts, origin, h, dims, target, normals, source, rot, trans, c0,
                max_d2, blocks, partial, paired):
  """Per block of `_BLOCK` source points (those numbered in `blocks`): the `_N_SUMS` sums over
  the pairs (moved source point, its nearest target point within sqrt(max_d2), as
  `engine.knn`), coordinates relative to c0, in the block's row of `partial`; each source
  point's target index (-1: unpaired) in `paired`."""
  m = source.shape[0]
  n = pts.shape[1]
  for t in nb.prange(blocks.shape[0]):
    blk = blocks[t]
    bd = np.empty(1)
    bi = np.empty(1, np.int64)
    a = np.empty(6)
    acc = partial[blk]
    acc[:] = 0.0
    for i in range(blk * _BLOCK, min(m, (blk + 1) * _BLOCK)):
      qx, qy, qz, j = nearest_moved(pts, slot_index, starts, origin, h, dims, source[i], rot,
                                    trans, max_d2, bd, bi)
      paired[i] = j if j < n else -1
      if j >= n:
        continue
      acc[0] += 1.0
      acc[1] += bd[0]
      nx, ny, nz = normals[j, 0], normals[j, 1], normals[j, 2]
      if not (np.isfinite(nx) and np.isfinite(ny) and np.isfinite(nz)):
        continue
      if nx == 0.0 and ny == 0.0 and nz == 0.0:
        continue
      px, py, pz = qx - c0[0], qy - c0[1], qz - c0[2]
      b = (target[j, 0] - qx) * nx + (target[j, 1] - qy) * ny + (target[j, 2] - qz) * nz
      a[0], a[1], a[2] = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx
      a[3], a[4], a[5] = nx, ny, nz
      acc[2] += 1.0
      for r in range(6):
        acc[3 + r] += a[r] * b
      k = 9
      for r in range(6):
        for c in range(r, 6):
          acc[k] += a[r] * a[c]
          k += 1


def plane_sums(grid: engine.Grid, normals: np.ndarray | TargetNormals, source: np.ndarray,
               rotation: np.ndarray, translation: np.ndarray, max_distance: float,
               center: np.ndarray) -> PlaneSums:
  """The point-to-plane normal equations of one step, without materialising the pairs.

  Each source point s is moved to p = R s + t and paired with its nearest grid point q within
  `max_distance` (as `engine.knn`: ties go to the smaller index), in the same pass. With a
  `TargetNormals`, the normals of target points paired for the first time are then computed and
  the sums of the blocks of source points paired with them taken again: the same sums as with
  those normals given.

  Args:
    grid: `engine.Grid` of the target cloud (any cell size).
    normals: (m, 3) float64 unit normals of the grid's points (NaN rows: unusable), or a
      `TargetNormals` of them.
    source: (n, 3) float64 source points.
    rotation: (3, 3) R.
    translation: (3,) t.
    max_distance: pairing distance (cloud units).
    center: (3,) c, the rotation centre of the step (pick a point near the clouds: it keeps the
      sums well conditioned).

  Returns:
    The `PlaneSums`.
  """
  src = writable_float64(source).reshape(-1, 3)  # one specialisation of the kernel
  r = float(max_distance)
  lazy = normals if isinstance(normals, TargetNormals) else None
  # a TargetNormals' own array (float64, contiguous, writable): `require` fills it in place and
  # the blocks run again read the new rows
  nrm = normals.unit if isinstance(normals, TargetNormals) else writable_float64(normals)
  nblock = max(1, (len(src) + _BLOCK - 1) // _BLOCK)
  partial = np.empty((nblock, _N_SUMS))
  paired = np.empty(len(src), np.int64)

  def run(blocks: np.ndarray) -> None:
    _plane_sums(grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h, grid.dims,
                grid.points, nrm, src, writable_float64(rotation),
                writable_float64(translation), writable_float64(center),
                r * r if np.isfinite(r) else np.inf, blocks, partial, paired)

  run(np.arange(nblock))
  if lazy is not None:
    rows = np.flatnonzero(paired >= 0)
    rows = rows[~lazy.done[paired[rows]]]
    if len(rows):
      lazy.require(paired[rows])
      run(np.unique(rows // _BLOCK))
  acc = partial.sum(axis=0)
  hessian = np.zeros((6, 6))
  hessian[np.triu_indices(6)] = acc[9:]
  hessian = hessian + np.triu(hessian, 1).T
  return PlaneSums(int(acc[0]), float(acc[1]), int(acc[2]), hessian, acc[3:9].copy())


def rodrigues(omega: np.ndarray) -> np.ndarray:
  """exp([ω]×): the (3, 3) rotation by |ω| radians about ω (identity for ω = 0)."""
  w = np.asarray(omega, np.float64)
  theta = float(np.linalg.norm(w))
  k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
  if theta < 1e-8:  # Taylor series to second order: exact in float64 at this size
    return np.eye(3) + k + 0.5 * (k @ k)
  return (np.eye(3) + (np.sin(theta) / theta) * k
          + ((1.0 - np.cos(theta)) / theta ** 2) * (k @ k))


def solve_step(hessian: np.ndarray, gradient: np.ndarray) -> np.ndarray:
  """x = [ω, t] (6,) from the normal equations, rescaled and damped as the module describes.

  Args:
    hessian: (6, 6) Aᵀ A.
    gradient: (6,) Aᵀ b.

  Returns:
    (6,) float64 step; zeros where the equations are empty, NaN if they are not finite.
  """
  h = np.asarray(hessian, np.float64)
  g = np.asarray(gradient, np.float64)
  rot, trans = np.trace(h[:3, :3]), np.trace(h[3:, 3:])
  lever = np.sqrt(rot / trans) if rot > 0 and trans > 0 else 1.0
  s = np.array([1.0 / lever] * 3 + [1.0] * 3)
  hs = h * s[:, None] * s[None, :]
  scale = np.trace(hs) / 6.0
  if not scale > 0:
    return np.zeros(6) if scale == 0 else np.full(6, np.nan)
  return np.linalg.solve(hs + DAMPING * scale * np.eye(6), g * s) * s


def step_transform(x: np.ndarray, center: np.ndarray) -> np.ndarray:
  """(4, 4) pose increment of the step x = [ω, t]: p -> exp(ω) (p - c) + c + t."""
  r = rodrigues(x[:3])
  out = np.eye(4)
  out[:3, :3] = r
  out[:3, 3] = np.asarray(center, np.float64) + x[3:] - r @ center
  return out


# Poses `point_to_plane_icp` remembers to detect a cycle of pairings (`revisited`).
CYCLE_MEMORY = 8


def revisited(pose: np.ndarray, recent: list[np.ndarray], max_distance: float,
              tolerance: float) -> int | None:
  """The index of the first pose in `recent` that `pose` equals to within `tolerance` (the
  convergence measure of `point_to_plane_icp`: the rotation angle between them in radians plus
  their translations' distance over `max_distance`), else None.

  Near convergence the pairing can alternate between a few sets of pairs: each step undoes the
  previous ones and the pose returns to where it was (measured on room fragments: cycles of 2
  and 5 poses from the 12th iteration on, to the iteration cap). Further steps only go round;
  `point_to_plane_icp` stops there and keeps the cycle's pose of least mean squared distance.
  """
  for i, old in enumerate(recent):
    moved = np.linalg.norm(pose[:3, 3] - old[:3, 3]) / max_distance
    if moved >= tolerance:  # the angle below is >= 0: this pose is not a return
      continue
    rel = pose[:3, :3] @ old[:3, :3].T
    axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    angle = np.arctan2(0.5 * np.linalg.norm(axis), 0.5 * (np.trace(rel) - 1.0))  # exact near 0
    if angle + moved < tolerance:
      return i
  return None


def point_to_plane_icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, *,
                       max_distance: float, iterations: int, tolerance: float,
                       target_grid: engine.Grid | None = None,
                       target_normals: np.ndarray | TargetNormals | None = None
                       ) -> tuple[np.ndarray, float, float]:
  """Point-to-plane ICP from `init` (what `registration.icp` runs in that mode).

  Stops when a step is below `tolerance` (its rotation in radians plus its translation over
  `max_distance`), has fewer than `MIN_PAIRS` pairs with a usable normal, or returns to one of
  the last `CYCLE_MEMORY` poses (`revisited`: a cycle of pairings; the cycle's pose of least
  mean squared pair distance is kept).

  Args:
    source: (n, 3) float64 source points.
    target: (m, 3) float64 target points.
    init: (4, 4) initial source -> target transform.
    max_distance: pairing distance (cloud units, > 0).
    iterations: at most this many steps.
    tolerance: convergence threshold.
    target_grid: optional `engine.Grid` of `target` to reuse (default: `engine.knn_grid`).
    target_normals: (m, 3) normals of `target` (any length or sign), or a `TargetNormals` of
      it (computed where pairs need them); None: a `TargetNormals` (`estimate_target_normals`'
      figures at the target points paired).

  Returns:
    (transform (4, 4), fitness = fraction of source points paired, rmse of the pairs' point
    distances), both at the returned transform.

  Raises:
    ValueError: `target_normals` not (m, 3), or an infinite `max_distance` with no normals.
  """
  target = np.ascontiguousarray(target, np.float64)
  if target_normals is None and not np.isfinite(max_distance):
    raise ValueError("max_distance: expected a finite distance to estimate the target normals "
                     f"over, got {max_distance!r}")
  grid = target_grid if target_grid is not None else engine.knn_grid(target)
  given: np.ndarray | TargetNormals
  if isinstance(target_normals, TargetNormals):
    own = target_normals.points
    if own is not target and not (own.shape == target.shape and np.array_equal(own, target)):
      raise ValueError(f"target_normals: a TargetNormals of another cloud ({len(own)} points) "
                       f"for a target of {len(target)}")
    given = target_normals
  elif target_normals is None:  # computed where the pairs need them
    given = TargetNormals(target, max_distance, grid)
  else:
    given = unit_normals(check_normals(target_normals, len(target)))
  center = target.mean(axis=0) if len(target) else np.zeros(3)
  tr = np.array(init, np.float64)

  def sums(pose):
    return plane_sums(grid, given, source, pose[:3, :3], pose[:3, 3], max_distance, center)

  cur = sums(tr)
  recent = [(tr, cur)]  # the last CYCLE_MEMORY poses and their sums
  for _ in range(int(iterations)):
    if cur.plane_pairs < MIN_PAIRS:
      break
    x = solve_step(cur.hessian, cur.gradient)
    if not np.all(np.isfinite(x)):
      break
    move = step_transform(x, center)
    tr = move @ tr
    cur = sums(tr)
    if np.linalg.norm(x[:3]) + np.linalg.norm(move[:3, 3]) / max_distance < tolerance:
      break
    back = revisited(tr, [pose for pose, _ in recent], max_distance, tolerance)
    if back is not None:  # a cycle of pairings: the pose of least mean squared distance
      tr, cur = min(recent[back:], key=lambda e: e[1].sq_distance / max(e[1].pairs, 1))
      break
    recent = (recent + [(tr, cur)])[-CYCLE_MEMORY:]
  rmse = np.sqrt(cur.sq_distance / cur.pairs) if cur.pairs else float("inf")
  return tr, (cur.pairs / len(source) if len(source) else 0.0), float(rmse)


# ---------------------------------------------------------------------------------------------
# Point-to-point sums (`icp`).


@nb.njit(parallel=True, cache=True)
def _icp_sums(pts, slot_index, starts, origin, h, dims, target, source, rot, trans, c0, max_d2,
              partial):
  """Per block of source points: the sums of one ICP step over the pairs (moved source point,
  its nearest target point within sqrt(max_d2), as `knn`), coordinates relative to c0."""
  m = source.shape[0]
  n = pts.shape[1]
  for blk in nb.prange(partial.shape[0]):
    bd = np.empty(1)
    bi = np.empty(1, np.int64)
    acc = partial[blk]
    acc[:] = 0.0
    for i in range(blk * _SUMS_BLOCK, min(m, (blk + 1) * _SUMS_BLOCK)):
      qx, qy, qz, j = nearest_moved(pts, slot_index, starts, origin, h, dims, source[i], rot,
                                    trans, max_d2, bd, bi)
      if j >= n:
        continue
      a0, a1, a2 = qx - c0[0], qy - c0[1], qz - c0[2]
      b0, b1, b2 = target[j, 0] - c0[0], target[j, 1] - c0[1], target[j, 2] - c0[2]
      acc[0] += 1.0
      acc[1] += bd[0]
      acc[2] += a0
      acc[3] += a1
      acc[4] += a2
      acc[5] += b0
      acc[6] += b1
      acc[7] += b2
      acc[8] += a0 * b0
      acc[9] += a0 * b1
      acc[10] += a0 * b2
      acc[11] += a1 * b0
      acc[12] += a1 * b1
      acc[13] += a1 * b2
      acc[14] += a2 * b0
      acc[15] += a2 * b1
      acc[16] += a2 * b2


def icp_sums(grid: Grid, source: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
             max_distance: float, center: np.ndarray
             ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray]:
  """One ICP step's statistics without materialising the pairs.

  Each source point s is moved to a = R s + t and paired with its nearest grid point b within
  `max_distance` (ties: the smaller index, as `knn`); unpaired points are left out.

  Args:
    grid: `Grid` of the target cloud (any cell size).
    source: (n, 3) source points.
    rotation: (3, 3) R.
    translation: (3,) t.
    max_distance: pairing distance (cloud units).
    center: (3,) the sums are taken of a - center and b - center (pick a point near the clouds:
      it keeps the float64 sums well conditioned).

  Returns:
    (pairs, sum of squared pair distances, sum_a (3,), sum_b (3,), sum of a bᵀ (3, 3)).
  """
  src = writable_float64(source).reshape(-1, 3)
  r = float(max_distance)
  nblock = max(1, (len(src) + _SUMS_BLOCK - 1) // _SUMS_BLOCK)
  partial = np.empty((nblock, 17))
  _icp_sums(grid.xyz, grid.slot_index, grid.starts, grid.origin, grid.h, grid.dims, grid.points,
            src, writable_float64(rotation), writable_float64(translation),
            writable_float64(center), r * r if np.isfinite(r) else np.inf, partial)
  acc = partial.sum(axis=0)
  return int(acc[0]), float(acc[1]), acc[2:5], acc[5:8], acc[8:17].reshape(3, 3)


# ---------------------------------------------------------------------------------------------
# The ICP loop (`register`'s refinement).


def icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, *, max_distance: float,
        iterations: int = 30, tolerance: float = 1e-7,
        target_grid: engine.Grid | None = None,
        target_normals: np.ndarray | TargetNormals | None = None,
        mode: str = "point_to_plane") -> tuple[np.ndarray, float, float]:
  """Point-to-plane or point-to-point ICP from an initial pose (host, float64, deterministic).

  Each iteration pairs every source point with its nearest target point and keeps the pairs
  closer than `max_distance`. "point_to_plane" (Chen & Medioni) takes one damped Gauss-Newton
  step of sum ((R p + t - q) · n_q)^2 (`lrf_jax.registration.icp_host`; pairs whose normal is zero or
  non-finite are left out of the step); "point_to_point" (Besl & McKay) solves Kabsch. It stops
  when the pose changes by less than `tolerance` (rotation in radians plus translation over
  `max_distance`).

  Args:
    source: (n, 3) points.
    target: (m, 3) points.
    init: (4, 4) initial source -> target transform.
    max_distance: pairs farther apart are ignored (cloud units).
    iterations: at most this many iterations.
    tolerance: convergence threshold.
    target_grid: optional `engine.Grid(target, max_distance)` to reuse.
    target_normals: (m, 3) target normals for "point_to_plane" (any length, any sign; zero or
      non-finite rows are skipped), or a `TargetNormals` of the target. None: unsigned PCA
      normals (`estimate_target_normals`: radius min(max_distance, 4 x the target's mean
      nearest-neighbor spacing), computed at the target points paired, `TargetNormals`).
      Ignored by "point_to_point".
    mode: "point_to_plane" or "point_to_point".

  Returns:
    (transform (4, 4), fitness = fraction of source points paired, rmse of the pairs' point
    distances), both modes alike.

  Raises:
    ValueError: an unknown `mode`, `target_normals` not of shape (m, 3), or `max_distance` not
      a positive number (finite when normals are estimated).
  """

  if mode not in ("point_to_point", "point_to_plane"):
    raise ValueError(f"mode: expected 'point_to_point' or 'point_to_plane', got {mode!r}")
  try:
    positive = float(max_distance) > 0
  except (TypeError, ValueError):
    positive = False
  if not positive:
    raise ValueError(f"max_distance: expected a positive distance, got {max_distance!r}")
  target = np.asarray(target, np.float64)
  source = np.asarray(source, np.float64)
  if mode == "point_to_plane":
    return point_to_plane_icp(source, target, init, max_distance=float(max_distance),
                                       iterations=iterations, tolerance=tolerance,
                                       target_grid=target_grid, target_normals=target_normals)
  grid = target_grid if target_grid is not None else engine.Grid(target, max_distance)
  center = target.mean(axis=0) if len(target) else np.zeros(3)

  def step(tr):  # the pairs' sums under tr (icp_sums), their count and rmse
    n, d2, sa, sb, sab = icp_sums(grid, source, tr[:3, :3], tr[:3, 3], max_distance,
                                         center)
    return n, (np.sqrt(d2 / n) if n else float("inf")), sa, sb, sab

  tr = np.array(init, np.float64)
  for _ in range(int(iterations)):
    n, _, sa, sb, sab = step(tr)
    if n < 3:
      break
    ca, cb = sa / n, sb / n  # centroids relative to `center`
    r = proper_rotation(sab - n * np.outer(ca, cb))
    move = to_transform(r, (cb + center) - r @ (ca + center))
    tr = move @ tr
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))
    if angle + np.linalg.norm(move[:3, 3]) / max_distance < tolerance:
      break
  n, rmse, *_ = step(tr)
  return tr, (n / len(source) if len(source) else 0.0), float(rmse)
