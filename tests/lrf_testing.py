"""Reusable assertions and fixtures-as-functions for LRF tests (e3nn-jax style helpers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def random_rotation(seed: int) -> np.ndarray:
  """A uniformly random (3, 3) rotation, seeded."""
  return Rotation.random(random_state=seed).as_matrix()


def assert_frames_orthonormal(frames, valid=None, atol=1e-5):
  """Rows orthonormal and det = +1 for every frame (invalid frames must be the identity)."""
  f = np.asarray(frames, np.float64)
  eye = np.broadcast_to(np.eye(3), f.shape)
  np.testing.assert_allclose(f @ np.swapaxes(f, -1, -2), eye, atol=atol)
  np.testing.assert_allclose(np.linalg.det(f), 1.0, atol=atol)
  assert np.isfinite(f).all()
  if valid is not None:
    v = np.asarray(valid)
    np.testing.assert_array_equal(f[~v], eye[~v])


def equivariance_deficit(frames, frames_moved, rotation, valid=None, valid_moved=None,
                         up_to_sign=False) -> np.ndarray:
  """Per-keypoint 1 - MeanCos between lrf(P)·Rᵀ and lrf(R·P + t) (0 for a perfect match).

  With `up_to_sign`, cosines are taken in absolute value (for methods whose axis signs are
  ambiguous by definition, e.g. Mian's).
  """
  f = np.asarray(frames, np.float64) @ np.asarray(rotation).T
  g = np.asarray(frames_moved, np.float64)
  cx = np.sum(f[:, 0] * g[:, 0], -1)
  cz = np.sum(f[:, 2] * g[:, 2], -1)
  if up_to_sign:
    cx, cz = np.abs(cx), np.abs(cz)
  mc = 0.5 * (cx + cz)
  if valid is not None:
    mc = np.where(np.asarray(valid) & np.asarray(valid_moved), mc, 0.0)
  return 1.0 - mc


def load_br_model(root: Path, name: str, scene: int | None = None):
  """A BR model as (points (n, 3) float64, faces (f, 3), mr, xf (4, 4) or None), with plyfile."""
  from plyfile import PlyData

  folder = Path(root) / "bologna_retrieval" / "models" / name
  ply = PlyData.read(next(folder.glob("*.ply")))
  v = ply["vertex"]
  pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
  faces = np.stack(ply["face"]["vertex_indices"]).astype(np.int64)
  e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
  e = np.unique(np.sort(e, axis=1), axis=0)
  mr = float(np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1).mean())
  xf = None
  if scene is not None:
    xf = np.loadtxt(Path(root) / "bologna_retrieval" / "scenes" / f"Scene{scene}-rs0.xf")
  return pts, faces, mr, xf


N_GOOD = 12  # interior keypoints of `synthetic_mesh`


def synthetic_mesh():
  """An irregular 41 x 41 height field (radius 6) plus two degenerate far-away parts.

  Returns:
    (points, faces, keypoints, radius): the first `N_GOOD` keypoints are interior surface points,
    then a keypoint with one neighbour and one on a collinear support.
  """
  rng = np.random.default_rng(3)
  n = 41
  gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
  x = gx + rng.uniform(-0.1, 0.1, gx.shape)
  y = gy + rng.uniform(-0.1, 0.1, gy.shape)
  z = 1.5 * np.sin(0.35 * x + 0.2 * y) + 0.8 * np.cos(0.3 * y - 0.15 * x) + 0.01 * x * y
  grid = np.stack([x, y, z], -1).reshape(-1, 3)
  ids = np.arange(n * n).reshape(n, n)
  a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
  faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                          np.stack([a, c, d], -1).reshape(-1, 3)])
  pair = np.array([[500.0, 500.0, 500.0], [500.1, 500.0, 500.0]])  # too few neighbours
  direction = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
  line = np.array([-500.0, -500.0, -500.0]) + 0.5 * np.arange(30)[:, None] * direction  # collinear
  points = np.concatenate([grid, pair, line])
  l0 = n * n + 2
  line_faces = np.stack([l0 + np.arange(28), l0 + np.arange(1, 29), l0 + np.arange(2, 30)], -1)
  faces = np.concatenate([faces, line_faces])  # zero-area triangles along the line
  interior = ids[14:27:4, 14:27:4].reshape(-1)[:12]
  keypoints = np.concatenate([interior, [n * n], [l0 + 15]])
  return points, faces.astype(np.int64), keypoints, 6.0
