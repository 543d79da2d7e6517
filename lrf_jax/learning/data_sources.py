"""Training and validation data for a `TrainConfig`: BR (the paper), the procedural demo set, or
the user's own scan sets (`lrf_jax.datasets.scan_sets`), alone or mixed with BR.

Scan pairs are not index-aligned: the training keypoints of a scan pair are model points with a
ground-truth counterpart in the scene (`datasets.training_correspondences`: the nearest scene
point under the ground truth, within `scan_match_mr` (0.5 mr by default), each scene point once, the evaluation keypoints of
seed 0 left out). `TrainingClouds` pairs point i of a model with point i of its scene, so each
scan pair enters it with both clouds reordered: the k corresponding points first, in
correspondence order, then every other point of each cloud (a reordering changes no
neighborhood); its keypoints are drawn among those k rows.

The Chamfer loss is in cloud units, so each scan pair is also scaled (both clouds by one factor:
frames are directions, no neighborhood changes) to a common mesh resolution: 1 / radius_mr
(support radius 1) when the scans train alone, BR's median model mr when they are mixed with BR.
Otherwise a raw LiDAR sweep's 6 m supports would outweigh BR's 7 mm ones a thousandfold in every
batch, and a set in millimetres one in metres.
"""

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
  * "scans": the training pairs of `config.scans` (`scan_split`), keypoints drawn uniformly
    over their corresponding points (`scan_training_clouds`).
  * "br+scans": both, `config.scan_share` of the keypoints on the scans, the rest on BR.

  Raises:
    ValueError: a scan set that cannot be read or split, or fewer corresponding points on the
      training scan pairs than the keypoints asked of them.
  """
  if config.data == "scans":
    return scan_training_clouds(scan_split(config)[0], config.num_train_keypoints, config,
                                unit_mr=1.0 / config.radius_mr)
  if config.data == "br+scans":
    n_scans = max(1, round(config.scan_share * config.num_train_keypoints))
    br = _br_clouds(config, config.num_train_keypoints - n_scans)
    scans = scan_training_clouds(scan_split(config)[0], n_scans, config,
                                 unit_mr=float(np.median(br.mr)))
    return concatenate(br, scans)
  if config.data == "br":
    return _br_clouds(config, config.num_train_keypoints)
  pairs = datasets.load_demo(4, seed=config.seed, partial=False)
  models = [p.model_points for p in pairs]
  scenes = [p.scene_points for p in pairs]
  mr = np.array([p.mr for p in pairs])
  keypoints = sample_training_keypoints([len(m) for m in models], config.num_train_keypoints,
                                        config.seed)
  return TrainingClouds(models=models, scenes=scenes, radii=config.radius_mr * mr, mr=mr,
                        keypoints=keypoints, names=[p.name for p in pairs])


def _br_clouds(config: TrainConfig, n_keypoints: int) -> TrainingClouds:
  """The noise-free BR pairs with `n_keypoints` training keypoints."""
  ts = datasets.build_training_set(config.data_root, n_keypoints=n_keypoints, seed=config.seed)
  models, scenes, mr = [], [], []
  for p in range(ts.num_pairs):
    m, s, r = ts.pair_points(p)
    models.append(m)
    scenes.append(s)
    mr.append(r)
  mr_arr = np.asarray(mr)
  keypoints = np.stack([ts.keypoint_pair, ts.keypoint_vertex], axis=1)
  return TrainingClouds(models=models, scenes=scenes, radii=config.radius_mr * mr_arr,
                        mr=mr_arr, keypoints=keypoints,
                        names=[f"Scene{int(s)}" for s in ts.pair_scene])


def scan_training_clouds(pairs: list[datasets.Pair], n_keypoints: int, config: TrainConfig,
                         *, unit_mr: float | None = None) -> TrainingClouds:
  """Scan pairs as `TrainingClouds` (see the module docstring) with `n_keypoints` keypoints drawn
  uniformly over their corresponding points (`sample_training_keypoints`, `config.seed`).

  Args:
    pairs: the training pairs (`Pair.correspondence` "nearest").
    n_keypoints: the keypoints wanted.
    config: the run's config (`radius_mr`, `seed`).
    unit_mr: each pair's clouds are scaled by unit_mr / pair.mr, so that every pair's mr is
      `unit_mr` (None: as stored).

  Raises:
    ValueError: fewer corresponding points than `n_keypoints` (the message gives both and what
      to lower).
  """
  models, scenes, counts, mr = [], [], [], []
  for pair in pairs:
    mi, si = datasets.training_correspondences(pair, max_dist_mr=config.scan_match_mr)
    scale = 1.0 if unit_mr is None else unit_mr / pair.mr
    models.append(scale * _corresponding_first(pair.model_points, mi))
    scenes.append(scale * _corresponding_first(pair.scene_points, si))
    counts.append(len(mi))
    mr.append(pair.mr * scale)
  available = int(sum(counts))
  if available < n_keypoints:
    raise ValueError(
        f"scans: {n_keypoints} training keypoints wanted on {len(pairs)} training pair(s) of "
        f"{', '.join(sorted({p.dataset for p in pairs}))}, which hold {available} points with "
        f"a ground-truth counterpart (within scan_match_mr = {config.scan_match_mr:g} mr); lower "
        "num_train_keypoints (or scan_share), add scans, or raise scan_match_mr (scans "
        "voxelised on their own grids, such as 3DMatch's fragments, have few points within "
        "0.5 mr of each other: 1 mr takes about a quarter of them)")
  mr_arr = np.asarray(mr, np.float64)
  return TrainingClouds(models=models, scenes=scenes, radii=config.radius_mr * mr_arr,
                        mr=mr_arr, keypoints=sample_training_keypoints(counts, n_keypoints,
                                                                       config.seed),
                        names=[f"{p.dataset}/{p.name}" for p in pairs])


def _corresponding_first(points: np.ndarray, first: np.ndarray) -> np.ndarray:
  """(n, 3) `points` reordered: rows `first` (distinct indices) in that order, then the others
  in index order."""
  rest = np.ones(len(points), bool)
  rest[first] = False
  return np.concatenate([points[first], points[rest]])


def concatenate(a: TrainingClouds, b: TrainingClouds) -> TrainingClouds:
  """The clouds of `a` then `b`, with every keypoint (the cloud ids of `b`'s shifted)."""
  shifted = b.keypoints + np.array([len(a.models), 0])
  return TrainingClouds(models=a.models + b.models, scenes=a.scenes + b.scenes,
                        radii=np.concatenate([a.radii, b.radii]), mr=np.concatenate([a.mr, b.mr]),
                        keypoints=np.concatenate([a.keypoints, shifted]).astype(np.int64),
                        names=a.names + b.names)


def scan_split(config: TrainConfig) -> tuple[list[datasets.Pair], list[datasets.Pair]]:
  """(training pairs, validation pairs) of `config`'s scan sets.

  With `config.val_scans`, their pairs validate and every pair of `config.scans` trains;
  otherwise, with several `scans` folders, the last one validates; with one, it is split by scan
  (`datasets.split_by_scan`). With `val_pairs=0` every pair of `scans` trains.

  Raises:
    ValueError: as `datasets.read_scan_set` and `datasets.split_by_scan`.
  """
  folders, held = list(config.scans), list(config.val_scans)
  least = config.scan_min_overlap
  if config.val_pairs <= 0:
    return _pairs_of(folders, least), []
  if held or len(folders) > 1:
    train = folders if held else folders[:-1]
    return _pairs_of(train, least), _pairs_of(held or folders[-1:], least)
  return datasets.split_by_scan(datasets.read_scan_set(folders[0], min_overlap=least))


def _pairs_of(folders: list[str], min_overlap: float) -> list[datasets.Pair]:
  return [p for f in folders for p in datasets.read_scan_set(f, min_overlap=min_overlap).pairs]


def validation_label(config: TrainConfig) -> str:
  """What `validation_pairs(config)` validates on, in words (figure titles, messages)."""
  if config.val_pairs <= 0:
    return "nothing (val_pairs=0)"
  if "scans" in config.data.split("+"):
    if config.val_scans or len(config.scans) > 1:
      held = ", ".join(config.val_scans or config.scans[-1:])
      return f"up to {config.val_pairs} pair(s) of the held-out scan set(s) {held}"
    return f"up to {config.val_pairs} pair(s) of the last scans of {config.scans[0]} (held out)"
  if config.data == "br":
    return f"{config.val_pairs} Stanford bunny scan pair(s)"
  return f"{config.val_pairs} procedural demo pair(s)"


def validation_pairs(config: TrainConfig) -> list[datasets.Pair]:
  """The first `config.val_pairs` consecutive Stanford bunny scan pairs (real partial scans;
  BR holds no held-out data), partial, noisy demo pairs for `data="demo"`, or with scan sets the
  first `config.val_pairs` held-out scan pairs (`scan_split`)."""
  if config.val_pairs <= 0:
    return []
  if "scans" in config.data.split("+"):
    return scan_split(config)[1][:config.val_pairs]
  if config.data == "br":
    return datasets.load_bunny_pairs(config.data_root)[:config.val_pairs]
  return [datasets.make_demo_pair(100 + i, seed=config.seed, noise_mr=0.3, partial=True)
          for i in range(config.val_pairs)]
