"""Host-side surface normals and mesh quantities shared by the hand-crafted LRFs.

Everything here runs once per cloud on the host (numpy, numba kernels and the engine, float64);
the LRF functions in
`lrf_jax.frames` then receive per-keypoint gathers of these arrays through their `prepare` hook
(`frames.normal_based.prepare_normals`, `frames.rops.prepare_triangles`).

Normals (`estimate_normals`, used when `compute_frames` is called without `normals=`):

* direction: PCL's `NormalEstimation` (Rusu 2009): the eigenvector of the smallest eigenvalue of
  the covariance, about their centroid, of all points within `normal_radius` of the point
  (default `NORMAL_RADIUS_RATIO` · r = 3 mr at the paper's r = 15 mr); NaN for fewer than 3
  neighbors (PCL's rule) or a degenerate spectrum (collinear points);
* orientation, which must be *equivariant* (it may not depend on a fixed viewpoint, which does not
  move with the cloud):
  - with a mesh (`faces`): the sign that agrees with the area-weighted vertex normal of the faces,
    i.e. with the triangles' winding;
  - without: Hoppe et al. (1992) propagation (`orientation.orient_by_propagation`; lrf_net_plus
    adds a convexity vote per component, `orientation.orient_by_vote`, via `voted_normals`). For
    a single-view scan pass normals oriented towards the sensor instead
    (`pca_normals(..., viewpoint=...)`, PCL's `flipNormalTowardsViewpoint`).

The orientation's names (`lrf_jax.geometry.orientation`) are importable from here too.

Mesh quantities: `vertex_normals` (area-weighted face normals) and `mean_curvature` (cotangent
Laplacian, Meyer et al. 2003), the scalar function of GFrames.

Results for the last cloud are cached (one entry, keyed by a digest of the arrays' bytes), so
`compute_frames`, which calls `prepare` once per chunk of keypoints, computes them once. The cache
hands out copies of its arrays: writing into a result never changes a later one.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax.search import engine
from lrf_jax.checks import validate_viewpoint
from lrf_jax.geometry.cloud_cache import CLOUD_CACHE, cache_last
from lrf_jax.geometry.orientation import (PROPAGATION_K, VOTE_EPS, VOTE_SAMPLES, knn_components,
                                          orient_by_propagation, orient_by_reference,
                                          orient_by_vote)

__all__ = [  # the orientation's and the cache's names stay importable from here
    "CLOUD_CACHE", "NORMAL_RADIUS_RATIO", "PROPAGATION_K", "VOTE_EPS", "VOTE_SAMPLES",
    "cache_last", "cotangent_laplacian_curvature", "default_normals", "estimate_normals",
    "face_cross", "knn_components", "mean_curvature", "orient_by_propagation",
    "orient_by_reference", "orient_by_vote", "pca_normals", "vertex_normals", "voted_normals",
]

# Default normal radius as a fraction of the support radius r (3 mr at r = 15 mr).
NORMAL_RADIUS_RATIO = 0.2
# Relative eigenvalue gap below which a PCA normal is undefined (as geometry.DEGENERATE_EPS).
_DEGENERATE = 1e-6

# Below this relative gap between the two smallest eigenvalues the closed form hands over to
# LAPACK (`np.linalg.eigh`), whose eigenvectors stay accurate as the gap closes.
_CLOSED_FORM_GAP = 1e-3


@nb.njit(inline="always")
def _smallest_eigpair(c, out):
  """Eigenvalues (ascending) and the smallest one's unit eigenvector of the symmetric 3 x 3 `c`
  in closed form (Smith 1961, the trigonometric solution; the vector from the largest cross
  product of two rows of c - λ I); LAPACK below `_CLOSED_FORM_GAP`. Returns the eigenvalues."""
  p1 = c[0, 1] ** 2 + c[0, 2] ** 2 + c[1, 2] ** 2
  q = (c[0, 0] + c[1, 1] + c[2, 2]) / 3.0
  p2 = (c[0, 0] - q) ** 2 + (c[1, 1] - q) ** 2 + (c[2, 2] - q) ** 2 + 2.0 * p1
  p = np.sqrt(p2 / 6.0)
  evals = np.empty(3)
  if p > 0.0 and np.isfinite(p):
    b00, b11, b22 = (c[0, 0] - q) / p, (c[1, 1] - q) / p, (c[2, 2] - q) / p
    b01, b02, b12 = c[0, 1] / p, c[0, 2] / p, c[1, 2] / p
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (
        b01 * b12 - b11 * b02)
    phi = np.arccos(min(max(det / 2.0, -1.0), 1.0)) / 3.0
    e_hi = q + 2.0 * p * np.cos(phi)
    e_lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    evals[0], evals[1], evals[2] = e_lo, 3.0 * q - e_hi - e_lo, e_hi
    if evals[1] - evals[0] > _CLOSED_FORM_GAP * max(evals[2], 0.0):
      r0 = np.array([c[0, 0] - e_lo, c[0, 1], c[0, 2]])
      r1 = np.array([c[0, 1], c[1, 1] - e_lo, c[1, 2]])
      r2 = np.array([c[0, 2], c[1, 2], c[2, 2] - e_lo])
      best = 0.0
      w = np.empty(3)
      for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        # u x v written out: numba's np.cross compiles its shape checks and their messages, a
        # tenth of a first registration's compile
        w[0], w[1], w[2] = u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], \
            u[0] * v[1] - u[1] * v[0]
        nw = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        if nw > best:
          best = nw
          out[:] = w
      if best > 0.0:
        out /= np.sqrt(best)
        return evals
  w, v = np.linalg.eigh(c)
  out[:] = v[:, 0]
  return w


@nb.njit(cache=True)  # serial: a few ms for 100k points, and parallel=True doubled its compile
def _smallest_eigvecs(cov, evals, vecs):
  for i in range(cov.shape[0]):
    evals[i] = _smallest_eigpair(cov[i], vecs[i])


def pca_normals(points: np.ndarray, radius: float, *, grid: engine.Grid | None = None,
                viewpoint: np.ndarray | None = None, min_neighbors: int = 3,
                at: np.ndarray | None = None) -> np.ndarray:
  """PCL-like PCA normals: smallest eigenvector of the neighbors' covariance about their centroid.

  Args:
    points: (n, 3) cloud.
    radius: normal radius (cloud units); every point within it, the point itself included, counts.
    grid: optional `lrf_jax.search.engine.Grid(points, cell)` to reuse (default: cells of radius / 2).
    viewpoint: (3,) optional; when given, normals are flipped towards it as PCL's
      `flipNormalTowardsViewpoint` ((v - p) · n >= 0). When None the sign is arbitrary (orient them
      with `orient_normals`).
    min_neighbors: fewer neighbors than this give a NaN normal (PCL: 3).
    at: optional (k,) indices of the points whose normals are wanted (default: every point);
      each is what the call for every point gives in its row, the neighbors still drawn from
      the whole cloud.

  Returns:
    (n, 3), or (k, 3) with `at`, float64 unit normals; NaN rows where undefined (too few
    neighbors, collinear points).

  References:
    Rusu, "Semantic 3D object maps for everyday manipulation in human living environments", 2009
    (PCL `NormalEstimation::computePointNormal`).
  """
  pts = np.asarray(points, np.float64)
  if grid is None:
    grid = engine.Grid(pts, float(radius) / 2)
  # One compiled pass: count, centroid and covariance about the centroid, offsets taken relative
  # to the query point (numerically stable far from the origin).
  centers = pts if at is None else pts[np.asarray(at, np.int64)]
  counts, mean, cov = engine.ball_stats(grid, centers, radius)
  evals = np.empty((len(centers), 3))
  normals = np.empty((len(centers), 3))
  _smallest_eigvecs(np.ascontiguousarray(cov), evals, normals)
  scale = np.maximum(evals[:, 2], 0.0)
  ok = (counts >= min_neighbors) & (scale > 0) & (evals[:, 1] - evals[:, 0] > _DEGENERATE * scale)
  if viewpoint is not None:
    flip = np.einsum("ij,ij->i", np.asarray(viewpoint, np.float64)[None] - centers, normals) < 0
    normals[flip] *= -1.0
  normals[~ok] = np.nan
  return normals


@nb.njit(inline="always")
def face_cross(pts, f, k):
  """(p1 - p0) × (p2 - p0) of face k (pts (n, 3) float64, f (f, 3) int64): twice its area
  times its unit normal, as a tuple of three floats (numba, inline)."""
  i0, i1, i2 = f[k, 0], f[k, 1], f[k, 2]
  ux, uy, uz = pts[i1, 0] - pts[i0, 0], pts[i1, 1] - pts[i0, 1], pts[i1, 2] - pts[i0, 2]
  vx, vy, vz = pts[i2, 0] - pts[i0, 0], pts[i2, 1] - pts[i0, 1], pts[i2, 2] - pts[i0, 2]
  return uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx


@nb.njit(cache=True, error_model="numpy")  # x / 0 -> inf or nan, as numpy
def _vertex_normals(pts, f):
  n = pts.shape[0]
  cross = np.empty((f.shape[0], 3))
  for k in range(f.shape[0]):
    cross[k, 0], cross[k, 1], cross[k, 2] = face_cross(pts, f, k)
  acc = np.zeros((n, 3))
  for c in range(3):  # corner by corner, each corner's faces in order
    for k in range(f.shape[0]):
      for a in range(3):
        acc[f[k, c], a] += cross[k, a]
  out = np.empty((n, 3))
  for v in range(n):
    norm = np.sqrt(acc[v, 0] * acc[v, 0] + acc[v, 1] * acc[v, 1] + acc[v, 2] * acc[v, 2])
    for a in range(3):
      out[v, a] = acc[v, a] / norm if norm != 0.0 else np.nan
  return out


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """Area-weighted vertex normals of a triangle mesh (orientation from the faces' winding).

  Each vertex sums (p1 - p0) × (p2 - p0) (twice the area times the unit normal) of its faces
  and normalises the sum.

  Args:
    points: (n, 3) vertices.
    faces: (f, 3) vertex indices, counter-clockwise seen from outside.

  Returns:
    (n, 3) float64 unit normals; NaN for vertices without (non-degenerate) faces.
  """
  pts = np.ascontiguousarray(points, np.float64)
  f = np.ascontiguousarray(faces, np.int64)
  return _vertex_normals(pts, f)


def voted_normals(points: np.ndarray, normal_radius: float, vote_radius: float
                  ) -> tuple[np.ndarray, np.ndarray]:
  """PCA normals over `normal_radius` (`pca_normals`) oriented from the points alone
  (`orient_by_vote` with votes over `vote_radius`): (normals (n, 3), trust (n,)), float64.
  Cached for the last (points, radii); each call returns its own copies."""
  pts = np.asarray(points, np.float64)
  return cache_last("voted_normals", (pts, float(normal_radius), float(vote_radius)),
                    lambda: orient_by_vote(pts, pca_normals(pts, normal_radius), vote_radius))


def estimate_normals(points: np.ndarray, normal_radius: float,
                     faces: np.ndarray | None = None,
                     viewpoint: np.ndarray | None = None) -> np.ndarray:
  """The default normals of `compute_frames`: PCA over `normal_radius`, oriented equivariantly.

  Orientation, in order of precedence: the mesh winding when `faces` is given; towards
  `viewpoint` when given (a single-view scan: the sensor position moves with the cloud, so this
  is equivariant too); MST propagation otherwise (see the module docstring). Propagation has no
  reliable global sign on an open scan: on the bunny scan bun000 it orients 94 % of the normals
  inwards, which flips every normal-based LRF on that scan. Cached for the last
  (points, radius, faces, viewpoint); each call returns its own copy.

  Args:
    points: (n, 3) cloud.
    normal_radius: PCA radius (cloud units).
    faces: optional (f, 3) triangles used for the orientation only.
    viewpoint: optional (3,) sensor position in the cloud's coordinates.

  Returns:
    (n, 3) float64 unit normals, NaN where undefined.
  """
  pts = np.asarray(points, np.float64)

  def compute():
    if faces is None and viewpoint is not None:
      return pca_normals(pts, normal_radius, viewpoint=viewpoint)
    nrm = pca_normals(pts, normal_radius)
    if faces is not None:
      return orient_by_reference(nrm, vertex_normals(pts, faces))
    return orient_by_propagation(pts, nrm)

  viewpoint = validate_viewpoint(viewpoint)
  return cache_last("normals", (pts, float(normal_radius), faces, viewpoint), compute)


@nb.njit(inline="always")
def _cot(pts, o, i, j):
  """cot of the angle at vertex o of the triangle (o, i, j), clipped to +-1e3 (0 if undefined)."""
  ux, uy, uz = pts[i, 0] - pts[o, 0], pts[i, 1] - pts[o, 1], pts[i, 2] - pts[o, 2]
  vx, vy, vz = pts[j, 0] - pts[o, 0], pts[j, 1] - pts[o, 1], pts[j, 2] - pts[o, 2]
  cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
  cr = np.sqrt(cx * cx + cy * cy + cz * cz)
  cot = (ux * vx + uy * vy + uz * vz) / cr
  if np.isnan(cot):
    return 0.0
  return min(max(cot, -1e3), 1e3)


@nb.njit(cache=True, error_model="numpy")  # x / 0 -> inf or nan, as numpy
def _cotangent_laplacian(pts, f):
  """(barycentric area (n,), the cotangent Laplacian's sum Σ_j w_ij (x_j - x_i) (n, 3))."""
  n = pts.shape[0]
  area = np.zeros(n)
  for k in range(f.shape[0]):
    x, y, z = face_cross(pts, f, k)
    third = 0.5 * np.sqrt(x * x + y * y + z * z) / 3.0
    for c in range(3):
      area[f[k, c]] += third
  lap = np.zeros((n, 3))
  w = np.empty(f.shape[0])
  for c in range(3):  # the edge (i, j) opposite corner c of every face: + at i, then - at j
    for k in range(f.shape[0]):
      w[k] = _cot(pts, f[k, c], f[k, (c + 1) % 3], f[k, (c + 2) % 3])
    for side in range(2):
      for k in range(f.shape[0]):
        i, j = f[k, (c + 1) % 3], f[k, (c + 2) % 3]
        v = i if side == 0 else j
        sgn = 1.0 if side == 0 else -1.0
        for a in range(3):
          lap[v, a] += sgn * (w[k] * (pts[j, a] - pts[i, a]))
  return area, lap


def cotangent_laplacian_curvature(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """Signed mean curvature per vertex from the cotangent Laplacian (uncached; see mean_curvature).

  H_i = -(Δx)_i · n_i / 2 with (Δx)_i = Σ_j (cot α_ij + cot β_ij)(x_j - x_i) / (2 A_i), A_i one
  third of the area of the faces around i (barycentric cells) and n_i the area-weighted vertex
  normal; positive for a convex surface whose faces wind outward (a sphere of radius ρ gives 1/ρ).
  Cotangents are clipped to ±1e3 so that slivers cannot dominate.

  Args:
    points: (n, 3) vertices.
    faces: (f, 3) triangles.

  Returns:
    (n,) float64 mean curvature (1 / cloud units); 0 for isolated vertices.

  References:
    Meyer, Desbrun, Schröder, Barr, "Discrete differential-geometry operators for triangulated
    2-manifolds", 2003.
  """
  pts = np.ascontiguousarray(points, np.float64)
  f = np.ascontiguousarray(faces, np.int64)
  area, lap = _cotangent_laplacian(pts, f)
  with np.errstate(invalid="ignore", divide="ignore"):
    lap = lap / (2.0 * area[:, None])
  vn = _vertex_normals(pts, f)
  h = -0.5 * np.einsum("ij,ij->i", np.nan_to_num(lap), np.nan_to_num(vn))
  return np.where(area > 0, h, 0.0)


def mean_curvature(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """`cotangent_laplacian_curvature`, cached for the last mesh (each call returns a copy)."""
  pts = np.asarray(points, np.float64)
  f = np.asarray(faces, np.int64)
  return cache_last("mean_curvature", (pts, f), lambda: cotangent_laplacian_curvature(pts, f))


def default_normals(points: np.ndarray, radius: float, faces: np.ndarray | None,
                    normals: np.ndarray | None,
                    viewpoint: np.ndarray | None = None) -> np.ndarray:
  """The normals a method uses: the caller's, else `estimate_normals` at NORMAL_RADIUS_RATIO · r.

  Raises:
    ValueError: `normals` of the wrong shape.
  """
  if normals is not None:
    nrm = np.asarray(normals)
    if nrm.ndim != 2 or nrm.shape != np.shape(points):
      raise ValueError(f"normals: expected shape {np.shape(points)} (one per point), "
                       f"got {nrm.shape}")
    return nrm
  return estimate_normals(points, NORMAL_RADIUS_RATIO * radius, faces, viewpoint)
