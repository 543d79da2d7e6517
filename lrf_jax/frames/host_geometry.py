"""What the methods' host fast paths share: ball lists per chunk and numba geometry (float64).

A host fast path (`MethodSpec.host_frames`) computes a method's frames on the CPU straight from
the engine's ball lists (`engine.ball_lists`: every point within r of each keypoint), one
keypoint per thread, in float64, without padded patches. The helpers below are the numba
counterparts of the `lrf_jax.geometry` rules the jitted functions use (same tolerances, same
tie-breaking), so that both paths return the same frames up to float32 rounding. The kernels of
`MethodSpec.host_patch_frames` (`lrf_net_host`: frames from prepared patches) use them too.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np

from lrf_jax.search import engine
from lrf_jax.search.grid import writable_float64
from lrf_jax.geometry import ops as geometry

EPS = geometry.DEGENERATE_EPS


def run_kernel(kernel: Any, n: int, *args: Any) -> tuple[np.ndarray, np.ndarray]:
  """`kernel(*args, frames, valid)` into fresh (n, 3, 3) float64 frames and (n,) bool valid,
  as every host kernel is called; returns (frames as float32, valid)."""
  frames = np.empty((n, 3, 3))
  valid = np.empty(n, np.bool_)
  kernel(*args, frames, valid)
  return frames.astype(np.float32), valid


def ball_lists(points: np.ndarray, keypoints: np.ndarray, radius: float, index: Any,
               shells: tuple[float, float] | None = None, with_counts: bool = False
               ) -> tuple[np.ndarray, ...]:
  """(points (n, 3) float64, centers (N, 3), ptr (N + 1,), ball (ptr[-1],)) of every point
  within `radius` of each keypoint (only those within a * r or beyond b * r with
  `shells=(a, b)`, slightly widened), from the cloud's `SearchIndex` (`engine.ball_lists`);
  with `with_counts`, also (N,) the number of points within `radius` (whatever `shells`)."""
  pts = writable_float64(points)  # one kernel specialisation (read-only arrays are another)
  centers = np.ascontiguousarray(pts[np.asarray(keypoints)])
  lists = engine.ball_lists(index.grid(radius), centers, float(radius), shells, with_counts)
  return (pts, centers) + lists


@nb.njit(inline="always")
def set_identity(frames, valid, i):
  """Frame i := the identity, flagged invalid."""
  valid[i] = False
  for a in range(3):
    for b in range(3):
      frames[i, a, b] = 1.0 if a == b else 0.0


@nb.njit(inline="always")
def start_keypoint(frames, valid, ptr, i):
  """Frame i := the identity, flagged invalid (what it stays unless the kernel writes one);
  returns (start, stop), the range of keypoint i's ball in the ball list."""
  set_identity(frames, valid, i)
  return ptr[i], ptr[i + 1]


@nb.njit(inline="always")
def offset(points, j, center):
  """(ox, oy, oz, d2): the offset of point j from `center` and its squared length, summed over
  x, y, z in that order (the engine's rule, `in_ball`)."""
  ox = points[j, 0] - center[0]
  oy = points[j, 1] - center[1]
  oz = points[j, 2] - center[2]
  return ox, oy, oz, ox * ox + oy * oy + oz * oz


@nb.njit(inline="always")
def full_spectrum_ok(evals, eps):
  """`geometry.eigen_frame`'s test on ascending eigenvalues: both gaps > eps * |largest|."""
  scale = abs(evals[2])
  gap = min(evals[2] - evals[1], evals[1] - evals[0])
  return gap > eps * scale and scale > 0.0


@nb.njit(inline="always")
def smallest_ok(evals, eps):
  """`geometry.smallest_eigvec`'s test on ascending eigenvalues: the smallest is unique."""
  scale = max(evals[2], 0.0)
  return evals[1] - evals[0] > eps * scale and scale > 0.0


@nb.njit(inline="always")
def write_frame(frames, valid, i, z, x, eps=0.0):
  """`geometry.frame_from_zx(z, x, eps)`: rows (x, y = z × x, z) from a unit z and an
  unnormalised x; frame i flagged valid.

  Returns False (frame i left as it is) when the part of x off z has norm <= eps (x's units)."""
  d = x[0] * z[0] + x[1] * z[1] + x[2] * z[2]
  t0, t1, t2 = x[0] - d * z[0], x[1] - d * z[1], x[2] - d * z[2]
  nx = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
  if not nx > eps:
    return False
  t0, t1, t2 = t0 / nx, t1 / nx, t2 / nx
  frames[i, 0, 0], frames[i, 0, 1], frames[i, 0, 2] = t0, t1, t2
  frames[i, 1, 0] = z[1] * t2 - z[2] * t1
  frames[i, 1, 1] = z[2] * t0 - z[0] * t2
  frames[i, 1, 2] = z[0] * t1 - z[1] * t0
  frames[i, 2, 0], frames[i, 2, 1], frames[i, 2, 2] = z[0], z[1], z[2]
  valid[i] = True
  return True


