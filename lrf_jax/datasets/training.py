"""Training keypoints on the noise-free BR pairs (the paper trains on noise-free BR only).

A `TrainingSet` is a fixed, seeded set of keypoints over the 18 noise-free BR pairs (all 6
models). A keypoint is (pair, vertex): the same vertex index on the model side and on the scene
side (the model under the ground truth), since BR correspondences are exact by index. Patches
are built from these points by `lrf_jax.search.neighborhoods`; this module only provides the points,
the keypoints and seeded shuffled batches of keypoint indices.

Disjointness from the evaluation: for each pair, the vertices that `repeatability_keypoints`
draws for that pair with (`eval_n`, `eval_seed`) are removed from the pool before the training
keypoints are drawn. For index correspondence those vertices depend only on (eval_seed, eval_n,
number of model vertices), so they are the same at every BR noise level: the training keypoints
are disjoint from the evaluation keypoints at 0.0-0.5 mr, provided the evaluation uses the same
seed and count (both recorded in the set).

Caching: the first build parses the 6 model PLYs and writes an .npz under `cache_dir`
(default $LRF_CACHE, else $XDG_CACHE_HOME/lrf_jax, else ~/.cache/lrf_jax). Later builds with the
same parameters and unchanged files (size and mtime) load it and parse no PLY.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from lrf_jax.datasets.bologna import (BR_MODELS, BR_SCENE_MODELS, FOLDER, br_model_path,
                                      load_br)
from lrf_jax.datasets.cache import default_cache_dir
from lrf_jax.datasets.pair import repeatability_keypoints, transform_points
from lrf_jax.datasets.root import dataset_dir
from lrf_jax.io import atomic

_CACHE_VERSION = 1


@dataclasses.dataclass(frozen=True, eq=False)
class TrainingSet:
  """Seeded training keypoints over the noise-free BR pairs.

  Attributes:
    model_names: the BR models, (6,).
    model_points: per model, (n_m, 3) float64 points in metres (read-only).
    model_mr: (6,) float64 mean edge length of each model, metres.
    pair_scene: (P,) int BR scene index of each pair (P = 18).
    pair_model: (P,) int index into `model_names` of each pair.
    transforms: (P, 4, 4) float64 ground truth of each pair (model -> scene).
    scene_points: per pair, (n, 3) float64 model points under the pair's ground truth.
    keypoint_pair: (N,) int64 pair of each keypoint.
    keypoint_vertex: (N,) int64 vertex of each keypoint (model and scene side alike).
    seed: the keypoint sampling seed.
    eval_n: evaluation keypoints per pair excluded from the pool.
    eval_seed: the evaluation seed whose keypoints were excluded.
  """

  model_names: tuple[str, ...]
  model_points: tuple[np.ndarray, ...]
  model_mr: np.ndarray
  pair_scene: np.ndarray
  pair_model: np.ndarray
  transforms: np.ndarray
  scene_points: tuple[np.ndarray, ...]
  keypoint_pair: np.ndarray
  keypoint_vertex: np.ndarray
  seed: int
  eval_n: int
  eval_seed: int

  def __len__(self) -> int:
    return int(len(self.keypoint_pair))

  @property
  def num_pairs(self) -> int:
    return int(len(self.pair_scene))

  def pair_points(self, pair: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(model points (n, 3), scene points (n, 3), mr) of one pair; point i matches point i."""
    m = int(self.pair_model[pair])
    return self.model_points[m], self.scene_points[pair], float(self.model_mr[m])

  def num_batches(self, batch_size: int, drop_remainder: bool = True) -> int:
    """Batches per epoch."""
    full, rest = divmod(len(self), batch_size)
    return full + (0 if drop_remainder or rest == 0 else 1)

  def batches(self, batch_size: int, *, epoch: int = 0,
              drop_remainder: bool = True) -> Iterator[np.ndarray]:
    """Shuffled batches of keypoint indices for one epoch.

    The order is `np.random.default_rng([seed, epoch]).permutation(N)`: the same seed and
    epoch always give the same batches; each epoch a different order.

    Args:
      batch_size: keypoints per batch.
      epoch: epoch number (part of the shuffling seed).
      drop_remainder: drop the last partial batch (fixed shapes under jit).

    Yields:
      (batch_size,) int64 indices into the keypoint arrays (the last one shorter when
      drop_remainder is False).
    """
    if batch_size <= 0:
      raise ValueError(f"batch_size: expected > 0, found {batch_size}")
    order = np.random.default_rng([self.seed, epoch]).permutation(len(self))
    for start in range(0, self.num_batches(batch_size, drop_remainder) * batch_size,
                       batch_size):
      yield order[start:start + batch_size]


