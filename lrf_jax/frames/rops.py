"""RoPS local reference frames (Guo, Sohel, Bennamoun, Lu, Wan 2013), as PCL 1.13 computes them.

Needs a triangle mesh. The local surface of a keypoint p is every triangle with at least one vertex
within r (PCL's `ROPSEstimation::getLocalSurface`); `prepare_triangles` gathers them on the host as
vertex offsets q - p, padded to a fixed T. For a triangle τ with offsets a_1, a_2, a_3:

* scatter (paper eq. `eq_triangle`): C_τ = (1/12) [Σ_i Σ_j a_i a_jᵀ + Σ_i a_i a_iᵀ];
* weights (eqs. `eq_rops_w1`, `eq_rops_w2`): w1 ∝ |(a_2 - a_1) × (a_3 - a_1)| (twice the area;
  the normalisation by the total area does not change the frame) and
  w2 = (r - |(a_1 + a_2 + a_3) / 3|)²;
* C = Σ_τ w1 w2 C_τ (eq. `eq_rops`); x, z = the eigenvectors of its largest and smallest
  eigenvalue;
* signs (eq. `eq_rops_sign`): v flips when Σ_τ w1 w2 (a_1 + a_2 + a_3) · v < 0; y = z × x.

Invalid (identity, `valid = False`) when the keypoint has no triangle with positive weight, two
eigenvalues of C coincide (e.g. all triangles degenerate or collinear), or an input is not finite.

Cap: a ball touching more than `MAX_TRIANGLES` triangles keeps a seeded subsample of that many
(priority hashed from the seed and the face index, so the subsample is equivariant); T is the
largest count in the chunk rounded up to a multiple of 64. At r = 15 mr a BR bunny ball touches
at most about 3600 triangles, so nothing is dropped there. Memory: N · T · 36 bytes per chunk
(about 130 MB for 1000 bunny keypoints); lower `chunk_size` for larger balls.

Deviations from PCL: float32 like PCL but summed in a different order; PCL reaches its LRF only
from a private member (our PCL driver reaches it through the explicit-instantiation access idiom).

References:
  Guo, Sohel, Bennamoun, Lu, Wan, "Rotational projection statistics for 3D local surface
  description and object recognition", IJCV 105(1), 2013, section 3.1. PCL 1.13
  `features/impl/rops_estimation.hpp` (`computeLRF`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.checks import validate_faces
from lrf_jax.search import engine
from lrf_jax.geometry import mesh
from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.host_path import BallKernel
from lrf_jax.frames.spec import TRIANGLE, TRIANGLE_MASK, MethodSpec
from lrf_jax.geometry.ops import sanitize
from lrf_jax.search.neighborhoods import Patches, hash_priority
from lrf_jax.geometry.normals import cache_last

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

MAX_TRIANGLES = 8192
_T_MULTIPLE = 64


def vertex_faces(faces: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
  """CSR map vertex -> incident faces: (ptr (n + 1,), face ids)."""
  flat = faces.reshape(-1)
  order = np.argsort(flat, kind="stable")
  ptr = np.zeros(n_points + 1, np.int64)
  ptr[1:] = np.cumsum(np.bincount(flat, minlength=n_points))
  return ptr, (order // 3).astype(np.int64)


def gather_triangles(points: np.ndarray, keypoints: np.ndarray, faces: np.ndarray, radius: float,
                     *, patches: Patches | None = None, cap: int = MAX_TRIANGLES,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """The triangles with at least one vertex within `radius` of each keypoint, padded.

  Args:
    points: (n, 3) vertices.
    keypoints: (N,) vertex indices.
    faces: (f, 3) triangles.
    radius: r (cloud units).
    patches: the keypoints' `Patches` at radius r; their neighbor lists are reused when they are
      complete (no subsample), else the ball is searched again.
    cap: the most triangles kept per keypoint.
    seed: seed of the subsample beyond `cap`.

  Returns:
    (tri, mask, face_ids): tri (N, T, 3, 3) float32 vertex offsets q - p, zeros in padding;
    mask (N, T) bool; face_ids (N, T) int64, -1 in padding.
  """
  pts = np.asarray(points, np.float64)
  kp = np.asarray(keypoints, np.int64)
  f = validate_faces(faces, pts.shape[0])
  m = kp.shape[0]
  ptr, vf = cache_last("vertex_faces", (f, pts.shape[0]), lambda: vertex_faces(f, pts.shape[0]))
  if patches is not None and np.all(np.asarray(patches.count) <= np.asarray(patches.mask).sum(1)):
    idx = np.asarray(patches.indices)
    have = idx >= 0
    ball_ptr = np.zeros(m + 1, np.int64)
    np.cumsum(have.sum(1), out=ball_ptr[1:])
    ball = idx[have].astype(np.int64)  # row-major: the rows' neighbors in order
  else:
    grid = cache_last("grid", (pts, float(radius)), lambda: engine.Grid(pts, radius / 3))
    ball_ptr, ball = engine.ball_lists(grid, pts[kp], radius)
  # Every face touching a ball vertex, once per keypoint, sorted by face index (compiled).
  face_ptr, t_id = mesh.incident_faces(ball_ptr, ball, ptr, vf, f.shape[0])
  counts = np.diff(face_ptr)
  starts = face_ptr[:-1]
  r_t = np.repeat(np.arange(m), counts)
  if m and counts.max() > cap:  # seeded subsample: keep the `cap` faces of smallest priority
    order = np.lexsort((hash_priority(seed, t_id), r_t))
    r_t, t_id = r_t[order], t_id[order]
  rank = np.arange(r_t.size) - starts[r_t]
  keep = rank < cap
  rr, slot, tt = r_t[keep], rank[keep], t_id[keep]
  width = int(min(max(int(counts.max()) if m else 1, 1), cap))
  width = -(-width // _T_MULTIPLE) * _T_MULTIPLE
  return mesh.fill_triangles(pts, f, pts[kp], rr, slot, tt, width)


class TriangleExtra(NamedTuple):
  """`extra` of RoPS: the triangles of each keypoint's support."""

  tri: AnyArray       # (N, T, 3, 3) float32 vertex offsets from the keypoint
  tri_mask: AnyArray  # (N, T) bool, False in padding
  # A class attribute, not a field: mypy takes it for a field (hence the ignores here and on
  # the constructor calls).
  AXES = {"tri": TRIANGLE, "tri_mask": TRIANGLE_MASK}  # type: ignore[misc]


