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