def x_axis_sum_of(weight):
  """`lrf_net.x_axis_from_weights` on the host, the x axis of TOLDI and LRF-Net (paper eqs.
  `eq_vector_x`, `eq_axis_x`), for one way of weighting the neighbors: returns the numba
  function

      x_axis_sum(points, center, ball, start, stop, z, data, x_eps) -> (ok, s)

  s = Σ_t w_t v_t over the listed neighbors t, with o_t = points[ball[start + t]] - center,
  v_t = o_t - (o_t · z) z its projection on the tangent plane, and (w_t, o_t · z) =
  weight(data, t, o_t[0], o_t[1], o_t[2], z).

  Args of `weight`, an `nb.njit(inline="always")` function: data (what the caller passes on),
  t (the neighbor's place in the list), the offset o_t (cloud units), z; it returns the weight
  (any sign) and the height o_t · z: computed there and then (TOLDI's weight) or read from
  lists made beforehand (`listed_weight`).

  Args of `x_axis_sum`:
    points: (n, 3) coordinates (cloud units): the cloud, or one patch's offsets.
    center: (3,) the keypoint (an array or a tuple: (0.0, 0.0, 0.0) for a patch's offsets).
    ball: (>= stop,) rows of `points`, the neighbors being ball[start:stop]; or None, the
      neighbors being rows start..stop - 1 themselves (a patch's slots; compiled without the
      lookup).
    start, stop: the neighbors' range in `ball`.
    z: (3,) float64 unit z axis.
    data: what `weight` reads.
    x_eps: `lrf_net.X_EPS`.

  Returns of `x_axis_sum`:
    (ok, s): s (3,) float64, unnormalised (cloud units); ok is False when s vanishes relative
    to Σ_t |w_t| |v_t| (|s| <= x_eps Σ_t |w_t| |v_t|: a symmetric patch, or all weights 0).
    Neighbors of weight 0 are skipped (they add exactly nothing), so a padding slot of weight
    0 may hold any offset.

  One definition for both kernels, specialised per weight by this factory rather than written
  like the inline="always" helpers above: inlining its IR into a parallel kernel cost ~1 s (6 %)
  more compilation (numba's parfor passes), and a weight function passed as an argument to a
  non-inlined helper made the TOLDI kernel uncacheable (numba embedded the dispatcher's
  address). Compiled apart (once per kernel), it runs as fast as the loop written in a kernel.
  """

  @nb.njit
  def x_axis_sum(points, center, ball, start, stop, z, data, x_eps):
    sx = sy = sz = 0.0  # scalars, not an array: they stay in registers
    scale = 0.0
    for t in range(start, stop):
      j = t if ball is None else ball[t]
      ox = points[j, 0] - center[0]
      oy = points[j, 1] - center[1]
      oz = points[j, 2] - center[2]
      w, dot = weight(data, t - start, ox, oy, oz, z)
      if w == 0.0:  # no term, whatever o_t holds (padding)
        continue
      vx, vy, vz = ox - dot * z[0], oy - dot * z[1], oz - dot * z[2]
      sx += w * vx
      sy += w * vy
      sz += w * vz
      scale += abs(w) * np.sqrt(vx * vx + vy * vy + vz * vz)
    s = np.empty(3)
    s[0], s[1], s[2] = sx, sy, sz
    return np.sqrt(sx * sx + sy * sy + sz * sz) > x_eps * scale, s

  return x_axis_sum


@nb.njit(inline="always")
def listed_weight(data, t, ox, oy, oz, z):
  """`x_axis_sum_of`'s `weight` read from lists made beforehand: data = (weights, heights),
  both float64 (>= stop - start,), indexed by the neighbor's place t; heights o_t · z."""
  weights, heights = data
  return weights[t], heights[t]


@nb.njit(inline="always")
def better(score, d2, idx, best_score, best_d2, best_idx):
  """`geometry.lexicographic_argmax`'s order: a larger score, then nearer, then lower index."""
  if score != best_score:
    return score > best_score
  if d2 != best_d2:
    return d2 < best_d2
  return idx < best_idx


