"""Nuisances of the robustness experiments: Gaussian noise, decimation, rotation.

Pure numpy, seeded explicitly (`seed` is an int or a `np.random.Generator`). The `with_*`
functions apply a nuisance to a Pair's scene and keep the noise-free model's mr: mr is never
recomputed on a noisy or decimated copy, so one absolute support radius serves both sides.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lrf_jax.extras import missing_extra
from lrf_jax.datasets.pair import Pair, transform_points

Seed = int | np.random.Generator


def _rng(seed: Seed) -> np.random.Generator:
  return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def add_gaussian_noise(points: np.ndarray, sigma_mr: float, mr: float,
                       seed: Seed) -> np.ndarray:
  """Adds i.i.d. Gaussian noise of per-axis sigma `sigma_mr * mr` (the BR convention).

  The 3-D RMS displacement is sqrt(3) times the per-axis sigma.

  Args:
    points: (n, 3).
    sigma_mr: per-axis standard deviation in mesh resolutions (>= 0).
    mr: the mesh resolution in the points' units (of the noise-free model).
    seed: int seed or Generator.

  Returns:
    (n, 3) float64 noisy copy.
  """
  if sigma_mr < 0 or not mr > 0:
    raise ValueError(f"add_gaussian_noise: expected sigma_mr >= 0 and mr > 0, found "
                     f"sigma_mr={sigma_mr}, mr={mr}")
  pts = np.asarray(points, dtype=np.float64)
  return pts + _rng(seed).normal(0.0, sigma_mr * mr, size=pts.shape)


class Decimation(NamedTuple):
  """Result of `decimate`.

  Attributes:
    points: (k, 3) float64 points of the decimated mesh or cloud.
    faces: (g, 3) int64 triangles (meshes) or None (clouds).
    kept: (k,) int64 indices into the input points for clouds (a subset), None for meshes
      (quadric decimation moves vertices; match them by ground truth + nearest neighbor).
  """

  points: np.ndarray
  faces: np.ndarray | None
  kept: np.ndarray | None


def decimate(points: np.ndarray, faces: np.ndarray | None, fraction: float,
             seed: Seed = 0) -> Decimation:
  """Reduces a mesh or cloud to `fraction` of its vertices.

  Meshes use quadric edge collapse (`fast_simplification`), which is deterministic: `seed` is
  unused. The face target is corrected up to three times so the vertex count lands within 1 %
  of the request (on open meshes vertices and faces do not shrink in proportion). Clouds are
  subsampled uniformly without replacement with `seed`.

  Args:
    points: (n, 3).
    faces: (f, 3) triangles, or None for a cloud.
    fraction: kept fraction of vertices, in (0, 1].
    seed: int seed or Generator (clouds only).

  Returns:
    Decimation(points, faces, kept).
  """
  if not 0.0 < fraction <= 1.0:
    raise ValueError(f"decimate: fraction: expected in (0, 1], found {fraction}")
  pts = np.asarray(points, dtype=np.float64)
  n = len(pts)
  if faces is None:
    kept = np.sort(_rng(seed).choice(n, size=max(1, round(fraction * n)), replace=False))
    return Decimation(pts[kept], None, kept.astype(np.int64))
  tri = np.asarray(faces, dtype=np.int64)
  if fraction == 1.0:
    return Decimation(pts.copy(), tri.copy(), None)
  wanted = fraction * n
  target = fraction * len(tri)
  # fast_simplification takes writeable C arrays only (a read-only one is a TypeError): the
  # dataset cache's frozen meshes and arrays unpickled by a Ray worker are read-only.
  pts, tri = (np.require(a, requirements=("C", "W")) for a in (pts, tri))
  try:
    import fast_simplification
  except ImportError as e:  # the [eval] extra
    raise missing_extra(e.name, "eval", "mesh decimation (datasets.decimate)") from e
  for _ in range(4):
    new_pts, new_faces = fast_simplification.simplify(pts, tri, target_count=int(round(target)))
    got = len(new_pts)
    if abs(got - wanted) <= 0.01 * wanted:
      break
    target = min(target * wanted / max(got, 1), len(tri) - 1)
  return Decimation(np.asarray(new_pts, dtype=np.float64), np.asarray(new_faces, np.int64),
                    None)


def rotation_matrix(axis: str | np.ndarray, angle_deg: float) -> np.ndarray:
  """The (3, 3) right-handed rotation by `angle_deg` about `axis` ("x", "y", "z" or a vector)."""
  if isinstance(axis, str):
    if axis not in ("x", "y", "z"):
      raise ValueError(f"axis: expected 'x', 'y', 'z' or a 3-vector, found {axis!r}")
    u = np.eye(3)["xyz".index(axis)]
  else:
    u = np.asarray(axis, dtype=np.float64)
    if u.shape != (3,) or not np.linalg.norm(u) > 0:
      raise ValueError(f"axis: expected a non-zero 3-vector, found {axis!r}")
    u = u / np.linalg.norm(u)
  a = np.deg2rad(angle_deg)
  k = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
  return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * (k @ k)  # Rodrigues


def rotate_about_axis(points: np.ndarray, angle_deg: float, axis: str | np.ndarray = "z",
                      center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
  """Rotates points by `angle_deg` about an axis through `center`.

  Args:
    points: (n, 3).
    angle_deg: angle in degrees (right-handed about the axis).
    axis: "x", "y", "z" or a (3,) direction.
    center: (3,) point on the axis; None uses the points' centroid (the cloud turns in place).

  Returns:
    (rotated (n, 3) float64, T (4, 4)) with rotated = T applied to points.
  """
  pts = np.asarray(points, dtype=np.float64)
  c = pts.mean(axis=0) if center is None else np.asarray(center, dtype=np.float64)
  r = rotation_matrix(axis, angle_deg)
  t = np.eye(4)
  t[:3, :3] = r
  t[:3, 3] = c - r @ c
  return transform_points(t, pts), t


def with_noise(pair: Pair, sigma_mr: float, seed: Seed) -> Pair:
  """The pair with Gaussian noise (per-axis sigma_mr * pair.mr) added to its scene.

  Args:
    pair: a pair.
    sigma_mr: per-axis sigma in mr.
    seed: int seed or Generator.

  Returns:
    A new Pair (same mr, correspondence, transform); meta records the added noise.
  """
  noisy = add_gaussian_noise(pair.scene_points, sigma_mr, pair.mr, seed)
  added = pair.meta.get("added_noise_mr", 0.0)
  return pair.replace(name=f"{pair.name}+noise{sigma_mr}", scene_points=noisy,
                      meta={"added_noise_mr": float(np.hypot(added, sigma_mr))})


def with_decimation(pair: Pair, fraction: float, seed: Seed = 0) -> Pair:
  """The pair with its scene decimated to `fraction` of its vertices.

  Args:
    pair: a pair.
    fraction: kept vertex fraction (e.g. 1/2, 1/4, 1/8, 1/16).
    seed: subsampling seed for a cloud scene (meshes decimate deterministically).

  Returns:
    A new Pair with correspondence "nearest" (decimated vertices move), the same mr and
    transform; meta records the fraction.
  """
  dec = decimate(pair.scene_points, pair.scene_faces, fraction, seed)
  return pair.replace(name=f"{pair.name}+decimate{fraction:g}", scene_points=dec.points,
                      scene_faces=dec.faces, correspondence="nearest",
                      meta={"decimation": fraction,
                            "decimated_vertices": int(len(dec.points))})


def with_rotation(pair: Pair, angle_deg: float, axis: str | np.ndarray = "z") -> Pair:
  """The pair with its scene rotated about an axis through the scene centroid.

  Args:
    pair: a pair.
    angle_deg: angle in degrees.
    axis: "x", "y", "z" or a (3,) direction.

  Returns:
    A new Pair whose transform is the rotation composed with the old ground truth.
  """
  rotated, t = rotate_about_axis(pair.scene_points, angle_deg, axis)
  vp = pair.scene_viewpoint
  return pair.replace(scene_viewpoint=None if vp is None else transform_points(t, vp[None])[0],
                      name=f"{pair.name}+rot{angle_deg:g}{axis if isinstance(axis, str) else ''}",
                      scene_points=rotated, transform=t @ pair.transform,
                      meta={"rotation_deg": angle_deg})


def random_rigid_motion(seed: Seed, scale: float = 1.0) -> np.ndarray:
  """A seeded random rigid motion: a rotation uniform on SO(3) (a normalised Gaussian
  quaternion) and a translation with per-axis sigma `scale`.

  Args:
    seed: int seed or Generator.
    scale: standard deviation of each translation component (cloud units).

  Returns:
    (4, 4) float64 [R t; 0 0 0 1], det R = +1.
  """
  rng = _rng(seed)
  q = rng.normal(size=4)
  w, x, y, z = q / np.linalg.norm(q)
  t = np.eye(4)
  t[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
               [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
               [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
  t[:3, 3] = rng.normal(size=3) * scale
  return t


def with_random_motion(pair: Pair, seed: Seed) -> Pair:
  """The pair with its model and its scene each moved by its own seeded random rigid motion
  (`random_rigid_motion`, translations on the scale of the cloud's extent), so that nothing can
  lean on a sensor position hidden in a file's origin or axes (range scans are stored in scanner
  coordinates). Viewpoints move with their clouds; the ground truth becomes
  T_scene · transform · T_model⁻¹; mr, faces and correspondences are unchanged.

  Args:
    pair: a pair.
    seed: int seed or Generator (two motions are drawn from it: model, then scene).

  Returns:
    A new Pair; meta records the two motions under "motion".
  """
  rng = _rng(seed)
  extent = float(np.ptp(pair.model_points, axis=0).max()) if len(pair.model_points) else 1.0
  tm, ts = random_rigid_motion(rng, extent), random_rigid_motion(rng, extent)

  def moved(t, vp):
    return None if vp is None else transform_points(t, vp[None])[0]

  return pair.replace(model_points=transform_points(tm, pair.model_points),
                      scene_points=transform_points(ts, pair.scene_points),
                      transform=ts @ pair.transform @ np.linalg.inv(tm),
                      model_viewpoint=moved(tm, pair.model_viewpoint),
                      scene_viewpoint=moved(ts, pair.scene_viewpoint),
                      meta={"motion": {"model": tm.tolist(), "scene": ts.tolist()}})


def points_only(pair: Pair) -> Pair:
  """The pair as bare clouds: faces and sensor positions dropped (mr, the ground truth and the
  correspondences kept), what a user holding only the points has."""
  return pair.replace(model_faces=None, scene_faces=None, model_viewpoint=None,
                      scene_viewpoint=None, meta={"points_only": True})
