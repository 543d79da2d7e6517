"""Mesh resolution (mr), the length unit of support radii and noise levels.

For a mesh, mr is the mean length of its unique edges (the Bologna convention: BR's noise sigma
is 0.1/0.3/0.5 of it). For a cloud, mr is the mean distance from each point to its nearest other
point. On the BR meshes the nearest-neighbor spacing is about 1/1.42-1/1.59 of the edge length,
so the two definitions are *not* interchangeable; every dataset records which one it used.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from lrf_jax.search import engine

MrDefinition = Literal["mean_edge_length", "mean_nn_distance"]


def unique_edges(faces: np.ndarray) -> np.ndarray:
  """The undirected edges of a triangle mesh, each once.

  Args:
    faces: (f, 3) integer vertex indices.

  Returns:
    (e, 2) int64 edges with e[:, 0] < e[:, 1], sorted.
  """
  f = np.asarray(faces, dtype=np.int64)
  e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
  e.sort(axis=1)
  e = e[e[:, 0] != e[:, 1]]  # degenerate faces contribute no zero-length edge
  n = int(f.max()) + 1 if f.size else 1
  keys = np.unique(e[:, 0] * n + e[:, 1])
  return np.stack([keys // n, keys % n], axis=1)


def mesh_resolution(points: np.ndarray, faces: np.ndarray | None = None, *,
                    name: str = "points") -> tuple[float, MrDefinition]:
  """Mesh resolution of a mesh (mean unique-edge length) or a cloud (mean NN distance).

  Args:
    points: (n, 3) coordinates, n >= 2.
    faces: (f, 3) triangles, or None for a cloud.

  Returns:
    (mr, definition): mr in the points' units, and "mean_edge_length" (mesh) or
    "mean_nn_distance" (cloud).

  Raises:
    ValueError: fewer than 2 points, an empty face array, or a cloud without spacing (mr 0:
      all points coincide, or every point has a duplicate); the message starts with `name`.
  """
  pts = np.asarray(points, dtype=np.float64)
  if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
    raise ValueError(f"points: expected an (n, 3) array with n >= 2, found shape {pts.shape}")
  if faces is not None:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
      raise ValueError(f"faces: expected a non-empty (f, 3) array, found shape {faces.shape}")
    e = unique_edges(faces)
    mr = float(np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1).mean())
    if mr == 0.0:
      raise ValueError(f"{name}: the mesh has no spacing (mean edge length 0): its edges join "
                       "coinciding vertices")
    return mr, "mean_edge_length"
  d, _ = engine.knn(engine.knn_grid(pts, 2), pts, 2)  # the point itself, then its nearest
  mr = float(d[:, 1].mean())
  if mr == 0.0:
    distinct = len(np.unique(pts, axis=0))
    what = (f"all {len(pts)} points coincide" if distinct == 1 else
            f"every point is duplicated ({distinct} distinct positions among {len(pts)} points)")
    raise ValueError(f"{name}: the cloud has no spacing (mean nearest-neighbor distance 0): "
                     f"{what}")
  return mr, "mean_nn_distance"
