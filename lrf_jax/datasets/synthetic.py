"""A procedural demo dataset that ships as code: no download, deterministic given a seed.

Closed, detailed triangle meshes (about 33k-41k vertices): a sphere ("blob") or a torus whose
surface is pushed along its normal by a sum of random plane waves of many frequencies, from
shape-scale undulations down to bumps the size of a 15 mr support. A pair is such a model and
a scene = the model under a random rigid pose, optionally seen from one viewpoint (hidden point
removal and back-face culling keep the vertices visible from it: a partial view with
self-occlusion) and noisy.
Units are arbitrary (radius about 1); mr is the model's mean edge length.
"""

from __future__ import annotations

import functools
from typing import Any, Literal

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from lrf_jax.datasets.nuisances import add_gaussian_noise
from lrf_jax.datasets.pair import Pair, transform_points
from lrf_jax.geometry.resolution import mesh_resolution

Shape = Literal["blob", "torus"]
SHAPES: tuple[Shape, ...] = ("blob", "torus")


@functools.lru_cache(maxsize=8)
def icosphere(level: int = 6) -> tuple[np.ndarray, np.ndarray]:
  """A unit icosphere: 10 * 4**level + 2 vertices (level 6: 40,962), 20 * 4**level faces.

  Returns:
    (points (n, 3) float64 on the unit sphere, faces (f, 3) int64, outward-oriented);
    read-only (cached).
  """
  g = (1 + 5 ** 0.5) / 2
  v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]],
               dtype=np.float64)
  f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                [8, 6, 7], [9, 8, 1]], dtype=np.int64)
  v /= np.linalg.norm(v, axis=1, keepdims=True)
  for _ in range(level):
    edges = np.sort(f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = v[uniq[:, 0]] + v[uniq[:, 1]]
    v = np.concatenate([v, mid / np.linalg.norm(mid, axis=1, keepdims=True)])
    ab, bc, ca = (len(v) - len(uniq) + inverse.reshape(-1, 3)).T
    a, b, c = f.T
    f = np.concatenate([np.stack(t, axis=1) for t in
                        ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
  v.flags.writeable = False
  f.flags.writeable = False
  return v, f


def torus(n_major: int = 256, n_minor: int = 128, major: float = 1.0,
          minor: float = 0.4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """A closed torus grid mesh about the z axis.

  Returns:
    (points (n_major * n_minor, 3), faces (2 * n, 3) int64 outward-oriented,
    normals (n, 3) unit outward normals).
  """
  u = 2 * np.pi * np.arange(n_major) / n_major
  w = 2 * np.pi * np.arange(n_minor) / n_minor
  uu, ww = (a.ravel() for a in np.meshgrid(u, w, indexing="ij"))
  normals = np.stack([np.cos(ww) * np.cos(uu), np.cos(ww) * np.sin(uu), np.sin(ww)], axis=1)
  centre = np.stack([major * np.cos(uu), major * np.sin(uu), np.zeros_like(uu)], axis=1)
  points = centre + minor * normals
  i, j = (a.ravel() for a in np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij"))
  idx = lambda a, b: (a % n_major) * n_minor + (b % n_minor)  # noqa: E731
  q00, q10, q11, q01 = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
  faces = np.concatenate([np.stack([q00, q10, q11], 1), np.stack([q00, q11, q01], 1)])
  return points, faces.astype(np.int64), normals


def bump_field(points: np.ndarray, rng: np.random.Generator, *, n_waves: int = 32,
               min_freq: float = 2.0, max_freq: float = 24.0,
               slope: float = 0.12) -> np.ndarray:
  """A smooth random height field: sum of plane waves a_k sin(f_k d_k·x + phi_k).

  Frequencies are log-uniform in [min_freq, max_freq] (radians per unit length); each wave's
  amplitude is slope * s_k / f_k (s_k uniform in [0.3, 1]), so every band adds similar slope.

  Args:
    points: (n, 3) positions where the field is evaluated.
    rng: the Generator.
    n_waves: number of plane waves.
    min_freq: lowest frequency.
    max_freq: highest frequency.
    slope: slope scale of one wave.

  Returns:
    (n,) heights.
  """
  freq = np.exp(rng.uniform(np.log(min_freq), np.log(max_freq), n_waves))
  direction = rng.normal(size=(n_waves, 3))
  direction /= np.linalg.norm(direction, axis=1, keepdims=True)
  phase = rng.uniform(0, 2 * np.pi, n_waves)
  amp = slope * rng.uniform(0.3, 1.0, n_waves) / freq
  return np.sin((points @ direction.T) * freq + phase) @ amp


def make_demo_mesh(shape: Shape = "blob", seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """A closed, detailed synthetic surface.

  Args:
    shape: "blob" (bumpy sphere, 40,962 vertices) or "torus" (bumpy torus, 32,768 vertices).
    seed: seed of the bump field.

  Returns:
    (points (n, 3) float64, faces (f, 3) int64).
  """
  rng = np.random.default_rng(seed)
  if shape == "blob":
    base, faces = icosphere(6)
    normals = base
    height = bump_field(base, rng, slope=0.12)
  elif shape == "torus":
    base, faces, normals = torus()
    height = bump_field(base, rng, min_freq=4.0, max_freq=32.0, slope=0.1)
  else:
    raise ValueError(f"shape: expected one of {SHAPES}, found {shape!r}")
  return base + height[:, None] * normals, np.array(faces)


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """Area-weighted vertex normals of a triangle mesh.

  Args:
    points: (n, 3).
    faces: (f, 3) triangles (orientation sets the normals' side).

  Returns:
    (n, 3) unit normals (zero for vertices in no face).
  """
  tri = points[faces]
  face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
  normals = np.zeros_like(points, dtype=np.float64)
  for k in range(3):
    np.add.at(normals, faces[:, k], face_normals)
  length = np.linalg.norm(normals, axis=1, keepdims=True)
  return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def hidden_point_removal(points: np.ndarray, viewpoint: np.ndarray,
                         radius_exponent: float = 3.0) -> np.ndarray:
  """Points visible from `viewpoint` (Katz, Tal, Basri, "Direct visibility of point sets",
  SIGGRAPH 2007): spherical flip about the viewpoint, then the convex hull.

  On the demo meshes (exponent 3, followed by back-face culling in `make_demo_pair`) no kept
  vertex is occluded (ray casting in the tests) and 0-7 % of the visible front-facing vertices
  are dropped, in concave folds: like a scanner's holes.

  Args:
    points: (n, 3).
    viewpoint: (3,) camera position.
    radius_exponent: the flip radius is max distance * 10**radius_exponent (larger keeps
      more points; 3 removes self-occluded parts while keeping the visible surface dense).

  Returns:
    (n,) bool mask of visible points.
  """
  rel = np.asarray(points, dtype=np.float64) - np.asarray(viewpoint, dtype=np.float64)
  dist = np.linalg.norm(rel, axis=1, keepdims=True)
  radius = dist.max() * 10.0 ** radius_exponent
  flipped = rel + 2 * (radius - dist) * rel / dist
  hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))
  mask = np.zeros(len(rel) + 1, dtype=bool)
  mask[hull.vertices] = True
  return mask[:-1]


def make_demo_pair(index: int = 0, *, seed: int = 0, noise_mr: float = 0.0,
                   partial: bool = True, shape: Shape | None = None,
                   view_distance: float = 4.0) -> Pair:
  """One demo pair: a synthetic model and its posed, optionally partial and noisy, scene.

  Everything is drawn from `np.random.default_rng([seed, index])`: the same arguments give
  the same pair.

  Args:
    index: pair number (also picks the shape when `shape` is None: even blob, odd torus).
    seed: dataset seed.
    noise_mr: per-axis Gaussian noise added to the scene, in mr.
    partial: keep only the scene vertices visible from a random viewpoint.
    shape: force "blob" or "torus".
    view_distance: viewpoint distance from the scene centroid (model radius about 1).

  Returns:
    Pair (dataset "demo") with index correspondence for full scenes and "nearest" for
    partial ones; meta holds shape, seed, index, noise, viewpoint, visible fraction and
    `scene_vertex_ids` (the model vertex of each scene vertex).
  """
  rng = np.random.default_rng([seed, index])
  shape = shape or SHAPES[index % 2]
  points, faces = make_demo_mesh(shape, int(rng.integers(2**31)))
  mr, definition = mesh_resolution(points, faces)
  transform = np.eye(4)
  transform[:3, :3] = Rotation.random(random_state=rng).as_matrix()
  transform[:3, 3] = rng.normal(0.0, 1.0, 3)
  scene = transform_points(transform, points)
  ids = np.arange(len(points))
  scene_faces = faces
  scene_viewpoint = None
  meta: dict[str, Any] = {"shape": shape, "seed": seed, "index": index, "noise_mr": noise_mr,
          "synthetic": True, "units": "arbitrary (radius ~1)"}
  if partial:
    direction = rng.normal(size=3)
    viewpoint = scene.mean(axis=0) + view_distance * direction / np.linalg.norm(direction)
    # Hidden point removal, then back-face culling: a scanner sees no surface facing away,
    # and culling removes the silhouette vertices HPR keeps behind small bumps.
    facing = np.einsum("ij,ij->i", vertex_normals(scene, faces), viewpoint - scene) > 0
    visible = hidden_point_removal(scene, viewpoint) & facing
    ids = np.flatnonzero(visible)
    remap = np.full(len(points), -1)
    remap[ids] = np.arange(len(ids))
    scene_faces = remap[faces[visible[faces].all(axis=1)]]
    scene = scene[ids]
    meta.update(viewpoint=viewpoint, visible_fraction=len(ids) / len(points))
    scene_viewpoint = viewpoint
  if noise_mr > 0:
    scene = add_gaussian_noise(scene, noise_mr, mr, rng)
  meta["scene_vertex_ids"] = ids
  return Pair(name=f"demo{index}/{shape}", dataset="demo", model_points=points,
              scene_points=scene, model_faces=faces, scene_faces=scene_faces,
              transform=transform, mr=mr, mr_definition=definition,
              correspondence="nearest" if partial else "index", meta=meta,
              scene_viewpoint=scene_viewpoint)


def load_demo(n_pairs: int = 4, *, seed: int = 0, noise_mr: float = 0.0,
              partial: bool = True) -> list[Pair]:
  """`n_pairs` demo pairs (`make_demo_pair(i, ...)` for i < n_pairs)."""
  return [make_demo_pair(i, seed=seed, noise_mr=noise_mr, partial=partial)
          for i in range(n_pairs)]


def street_quads(period: float = 4.0, *, length: float = 80.0, both_sides: bool = True,
                 pole_period: float | None = None) -> np.ndarray:
  """The surfaces of a synthetic street as parallelograms (origin, edge u, edge v): a ground
  plane 20 m wide, a 10 m facade at y = 8 m (and y = -8 m with `both_sides`) with two floors of
  1.5 m window frames standing 0.3 m out every `period` m, and with `pole_period` 0.2 m square
  poles 6 m tall at y = 6 m every `pole_period` m. Metres.

  Returns:
    (q, 3, 3) float64: q parallelograms' origin, u and v.
  """
  half = length / 2
  quads = [((-half, -10.0, 0.0), (length, 0.0, 0.0), (0.0, 20.0, 0.0))]
  for y, out in ((8.0, -0.3), (-8.0, 0.3))[:2 if both_sides else 1]:
    quads.append(((-half, y, 0.0), (length, 0.0, 0.0), (0.0, 0.0, 10.0)))
    for x in np.arange(-half + 1.0, half - 1.5, period):
      for z in (1.0, 5.0):
        quads += [((x, y + out, z), (1.5, 0, 0), (0, 0, 1.5)),  # front, bottom, top, sides
                  ((x, y, z), (1.5, 0, 0), (0, out, 0)),
                  ((x, y, z + 1.5), (1.5, 0, 0), (0, out, 0)),
                  ((x, y, z), (0, out, 0), (0, 0, 1.5)),
                  ((x + 1.5, y, z), (0, out, 0), (0, 0, 1.5))]
  if pole_period:
    edges = [np.array(e, float) for e in ((0.2, 0, 0), (0, 0.2, 0), (-0.2, 0, 0), (0, -0.2, 0))]
    for x in np.arange(-half + 3.0, half, pole_period):
      corner = np.array([x, 6.0, 0.0])
      for e in edges:
        quads.append((tuple(corner), tuple(e), (0.0, 0.0, 6.0)))
        corner = corner + e
  return np.array(quads, np.float64)


def lidar_sample(quads: np.ndarray, sensor: np.ndarray, n_points: int,
                 rng: np.random.Generator, *, max_range: float = 40.0,
                 noise: float = 0.01) -> np.ndarray:
  """Up to `n_points` points of the parallelograms as a spinning LiDAR at `sensor` samples them:
  density falling as 1 / r² beyond 3 m, nothing beyond `max_range`, Gaussian noise of `noise`
  per axis (no occlusion). In the sensor's frame (its position subtracted); metres.

  Returns:
    (m, 3) float64, m <= n_points.
  """
  area = np.linalg.norm(np.cross(quads[:, 1], quads[:, 2]), axis=1)
  m = 40 * n_points
  k = rng.choice(len(quads), m, p=area / area.sum())
  uv = rng.random((m, 2))
  pts = quads[k, 0] + uv[:, :1] * quads[k, 1] + uv[:, 1:] * quads[k, 2]
  r = np.linalg.norm(pts - sensor, axis=1)
  keep = (rng.random(m) < np.minimum(1.0, (3.0 / np.maximum(r, 0.5)) ** 2)) & (r < max_range)
  pts = pts[keep][:n_points] - sensor
  return pts + rng.normal(0.0, noise, pts.shape)


def make_street_pair(period: float = 4.0, shift: float = 4.0, *, both_sides: bool = True,
                     pole_period: float | None = None, n_points: int = 60_000,
                     seed: int = 0) -> Pair:
  """Two LiDAR sweeps of a street with repeating facades (`street_quads`, `lidar_sample`): the
  model from a sensor at (0, 0, 1.7) m, the scene from one `shift` m further along x. With the
  shift a multiple of `period` and no poles, a pose a period off explains the facades as well as
  the true one: a case where a verdict must not claim a wrong pose.

  Returns:
    Pair (dataset "demo"), each cloud in its sensor's frame (viewpoints at the origin); the
    transform maps the model onto the scene (a translation by -shift along x); mr the model's
    mean spacing; meta holds the arguments.
  """
  rng = np.random.default_rng([seed, 7])
  quads = street_quads(period, both_sides=both_sides, pole_period=pole_period)
  model = lidar_sample(quads, np.array([0.0, 0.0, 1.7]), n_points, rng)
  scene = lidar_sample(quads, np.array([shift, 0.0, 1.7]), n_points, rng)
  transform = np.eye(4)
  transform[0, 3] = -float(shift)
  mr, definition = mesh_resolution(model)
  return Pair(name=f"street/period{period:g}_shift{shift:g}", dataset="demo", model_points=model,
              scene_points=scene, model_faces=None, scene_faces=None, transform=transform, mr=mr,
              mr_definition=definition, correspondence="nearest",
              meta={"period": period, "shift": shift, "both_sides": both_sides,
                    "pole_period": pole_period, "seed": seed, "synthetic": True,
                    "units": "metres"},
              model_viewpoint=np.zeros(3), scene_viewpoint=np.zeros(3))