def prepare_triangles(points, keypoints, patches, *, faces=None, normals=None,
                      radius: float) -> TriangleExtra:
  """`MethodSpec.prepare` hook of RoPS (host, numpy): its `TriangleExtra`."""
  del normals
  if faces is None:
    raise ValueError("rops needs a triangle mesh: pass faces=(f, 3) indices")
  tri, mask, _ = gather_triangles(points, keypoints, faces, radius, patches=patches)
  return TriangleExtra(tri, mask)  # type: ignore[call-arg]  # AXES is no field


def rops_frame(tri: jax.Array, tri_mask: AnyArray, radius: jax.Array):
  """RoPS frame of one keypoint.

  Args:
    tri: (T, 3, 3) triangle vertex offsets q - p (cloud units), finite.
    tri_mask: (T,) bool, real triangles.
    radius: () support radius r.

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool).
  """
  a1, a2, a3 = tri[:, 0], tri[:, 1], tri[:, 2]
  w1 = geometry.safe_norm(jnp.cross(a2 - a1, a3 - a1))
  s = a1 + a2 + a3
  w2 = (radius - geometry.safe_norm(s / 3.0)) ** 2
  w = jnp.where(tri_mask, w1 * w2, 0.0)
  wsum = jnp.sum(w)
  # Σ_τ w_τ C_τ without materialising the (T, 3, 3) per-triangle scatters.
  cov = (jnp.einsum("t,ti,tj->ij", w, s, s) + jnp.einsum("t,tvi,tvj->ij", w, tri, tri)) / 12.0
  cov = cov / jnp.where(wsum > 0, wsum, 1.0)
  _, evecs, ok = geometry.eigen_frame(cov)
  x = geometry.disambiguate_sign(evecs[0], s, w)
  z = geometry.disambiguate_sign(evecs[2], s, w)
  frame, f_ok = geometry.frame_from_zx(z, x)
  valid = ok & f_ok & (wsum > 0)
  return geometry.identity_where_invalid(frame, valid), valid


