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
GRID = 41  # the height field's grid: GRID x GRID points, spacing 1 (about 1 mr)


def _grid(rng: np.random.Generator, height=None) -> tuple[np.ndarray, np.ndarray]:
  """A GRID x GRID grid of spacing 1 jittered by up to 0.1 in x and y, z = height(x, y) (0
  when None), and its triangles: ((GRID**2, 3) points, (f, 3) faces), row-major (x index
  first)."""
  n = GRID
  gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
  x = gx + rng.uniform(-0.1, 0.1, gx.shape)
  y = gy + rng.uniform(-0.1, 0.1, gy.shape)
  z = np.zeros_like(x) if height is None else height(x, y)
  ids = np.arange(n * n).reshape(n, n)
  a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
  faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                          np.stack([a, c, d], -1).reshape(-1, 3)])
  return np.stack([x, y, z], -1).reshape(-1, 3), faces


def _height(x, y):
  """`synthetic_mesh`'s irregular height field (a few units of relief over the 41 x 41 grid)."""
  return 1.5 * np.sin(0.35 * x + 0.2 * y) + 0.8 * np.cos(0.3 * y - 0.15 * x) + 0.01 * x * y


def _grid_keypoints(rows, cols) -> np.ndarray:
  """Indices of the grid points at (rows x cols), row-major."""
  return np.arange(GRID * GRID).reshape(GRID, GRID)[np.ix_(rows, cols)].reshape(-1)


def _with_degenerate_parts(surface: np.ndarray, faces: np.ndarray, keypoints: np.ndarray):
  """`surface` plus, far away, a pair of points (a keypoint with one neighbor) and 30 collinear
  points with zero-area triangles (a keypoint on a collinear support): (points, faces int64,
  keypoints = `keypoints` then those two, radius 6)."""
  s = len(surface)
  pair = np.array([[500.0, 500.0, 500.0], [500.1, 500.0, 500.0]])  # too few neighbors
  direction = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
  line = np.array([-500.0, -500.0, -500.0]) + 0.5 * np.arange(30)[:, None] * direction  # collinear
  points = np.concatenate([surface, pair, line])
  l0 = s + 2
  line_faces = np.stack([l0 + np.arange(28), l0 + np.arange(1, 29), l0 + np.arange(2, 30)], -1)
  faces = np.concatenate([faces, line_faces])  # zero-area triangles along the line
  return points, faces.astype(np.int64), np.concatenate([keypoints, [s], [l0 + 15]]), 6.0


def synthetic_mesh():
  """An irregular 41 x 41 height field (radius 6) plus two degenerate far-away parts.

  Returns:
    (points, faces, keypoints, radius): the first `N_GOOD` keypoints are interior surface points,
    then a keypoint with one neighbor and one on a collinear support.
  """
  grid, faces = _grid(np.random.default_rng(3), _height)
  interior = _grid_keypoints(range(14, 27, 4), range(14, 27, 4))[:N_GOOD]
  return _with_degenerate_parts(grid, faces, interior)


# The kinds of `host_check_cloud`: every host kernel must give its jitted function's frames on
# each. "tilted_plane" is where some methods' frames are set by float rounding (see there).
HOST_CHECK_KINDS = ("smooth", "noisy", "planar", "cut", "tilted_plane")


def host_check_cloud(kind: str):
  """A procedural mesh of `kind` on which a method's host kernel and its jitted function must
  give the same frames: (points (n, 3) float64, faces (f, 3) int64, keypoints (14,), radius 6).

  The surface is a 41 x 41 grid (spacing 1, about 1 mr; the radius is 6 mr), its 12 keypoints
  first, then `synthetic_mesh`'s two degenerate keypoints (one neighbor; a collinear support),
  which every method must flag invalid:

  * "smooth": `synthetic_mesh` (an irregular height field, all 12 keypoints interior);
  * "noisy": that field with Gaussian noise of 0.1 grid spacings (about 0.1 mr) per axis;
  * "planar": the grid on the exact plane z = 0 (offsets exact in float32 and float64: a frame
    undefined there is invalid on both paths, e.g. TOLDI's x weights h = 0);
  * "cut": the field cut off at x = 20.5, as a scan ends: 4 keypoints on the cut, 8 within 3 mr
    of it (their balls half-empty);
  * "tilted_plane": the "planar" grid rotated: the points' heights above their plane, exactly 0,
    are float rounding (about 1e-7 r in float32, 1e-16 r in float64), so a method that reads
    their signs (a z vote, a highest point, an x weighted by h) may take any frame, and the two
    paths differ.
  """
  from lrf_jax.datasets.nuisances import add_gaussian_noise
  if kind not in HOST_CHECK_KINDS:
    raise ValueError(f"kind: expected one of {HOST_CHECK_KINDS}, got {kind!r}")
  if kind == "smooth":
    return synthetic_mesh()
  rng = np.random.default_rng(5)
  interior = _grid_keypoints(range(14, 27, 4), range(14, 27, 4))[:N_GOOD]
  if kind == "noisy":
    grid, faces = _grid(rng, _height)
    return _with_degenerate_parts(add_gaussian_noise(grid, 0.1, 1.0, rng), faces, interior)
  if kind in ("planar", "tilted_plane"):
    grid, faces = _grid(rng)
    if kind == "tilted_plane":
      grid = grid @ Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix().T
    return _with_degenerate_parts(grid, faces, interior)
  grid, faces = _grid(rng, _height)
  keep = grid[:, 0] <= 20.5  # rows 0..20 (x = row +- 0.1)
  remap = np.cumsum(keep) - 1
  kp = remap[_grid_keypoints([20, 19, 17], [5, 15, 25, 35])]
  return _with_degenerate_parts(grid[keep], remap[faces[keep[faces].all(1)]], kp)