@nb.njit(inline="always")
def inner_stats(points, center, ball, start, stop, rz2, mean, cov):
  """Count, centroid offset and covariance about the centroid of the listed points within
  sqrt(rz2) of `center`, as the engine's r/3 statistics (`engine.ball_stats`) compute them."""
  s = engine.NO_MOMENTS
  for t in range(start, stop):
    j = ball[t]
    dx = points[j, 0] - center[0]
    dy = points[j, 1] - center[1]
    dz = points[j, 2] - center[2]
    if dx * dx + dy * dy + dz * dz <= rz2:
      s = engine.add_moment(s, dx, dy, dz)
  return engine.store_moments(s, mean, cov)


@nb.njit(inline="always")
def plane_z(points, center, ball, start, stop, rz2, eps, min_count):
  """(ok, z, mean): z the least-variance direction of the listed points within sqrt(rz2) of
  `center`, mean (3,) their centroid's offset from it; ok is False for fewer than `min_count` of
  them or a smallest eigenvalue not separated from the next (`smallest_ok`)."""
  mean = np.zeros(3)
  cov = np.zeros((3, 3))
  count = inner_stats(points, center, ball, start, stop, rz2, mean, cov)
  ok, z = smallest_z(cov, count, eps, min_count)
  return ok, z, mean


@nb.njit(inline="always")
def smallest_z(cov, count, eps, min_count):
  """(ok, z): z the eigenvector of the smallest eigenvalue of the float64 (3, 3) `cov` (sign
  arbitrary); ok is False for fewer than `min_count` points or a degenerate spectrum
  (`smallest_ok`)."""
  evals, evecs = np.linalg.eigh(cov)
  return smallest_ok(evals, eps) and count >= min_count, evecs[:, 0].copy()


@nb.njit(inline="always")
def z_signed_by(evecs, normal):
  """(z, ok): the eigenvector of the smallest eigenvalue (the first column of `evecs`, as
  `np.linalg.eigh` orders them), flipped to agree with `normal` (z · n >= 0); ok is False for a
  normal that is not finite or zero (`unit_or_zero`)."""
  n, ok = unit_or_zero(normal)
  z = evecs[:, 0].copy()
  if z[0] * n[0] + z[1] * n[1] + z[2] * n[2] < 0.0:
    z = -z
  return z, ok


@nb.njit(inline="always")
def finite_row(a, j):
  """a[j] (a row of 3) is finite."""
  return np.isfinite(a[j, 0]) and np.isfinite(a[j, 1]) and np.isfinite(a[j, 2])


@nb.njit(inline="always")
def unit_or_zero(v):
  """(v / |v|, True) for a finite non-zero v, else (zeros, False)."""
  n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
  out = np.zeros(3)
  if not (np.isfinite(n) and n > 0.0):
    return out, False
  out[0], out[1], out[2] = v[0] / n, v[1] / n, v[2] / n
  return out, True


@nb.njit(inline="always")
def in_ball(points, j, center, r2):
  """Point j lies within sqrt(r2) of center, by the engine's rule (float64 x, y, z sum, <=)."""
  return offset(points, j, center)[3] <= r2


@nb.njit(inline="always")
def owns_face(points, faces, k, v, center, r2):
  """Whether ball vertex v is the first of face k's vertices (in the face's order) within the
  ball: visiting every ball vertex's incident faces and keeping the owned ones visits every face
  with a vertex in the ball exactly once, without a list of faces."""
  for c in range(3):
    u = faces[k, c]
    if u == v:
      return True
    if in_ball(points, u, center, r2):
      return False
  return False


@nb.njit(inline="always")
def highest_point(points, center, ball, start, stop, z, ring2, strict):
  """The listed point farthest above the plane of `z` through `center` (largest (q - c) · z,
  ties as `better`) among those with |q - c|^2 > ring2 (`strict`) or >= ring2; -1 if none.
  FLARE's and the point signature's x direction."""
  best, best_d2, best_j = -np.inf, np.inf, -1
  for t in range(start, stop):
    j = ball[t]
    ox, oy, oz, d2 = offset(points, j, center)
    if d2 > ring2 or (not strict and d2 == ring2):
      h = ox * z[0] + oy * z[1] + oz * z[2]
      if best_j < 0 or better(h, d2, j, best, best_d2, best_j):
        best, best_d2, best_j = h, d2, j
  return best_j
