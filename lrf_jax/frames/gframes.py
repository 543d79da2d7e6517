"""GFrames (Melzi, Spezialetti, Tombari, Bronstein, Di Stefano, Rodolà 2019) on triangle meshes.

z = the keypoint's normal; x = the area-weighted mean of the gradient of a scalar function f over
the triangles within r of the keypoint, projected on the tangent plane and normalised (paper eq.
`eq_GFrame`); y = z × x. Our choices:

* f = the signed mean curvature H of the mesh (`normals.mean_curvature`: cotangent Laplacian,
  positive on convex parts), one of the functions Melzi et al. evaluate, computed once per mesh
  on the host and gathered per triangle vertex by `prepare_gframes`;
* the triangles "within distance r" are those with at least one vertex within r (as RoPS,
  `rops.gather_triangles`, same cap);
* on a triangle with vertices q_1, q_2, q_3, unit normal n and area A, f is linear and
  A ∇f = ½ Σ_i f_i n × (q_{i+2} - q_{i+1}) (indices mod 3): no division by the area, never
  NaN; the result does not depend on the vertex order or winding. A sliver (height at most
  `SLIVER_EPS` of its longest edge: its n is rounding noise) contributes nothing, so a
  support of collinear points gives no x;
* z = the keypoint normal from the `prepare` hook (the caller's `normals=`, else
  `normals.estimate_normals`: PCA over 0.2 r oriented by the faces' winding).

Invalid (identity, `valid = False`) when the keypoint normal is not finite or zero, the
projected sum vanishes (|Σ A ∇f| <= 1e-5 Σ |A ∇f|: e.g. a plane or a sphere, where H is
constant, or a support of slivers only), or an input is not finite.

References:
  Melzi et al., "GFrames: Gradient-based local reference frame for 3D shape matching", CVPR 2019,
  section 4 (eq. 3).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

from lrf_jax._jax import jax, jnp
import numba as nb
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.host_path import BallKernel
from lrf_jax.checks import validate_faces
from lrf_jax.frames.rops import gather_triangles, vertex_faces
from lrf_jax.frames.normal_based import usable_normals
from lrf_jax.frames.spec import KEYPOINT, TRIANGLE, TRIANGLE_MASK, MethodSpec
from lrf_jax.geometry.ops import sanitize
from lrf_jax.search.neighborhoods import Patches
from lrf_jax.geometry.normals import cache_last, default_normals, face_cross, mean_curvature

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

X_EPS = 1e-5
# A triangle whose height is at most this fraction of its longest edge (|cross| <= SLIVER_EPS ·
# longest edge²) has no reliable normal (float32 rounding alone gives collinear points a
# cross product ~1e-7 of it): it contributes no gradient, on both paths.
SLIVER_EPS = 1e-5


class GFramesExtra(NamedTuple):
  """`extra` of GFrames: the support's triangles, their vertices' curvature, the normal."""

  tri: AnyArray        # (N, T, 3, 3) float32 vertex offsets from the keypoint
  tri_mask: AnyArray   # (N, T) bool, False in padding
  tri_f: AnyArray      # (N, T, 3) float32 mean curvature at the vertices
  kp_normal: AnyArray  # (N, 3) float32
  # A class attribute, not a field: mypy takes it for a field (hence the ignores here and on
  # the constructor calls).
  AXES = {"tri": TRIANGLE, "tri_mask": TRIANGLE_MASK, "tri_f": TRIANGLE,  # type: ignore[misc]
          "kp_normal": KEYPOINT}


def prepare_gframes(points, keypoints, patches, *, faces=None, normals=None,
                    radius: float) -> GFramesExtra:
  """`MethodSpec.prepare` hook of GFrames (host, numpy): its `GFramesExtra`."""
  if faces is None:
    raise ValueError("gframes needs a triangle mesh: pass faces=(f, 3) indices")
  tri, mask, ids = gather_triangles(points, keypoints, faces, radius, patches=patches)
  h = mean_curvature(points, faces)
  f = np.asarray(faces, np.int64)
  tri_f = np.where(mask[..., None], h[f[np.maximum(ids, 0)]], 0.0).astype(np.float32)
  nrm = default_normals(points, radius, faces, normals)
  return GFramesExtra(tri, mask, tri_f,  # type: ignore[call-arg]  # AXES is no field
                      usable_normals(np.asarray(nrm)[np.asarray(keypoints)], np.float32))


def area_gradient(tri: jax.Array, f: jax.Array) -> jax.Array:
  """A ∇f of the linear interpolant of f on each triangle.

  Args:
    tri: (T, 3, 3) vertices (any origin).
    f: (T, 3) values at the vertices.

  Returns:
    (T, 3) area times gradient (0 for degenerate triangles).
  """
  cross = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
  longest2 = jnp.max(jnp.stack([jnp.sum((tri[:, (i + 1) % 3] - tri[:, i]) ** 2, axis=-1)
                                for i in range(3)]), axis=0)
  n, _ = geometry.safe_normalize(cross)
  n = jnp.where((geometry.safe_norm(cross) > SLIVER_EPS * longest2)[:, None], n, 0.0)
  f = f - jnp.mean(f, axis=-1, keepdims=True)  # constants have no gradient; better rounding
  out = jnp.zeros_like(tri[:, 0])
  for i in range(3):
    edge = tri[:, (i + 2) % 3] - tri[:, (i + 1) % 3]
    out = out + f[:, i:i + 1] * jnp.cross(n, edge)
  return 0.5 * out


def gframes_frame(tri, tri_mask, tri_f, kp_normal):
  """GFrames frame of one keypoint.

  Args:
    tri: (T, 3, 3) triangle vertex offsets (finite).
    tri_mask: (T,) bool.
    tri_f: (T, 3) f at the vertices (finite).
    kp_normal: (3,) keypoint normal (NaN allowed: invalid).

  Returns:
    (frame (3, 3) rows x, y, z; valid () bool).
  """
  z, z_ok = geometry.safe_normalize(geometry.finite_or_zero(kp_normal))
  z_ok = z_ok & jnp.all(jnp.isfinite(kp_normal))
  g = jnp.where(tri_mask[:, None], area_gradient(tri, tri_f), 0.0)
  s = jnp.sum(g, axis=0)
  s_t = s - jnp.dot(s, z) * z
  scale = jnp.sum(geometry.safe_norm(g))
  frame, f_ok = geometry.frame_from_zx(z, s_t)
  valid = z_ok & f_ok & (geometry.safe_norm(s_t) > X_EPS * scale)
  return geometry.identity_where_invalid(frame, valid), valid


def gframes_frames(patches: Patches, tri: AnyArray, tri_mask: AnyArray, tri_f: AnyArray,
                   kp_normal: AnyArray) -> tuple[jax.Array, jax.Array]:
  """GFrames for a batch (pure, jittable).

  Args:
    patches: `Patches` (used for input checks only).
    tri: (N, T, 3, 3) triangle vertex offsets (`rops.gather_triangles`).
    tri_mask: (N, T) bool.
    tri_f: (N, T, 3) scalar function at the vertices.
    kp_normal: (N, 3) keypoint normals.

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  _, finite = sanitize(patches)
  ok = jnp.all(jnp.isfinite(tri), axis=(-1, -2)) & jnp.all(jnp.isfinite(tri_f), axis=-1)
  finite = finite & jnp.all(ok | ~tri_mask, axis=-1)
  tri = jnp.where(ok[..., None, None], tri, 0.0)
  tri_f = jnp.where(ok[..., None], tri_f, 0.0)
  frames, valid = jax.vmap(gframes_frame)(tri, tri_mask & ok, tri_f, kp_normal)
  valid = valid & finite
  return geometry.identity_where_invalid(frames, valid), valid

