"""`Pair`: one model/scene pair with its ground truth, the unit every dataset yields.

Also the repeatability protocol's keypoint sampling (paper section 3: 1000 random model points
per pair, their scene correspondences by ground truth, within 0.5 mr for partial scans).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

Correspondence = Literal["index", "nearest"]


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
  """Applies a (4, 4) rigid transform to points: R p + t.

  Args:
    transform: (4, 4) matrix [R t; 0 0 0 1].
    points: (n, 3).

  Returns:
    (n, 3) float64 transformed points.
  """
  t = np.asarray(transform, dtype=np.float64)
  return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


@dataclasses.dataclass(frozen=True, eq=False)
class Pair:
  """A model and a scene related by a known rigid transform.

  Attributes:
    name: unique name within the dataset, e.g. "Scene3/noise0.3".
    dataset: "BR", "UWAOR", "UWA3M", "bunny" or "demo".
    model_points: (n, 3) float64 (dataset units: metres for BR/bunny, mm for UWA).
    scene_points: (m, 3) float64, same units.
    model_faces: (f, 3) int64 or None.
    scene_faces: (g, 3) int64 or None.
    transform: (4, 4) float64 ground truth mapping model points into the scene:
      scene ≈ R · model + t.
    mr: mesh resolution of the *noise-free model*, in dataset units; nuisances keep it.
    mr_definition: "mean_edge_length" or "mean_nn_distance" (see `mesh_resolution`).
    correspondence: "index" (scene point i corresponds to model point i) or "nearest" (by
      mapping the model point with `transform` and taking the nearest scene point).
    meta: provenance (files, noise level and source, seeds, labels of synthetic parts).
    model_viewpoint: (3,) float64 sensor position in the model's own coordinates when the model
      is a single-view scan (normals of a scan are oriented towards it, as PCL's
      `flipNormalTowardsViewpoint`), else None (a mesh or a complete model: orientation from the
      faces' winding or by propagation, see `lrf_jax.geometry.normals`).
    scene_viewpoint: (3,) the same for the scene, in the scene's coordinates.
  """

  name: str
  dataset: str
  model_points: np.ndarray
  scene_points: np.ndarray
  model_faces: np.ndarray | None
  scene_faces: np.ndarray | None
  transform: np.ndarray
  mr: float
  mr_definition: str
  correspondence: Correspondence
  meta: dict[str, Any] = dataclasses.field(default_factory=dict)
  model_viewpoint: np.ndarray | None = None
  scene_viewpoint: np.ndarray | None = None

  def __post_init__(self):
    for field in ("model_viewpoint", "scene_viewpoint"):
      v = getattr(self, field)
      if v is not None:
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (3,) or not np.isfinite(v).all():
          raise ValueError(f"Pair {self.name}: {field}: expected a finite (3,) sensor position "
                           f"or None, found {v!r}")
        object.__setattr__(self, field, v)
    if self.correspondence not in ("index", "nearest"):
      raise ValueError(f"Pair {self.name}: correspondence: expected 'index' or 'nearest', "
                       f"found {self.correspondence!r}")
    for field in ("model_points", "scene_points"):
      a = getattr(self, field)
      if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"Pair {self.name}: {field}: expected (n, 3), found {a.shape}")
    if self.transform.shape != (4, 4):
      raise ValueError(f"Pair {self.name}: transform: expected (4, 4), found "
                       f"{self.transform.shape}")
    if self.correspondence == "index" and len(self.model_points) != len(self.scene_points):
      raise ValueError(f"Pair {self.name}: correspondence 'index' needs equal point counts, "
                       f"found model {len(self.model_points)} vs scene {len(self.scene_points)}")
    if not self.mr > 0:
      raise ValueError(f"Pair {self.name}: mr: expected > 0, found {self.mr}")

  @property
  def rotation(self) -> np.ndarray:
    """(3, 3) rotation part of `transform`."""
    return self.transform[:3, :3]

  @property
  def translation(self) -> np.ndarray:
    """(3,) translation part of `transform`."""
    return self.transform[:3, 3]

  def model_in_scene(self) -> np.ndarray:
    """(n, 3) the model points mapped into the scene frame by the ground truth."""
    return transform_points(self.transform, self.model_points)

  def replace(self, **changes: Any) -> Pair:
    """A copy with some fields replaced (`dataclasses.replace`); `meta` is merged, not replaced."""
    if "meta" in changes:
      changes["meta"] = {**self.meta, **changes["meta"]}
    return dataclasses.replace(self, **changes)


def repeatability_keypoints(pair: Pair, n: int = 1000, seed: int = 0,
                            max_dist_mr: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """Seeded model keypoints and their scene correspondences (the repeatability protocol).

  With index correspondence the model indices are `rng.choice(n_model, n)` for
  `rng = np.random.default_rng(seed)`: they depend only on (seed, n, n_model), so every scene
  and noise level of a BR model shares the same keypoints. With nearest correspondence each
  model point is mapped by the ground truth; it is eligible when a scene point lies within
  `max_dist_mr * pair.mr` (partial scans), and n eligible points are drawn the same way.

  Args:
    pair: the pair.
    n: keypoints wanted; fewer come back when fewer are eligible.
    seed: the sampling seed.
    max_dist_mr: the eligibility distance in mr (nearest correspondence only).

  Returns:
    (model_idx, scene_idx): (k,) int64 each, k = min(n, eligible), model_idx sorted
    ascending; scene_idx[i] is the scene point corresponding to model point model_idx[i].
  """
  if pair.correspondence == "index":
    eligible = np.arange(len(pair.model_points))
    match = eligible
  else:
    dist, nearest = cKDTree(pair.scene_points).query(
        pair.model_in_scene(), distance_upper_bound=max_dist_mr * pair.mr, workers=-1)
    eligible = np.flatnonzero(np.isfinite(dist))
    match = np.full(len(pair.model_points), -1, dtype=np.int64)
    match[eligible] = nearest[eligible]
  rng = np.random.default_rng(seed)
  chosen = np.sort(rng.choice(eligible, size=min(n, len(eligible)), replace=False))
  return chosen.astype(np.int64), np.asarray(match)[chosen].astype(np.int64)