def build_training_set(root: str | os.PathLike | None = None, *, n_keypoints: int = 20000,
                       seed: int = 0, eval_n: int = 1000, eval_seed: int = 0,
                       cache_dir: str | os.PathLike | None = None,
                       use_cache: bool = True) -> TrainingSet:
  """Builds (or loads from the cache) the training keypoints.

  Keypoints are split evenly over the 18 noise-free BR pairs (the first n_keypoints % 18
  pairs get one more); within a pair they are drawn without replacement from the model's
  vertices minus that pair's evaluation keypoints, with `np.random.default_rng(seed)` used
  pair after pair.

  Args:
    root: data root (None: search $LRF_DATA, `<repo>/data`).
    n_keypoints: total number of training keypoints.
    seed: keypoint sampling seed (also seeds `TrainingSet.batches`).
    eval_n: evaluation keypoints per pair to exclude (the repeatability protocol's 1000).
    eval_seed: seed of the evaluation keypoints to exclude.
    cache_dir: where the .npz cache lives (default `default_cache_dir()`).
    use_cache: read and write the cache.

  Returns:
    The TrainingSet.
  """
  if n_keypoints <= 0:
    raise ValueError(f"n_keypoints: expected > 0, found {n_keypoints}")
  folder = dataset_dir(FOLDER, root)
  params = {"version": _CACHE_VERSION, "n_keypoints": n_keypoints, "seed": seed,
            "eval_n": eval_n, "eval_seed": eval_seed}
  cache_file = None
  if use_cache:
    files = [br_model_path(m, folder.parent) for m in BR_MODELS]
    files += [folder / "scenes" / f"Scene{i}-rs0.xf" for i in range(len(BR_SCENE_MODELS))]
    stamp = [(str(f.relative_to(folder)), f.stat().st_size, f.stat().st_mtime_ns)
             for f in files]
    key = hashlib.sha1(json.dumps([params, stamp]).encode()).hexdigest()[:16]
    cache_file = Path(cache_dir or default_cache_dir()) / f"br_training_{key}.npz"
    if cache_file.exists():
      return _from_arrays(dict(np.load(cache_file)), params)
  arrays = _build_arrays(folder.parent, params)
  if cache_file is not None:
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    with atomic.atomic_write(cache_file) as f:  # a concurrent reader never sees half a file
      np.savez(f, **arrays)  # type: ignore[arg-type]  # array names: none is allow_pickle
  return _from_arrays(arrays, params)


def _build_arrays(root: Path, params: dict) -> dict[str, np.ndarray]:
  pairs = load_br(root, 0.0)
  model_index = {name: i for i, name in enumerate(BR_MODELS)}
  models = {p.meta["model"]: p for p in pairs}
  n_pairs = len(pairs)
  quota = np.full(n_pairs, params["n_keypoints"] // n_pairs)
  quota[:params["n_keypoints"] % n_pairs] += 1
  rng = np.random.default_rng(params["seed"])
  kp_pair, kp_vertex = [], []
  for k, pair in enumerate(pairs):
    excluded, _ = repeatability_keypoints(pair, params["eval_n"], params["eval_seed"])
    pool = np.setdiff1d(np.arange(len(pair.model_points)), excluded)
    if quota[k] > len(pool):
      raise ValueError(f"n_keypoints: {quota[k]} keypoints wanted on pair {pair.name}, only "
                       f"{len(pool)} vertices outside the evaluation keypoints")
    kp_vertex.append(np.sort(rng.choice(pool, size=quota[k], replace=False)))
    kp_pair.append(np.full(quota[k], k))
  arrays = {
      "model_mr": np.array([models[m].mr for m in BR_MODELS]),
      "pair_scene": np.array([p.meta["scene"] for p in pairs]),
      "pair_model": np.array([model_index[p.meta["model"]] for p in pairs]),
      "transforms": np.stack([p.transform for p in pairs]),
      "keypoint_pair": np.concatenate(kp_pair).astype(np.int64),
      "keypoint_vertex": np.concatenate(kp_vertex).astype(np.int64),
  }
  for i, m in enumerate(BR_MODELS):
    arrays[f"model_points_{i}"] = np.asarray(models[m].model_points)
  return arrays


def _from_arrays(arrays: dict[str, np.ndarray], params: dict) -> TrainingSet:
  model_points = tuple(arrays[f"model_points_{i}"] for i in range(len(BR_MODELS)))
  scene_points = tuple(transform_points(t, model_points[m])
                       for t, m in zip(arrays["transforms"], arrays["pair_model"]))
  for a in (*model_points, *scene_points):
    a.flags.writeable = False
  return TrainingSet(
      model_names=BR_MODELS, model_points=model_points, model_mr=arrays["model_mr"],
      pair_scene=arrays["pair_scene"], pair_model=arrays["pair_model"],
      transforms=arrays["transforms"], scene_points=scene_points,
      keypoint_pair=arrays["keypoint_pair"], keypoint_vertex=arrays["keypoint_vertex"],
      seed=params["seed"], eval_n=params["eval_n"], eval_seed=params["eval_seed"])