def rops_frames(patches: Patches, tri: AnyArray,
                tri_mask: AnyArray) -> tuple[jax.Array, jax.Array]:
  """RoPS frames for a batch (pure, jittable).

  Args:
    patches: `Patches` (only the radius is used).
    tri: (N, T, 3, 3) triangle vertex offsets from `gather_triangles`.
    tri_mask: (N, T) bool.

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  _, finite = sanitize(patches)
  tri_ok = jnp.all(jnp.isfinite(tri), axis=(-1, -2))
  finite = finite & jnp.all(tri_ok | ~tri_mask, axis=-1)
  tri = jnp.where(tri_ok[..., None, None], tri, 0.0)
  radius = geometry.finite_or_zero(patches.radius)
  frames, valid = jax.vmap(rops_frame)(tri, tri_mask & tri_ok, radius)
  valid = valid & finite
  return geometry.identity_where_invalid(frames, valid), valid

# ------------------------------------------------------------------------------ host fast path
# The same frame on the host: the faces with a vertex in each keypoint's ball (visited from the
# engine's ball lists, each once: `host_geometry.owns_face`), summed in float64 one keypoint per
# thread, without padded triangles and without the `MAX_TRIANGLES` subsample: `compute_frames`'
# default on the CPU.


@nb.njit(parallel=True, cache=True)
def _rops_host_kernel(points, centers, ptr, ball, r, faces, vf_ptr, vf, eps, frames, valid):
  r2 = r * r
  for i in nb.prange(centers.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    cov = np.zeros((3, 3))
    ssum = np.zeros(3)  # Σ w s, for the signs
    wsum = 0.0
    cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
    for e in range(start, stop):
      v = ball[e]
      for q in range(vf_ptr[v], vf_ptr[v + 1]):
        k = vf[q]
        if not hg.owns_face(points, faces, k, v, centers[i], r2):
          continue
        i0, i1, i2 = faces[k, 0], faces[k, 1], faces[k, 2]
        a0 = points[i0, 0] - cx
        a1 = points[i0, 1] - cy
        a2 = points[i0, 2] - cz
        b0 = points[i1, 0] - cx
        b1 = points[i1, 1] - cy
        b2 = points[i1, 2] - cz
        c0 = points[i2, 0] - cx
        c1 = points[i2, 1] - cy
        c2 = points[i2, 2] - cz
        e10, e11, e12 = b0 - a0, b1 - a1, b2 - a2
        e20, e21, e22 = c0 - a0, c1 - a1, c2 - a2
        nx = e11 * e22 - e12 * e21
        ny = e12 * e20 - e10 * e22
        nz = e10 * e21 - e11 * e20
        w1 = np.sqrt(nx * nx + ny * ny + nz * nz)
        s0, s1, s2 = a0 + b0 + c0, a1 + b1 + c1, a2 + b2 + c2
        w = w1 * (r - np.sqrt(s0 * s0 + s1 * s1 + s2 * s2) / 3.0) ** 2
        if w == 0.0:
          continue
        wsum += w
        ssum[0] += w * s0
        ssum[1] += w * s1
        ssum[2] += w * s2
        cov[0, 0] += w * (s0 * s0 + a0 * a0 + b0 * b0 + c0 * c0)
        cov[0, 1] += w * (s0 * s1 + a0 * a1 + b0 * b1 + c0 * c1)
        cov[0, 2] += w * (s0 * s2 + a0 * a2 + b0 * b2 + c0 * c2)
        cov[1, 1] += w * (s1 * s1 + a1 * a1 + b1 * b1 + c1 * c1)
        cov[1, 2] += w * (s1 * s2 + a1 * a2 + b1 * b2 + c1 * c2)
        cov[2, 2] += w * (s2 * s2 + a2 * a2 + b2 * b2 + c2 * c2)
    if not wsum > 0.0:
      continue
    cov[1, 0], cov[2, 0], cov[2, 1] = cov[0, 1], cov[0, 2], cov[1, 2]
    evals, evecs = np.linalg.eigh(cov / (12.0 * wsum))
    if not hg.full_spectrum_ok(evals, eps):
      continue
    x = evecs[:, 2].copy()
    z = evecs[:, 0].copy()
    if ssum[0] * x[0] + ssum[1] * x[1] + ssum[2] * x[2] < 0.0:
      x = -x
    if ssum[0] * z[0] + ssum[1] * z[1] + ssum[2] * z[2] < 0.0:
      z = -z
    hg.write_frame(frames, valid, i, z, x)


def host_mesh(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """What the host kernel reads of the mesh (`BallKernel.mesh`): (faces (f, 3) int64, ptr
  (n + 1,), face ids), the checked triangles and the vertex -> faces map (`vertex_faces`, kept
  for the last mesh seen)."""
  f = validate_faces(faces, points.shape[0])
  vptr, vf = cache_last("vertex_faces", (f, points.shape[0]),
                        lambda: vertex_faces(f, points.shape[0]))
  return np.ascontiguousarray(f), vptr, vf


# ------------------------------------------------------------------------------ registry entry

def _rops(patches: Patches, extra: TriangleExtra):
  return rops_frames(patches, extra.tri, extra.tri_mask)


SPEC = MethodSpec(
    "rops", _rops, default_k=None, needs_mesh=True, prepare=prepare_triangles,
    extra=TriangleExtra,
    host_frames=BallKernel(_rops_host_kernel, ("radius", "mesh"), (hg.EPS,), mesh=host_mesh),
    description="RoPS (Guo et al. 2013): area- and distance-weighted triangle scatter (PCL); "
                "needs a mesh")