# ------------------------------------------------------------------------------ host fast path
# A ∇f of a face does not depend on the keypoint (it is built from edge vectors), so the host
# path computes it once per face (and a third of it per vertex) and sums it over the faces with
# a vertex in each keypoint's ball (from the engine's ball lists), float64, without padded
# triangles and without the `MAX_TRIANGLES` subsample: `compute_frames`' default on the CPU.


@nb.njit(cache=True, error_model="numpy")  # x / 0 -> inf or nan, as numpy
def _face_gradients(pts, f, hv):
  """A ∇f (f, 3) of the vertex function hv on every face, and whether hv is finite at its
  three vertices (f,) (zero f on the others); as `area_gradient`, float64."""
  m = f.shape[0]
  g = np.zeros((m, 3))
  ok = np.empty(m, np.bool_)
  for k in range(m):
    h0, h1, h2 = hv[f[k, 0]], hv[f[k, 1]], hv[f[k, 2]]
    ok[k] = np.isfinite(h0) and np.isfinite(h1) and np.isfinite(h2)
    if not ok[k]:
      h0 = h1 = h2 = 0.0
    x, y, z = face_cross(pts, f, k)
    length = np.sqrt(x * x + y * y + z * z)
    longest2 = 0.0
    for i in range(3):
      a, b = f[k, i], f[k, (i + 1) % 3]
      e2 = ((pts[a, 0] - pts[b, 0]) ** 2 + (pts[a, 1] - pts[b, 1]) ** 2
            + (pts[a, 2] - pts[b, 2]) ** 2)
      longest2 = max(longest2, e2)
    sliver = not length > SLIVER_EPS * longest2
    nx, ny, nz = (0.0, 0.0, 0.0) if sliver else (x / length, y / length, z / length)
    mean = (h0 + h1 + h2) / 3.0
    hs = (h0 - mean, h1 - mean, h2 - mean)
    for i in range(3):
      a, b = f[k, (i + 2) % 3], f[k, (i + 1) % 3]
      ex, ey, ez = pts[a, 0] - pts[b, 0], pts[a, 1] - pts[b, 1], pts[a, 2] - pts[b, 2]
      hi = hs[i]
      g[k, 0] += hi * (ny * ez - nz * ey)
      g[k, 1] += hi * (nz * ex - nx * ez)
      g[k, 2] += hi * (nx * ey - ny * ex)
    for a in range(3):
      g[k, a] = 0.5 * g[k, a]
  return g, ok


