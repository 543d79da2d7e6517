"""A straightforward, per-keypoint numpy implementation of LRF-Net / TOLDI / uniform frames.

It exists to check the JAX implementation formula by formula (tests) and to be the baseline of
the speed benchmark. It shares nothing with the JAX path except the definition of the seeded
subsample (`neighborhoods.hash_priority`) and the weight network's forward pass
(`weights.apply_weights` in numpy float64, itself held equal to the flax module
`networks.WeightNet` by tests/test_weights_shipped.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from lrf_jax.frames.weights import apply_weights
from lrf_jax.search.neighborhoods import hash_priority


def reference_frame(points: np.ndarray, center_index: int, radius: float, *, weights: str,
                    params: Any = None, k: int | None = 256, seed: int = 0,
                    tree: cKDTree | None = None) -> tuple[np.ndarray, bool]:
  """One frame, the slow and obvious way (float64).

  Args:
    points: (n, 3) cloud.
    center_index: keypoint index.
    radius: support radius.
    weights: "lrf_net" (needs params), "uniform", "toldi" (signed) or "toldi_unsigned".
    params: WeightNet params for "lrf_net".
    k: patch size (None = all neighbors).
    seed: subsample seed.
    tree: optional cKDTree of points.

  Returns:
    (frame (3, 3) rows x, y, z, valid).
  """
  tree = cKDTree(points) if tree is None else tree
  p = points[center_index]
  idx = np.asarray(tree.query_ball_point(p, radius), np.int64)
  off = points[idx] - p
  d = np.linalg.norm(off, axis=1)

  inner = off[d <= radius / 3.0]
  if len(inner) < 3:
    return np.eye(3), False
  mu = inner.mean(axis=0)
  cov = (inner - mu).T @ (inner - mu) / len(inner)
  evals, evecs = np.linalg.eigh(cov)
  if not evals[1] - evals[0] > 1e-6 * max(evals[2], 0.0):
    return np.eye(3), False
  z = evecs[:, 0]
  if -np.sum(inner, axis=0) @ z < 0:  # orient so that Σ (p - q_i)·z >= 0
    z = -z
  if k is not None and len(idx) > k:
    prio = hash_priority(seed, idx)
    keep = np.argsort(prio, kind="stable")[:k]
    idx, off, d = idx[keep], off[keep], d[keep]

  h = off @ z
  if weights == "lrf_net":
    cos = np.where(d > 0, h / np.where(d > 0, d, 1.0), 0.0)
    w = apply_weights(params, np.stack([d / radius, cos], axis=1), np, np.float64)
  elif weights == "uniform":
    w = np.ones(len(idx))
  elif weights == "toldi":
    w = (radius - d) ** 2 * np.sign(h) * h ** 2
  elif weights == "toldi_unsigned":
    w = (radius - d) ** 2 * h ** 2
  else:
    raise ValueError(f"weights: unknown {weights!r}")
  v = off - np.outer(h, z)
  s = (w[:, None] * v).sum(axis=0)
  if not np.linalg.norm(s) > 1e-5 * np.sum(np.abs(w) * np.linalg.norm(v, axis=1)):
    return np.eye(3), False
  x = s / np.linalg.norm(s)
  return np.stack([x, np.cross(z, x), z]), True


def reference_frames(points: np.ndarray, keypoints: np.ndarray, radius: float, *, weights: str,
                     params: Any = None, k: int | None = 256,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """`reference_frame` for every keypoint: (m, 3, 3) frames and (m,) validity."""
  points = np.asarray(points, np.float64)
  tree = cKDTree(points)
  out = [reference_frame(points, int(i), radius, weights=weights, params=params, k=k, seed=seed,
                         tree=tree) for i in keypoints]
  return np.stack([f for f, _ in out]), np.array([v for _, v in out])
