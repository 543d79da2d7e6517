"""Training and validation data for a `TrainConfig`: BR (the paper) or the procedural demo set."""

from __future__ import annotations

import numpy as np

from lrf_jax import datasets
from lrf_jax.learning.config import TrainConfig
from lrf_jax.learning.batches import TrainingClouds, sample_training_keypoints


def training_clouds(config: TrainConfig) -> TrainingClouds:
  """The clouds and fixed training keypoints of `config.data`.

  * "br": the 18 noise-free BR pairs (each model vs itself under the scene's ground truth),
    `config.num_train_keypoints` keypoints disjoint from the evaluation keypoints of seed 0
    (`datasets.build_training_set`; cached so a second run parses no PLY).
  * "demo": 4 full (non-partial) noise-free synthetic pairs; no download.
  """
  if config.data == "br":
    ts = datasets.build_training_set(config.data_root, n_keypoints=config.num_train_keypoints,
                                     seed=config.seed)
    models, scenes, mr = [], [], []
    for p in range(ts.num_pairs):
      m, s, r = ts.pair_points(p)
      models.append(m)
      scenes.append(s)
      mr.append(r)
    mr = np.asarray(mr)
    keypoints = np.stack([ts.keypoint_pair, ts.keypoint_vertex], axis=1)
    names = [f"Scene{int(s)}" for s in ts.pair_scene]
  else:
    pairs = datasets.load_demo(4, seed=config.seed, partial=False)
    models = [p.model_points for p in pairs]
    scenes = [p.scene_points for p in pairs]
    mr = np.array([p.mr for p in pairs])
    keypoints = sample_training_keypoints([len(m) for m in models], config.num_train_keypoints,
                                          config.seed)
    names = [p.name for p in pairs]
  return TrainingClouds(models=models, scenes=scenes, radii=config.radius_mr * mr, mr=mr,
                        keypoints=keypoints, names=names)


def validation_label(config: TrainConfig) -> str:
  """What `validation_pairs(config)` validates on, in words (figure titles, messages)."""
  if config.val_pairs <= 0:
    return "nothing (val_pairs=0)"
  if config.data == "br":
    return f"{config.val_pairs} Stanford bunny scan pair(s)"
  return f"{config.val_pairs} procedural demo pair(s)"


def validation_pairs(config: TrainConfig) -> list[datasets.Pair]:
  """The first `config.val_pairs` consecutive Stanford bunny scan pairs (real partial scans;
  BR holds no held-out data), or partial, noisy demo pairs for `data="demo"` or when the bunny
  scans are not found."""
  if config.val_pairs <= 0:
    return []
  if config.data == "br":
    return datasets.load_bunny_pairs(config.data_root)[:config.val_pairs]
  return [datasets.make_demo_pair(100 + i, seed=config.seed, noise_mr=0.3, partial=True)
          for i in range(config.val_pairs)]