def face_gradients(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(g (f, 3) float64 A ∇f of the mean curvature on every face, as `area_gradient`;
  ok (f,) bool: f finite at its three vertices)."""
  pts = np.ascontiguousarray(points, np.float64)
  f = np.ascontiguousarray(faces, np.int64)
  return _face_gradients(pts, f, np.ascontiguousarray(mean_curvature(pts, f)))


@nb.njit(cache=True, error_model="numpy")  # x / 0 -> inf or nan, as numpy
def _vertex_shares(pts, f, g, ok):
  n = pts.shape[0]
  gn = np.empty(f.shape[0])
  for k in range(f.shape[0]):
    gn[k] = np.sqrt(g[k, 0] * g[k, 0] + g[k, 1] * g[k, 1] + g[k, 2] * g[k, 2])
  share = np.zeros((n, 3))
  share_n = np.zeros(n)
  bad = np.zeros(n)
  edge = np.zeros(n)
  for c in range(3):  # corner by corner, each corner's faces in order
    for k in range(f.shape[0]):
      v = f[k, c]
      for a in range(3):
        share[v, a] += g[k, a]
      share_n[v] += gn[k]
      bad[v] += 0.0 if ok[k] else 1.0
      u = f[k, (c + 1) % 3]
      dx, dy, dz = pts[v, 0] - pts[u, 0], pts[v, 1] - pts[u, 1], pts[v, 2] - pts[u, 2]
      length = np.sqrt(dx * dx + dy * dy + dz * dz)
      edge[v] = max(edge[v], length)
      edge[u] = max(edge[u], length)
  for v in range(n):
    for a in range(3):
      share[v, a] /= 3.0
    share_n[v] /= 3.0
  return gn, share, share_n, bad == 0.0, edge


def vertex_shares(points: np.ndarray, faces: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """Per face: (g (f, 3) its A ∇f, |g| (f,)); per vertex: a third of the g and of the |g| of
  its faces (n, 3), (n,), whether all its faces' f is finite (n,), and its longest edge (n,)."""
  pts = np.ascontiguousarray(points, np.float64)
  f = np.ascontiguousarray(faces, np.int64)
  g, ok = face_gradients(pts, f)
  return (g,) + _vertex_shares(pts, f, g, ok)


@nb.njit(parallel=True, cache=True)
def _gframes_host_kernel(points, centers, ptr, ball, r, kp_normals, faces, vf_ptr, vf, g, gn,
                         share, share_n, v_ok, edge, x_eps, frames, valid):
  """Σ of A ∇f over the faces touching each ball: every in-ball vertex adds a third of its
  faces' (`share`), and the vertices whose faces may leave the ball correct the faces with
  c < 3 vertices inside by (1/c - 1/3) each."""
  r2 = r * r
  inner = r * (1.0 - 1e-7)
  for i in nb.prange(kp_normals.shape[0]):
    start, stop = hg.start_keypoint(frames, valid, ptr, i)
    z, z_ok = hg.unit_or_zero(kp_normals[i])
    if not z_ok:
      continue
    s0 = s1 = s2 = 0.0
    scale = 0.0
    finite = True
    for e in range(start, stop):
      v = ball[e]
      s0 += share[v, 0]
      s1 += share[v, 1]
      s2 += share[v, 2]
      scale += share_n[v]
      finite = finite and v_ok[v]
      if np.sqrt(hg.offset(points, v, centers[i])[3]) + edge[v] < inner:
        continue  # every face of v lies in the ball
      for q in range(vf_ptr[v], vf_ptr[v + 1]):
        k = vf[q]
        c = 0
        for a in range(3):
          c += 1 if hg.in_ball(points, faces[k, a], centers[i], r2) else 0
        if c < 3:
          w = 1.0 / c - 1.0 / 3.0
          s0 += w * g[k, 0]
          s1 += w * g[k, 1]
          s2 += w * g[k, 2]
          scale += w * gn[k]
    d = s0 * z[0] + s1 * z[1] + s2 * z[2]
    st = np.array([s0 - d * z[0], s1 - d * z[1], s2 - d * z[2]])
    if finite and np.sqrt(st[0] ** 2 + st[1] ** 2 + st[2] ** 2) > x_eps * scale:
      hg.write_frame(frames, valid, i, z, st)


def host_mesh(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, ...]:
  """What the host kernel reads of the mesh (`BallKernel.mesh`): the checked faces (f, 3)
  int64, the vertex -> faces map (`rops.vertex_faces`: ptr (n + 1,), face ids) and
  `vertex_shares`' six arrays, all kept for the last mesh seen (one digest of it per call)."""
  f = validate_faces(faces, points.shape[0])
  g, gn, share, share_n, v_ok, edge, vptr, vf = cache_last(
      "gframes_mesh", (points, f),
      lambda: vertex_shares(points, f) + vertex_faces(f, points.shape[0]))
  return np.ascontiguousarray(f), vptr, vf, g, gn, share, share_n, v_ok, edge


# ------------------------------------------------------------------------------ registry entry

def _gframes(patches: Patches, extra: GFramesExtra):
  return gframes_frames(patches, extra.tri, extra.tri_mask, extra.tri_f, extra.kp_normal)


SPEC = MethodSpec(
    "gframes", _gframes, default_k=None, needs_normals=True, needs_mesh=True, prepare=prepare_gframes,
    extra=GFramesExtra,
    host_frames=BallKernel(_gframes_host_kernel, ("radius", "keypoint_normals", "mesh"), (X_EPS,),
                           mesh=host_mesh),
    description="GFrames (Melzi et al. 2019): normal z, x = area-weighted mean-curvature "
                "gradient; needs a mesh")
