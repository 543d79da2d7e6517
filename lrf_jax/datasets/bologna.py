"""Bologna retrieval (BR): 6 Stanford models, 18 scenes, Gaussian noise 0.1-0.5 mr.

Layout under the data root::

    bologna_retrieval/models/<model>/<file>.ply      binary PLY, metres, with faces
    bologna_retrieval/scenes/Scene{i}-rs0.xf         ground truth, model -> scene
    bologna_retrieval/scenes/Scene{i}_{0.1,0.3,0.5}.ply

Each scene is one whole model moved by its .xf plus i.i.d. Gaussian noise; vertex order and
faces are the model's, so correspondences are exact by index. Noise levels:

* 0.0: the model under its .xf (the noise-free scenes are not stored; the training set);
* 0.1, 0.3, 0.5: read from the files;
* 0.2, 0.4: synthesised here (per-axis sigma = level * mr, seeded), labelled in `meta`.

mr is the noise-free model's mean edge length (the noise levels are defined in it).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lrf_jax.datasets.cache import Mesh, load_mesh
from lrf_jax.datasets.nuisances import add_gaussian_noise
from lrf_jax.datasets.pair import Pair, transform_points
from lrf_jax.datasets.root import dataset_dir, require
from lrf_jax.io import read_ply, read_xf

FOLDER = "bologna_retrieval"
BR_MODELS = ("armadillo", "buddha", "bunny", "chinese_dragon", "dragon", "statuette")
# Model of each scene (from ConfigScene{i}.ini; tests check it against the data).
BR_SCENE_MODELS = ("bunny", "dragon", "chinese_dragon", "armadillo", "buddha", "statuette",
                   "bunny", "buddha", "dragon", "dragon", "armadillo", "buddha", "statuette",
                   "dragon", "armadillo", "statuette", "buddha", "buddha")
BR_NOISE_LEVELS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
STORED_NOISE_LEVELS = (0.1, 0.3, 0.5)


def _folder(root: str | os.PathLike | None) -> Path:
  return dataset_dir(FOLDER, root)


def br_model_path(name: str, root: str | os.PathLike | None = None) -> Path:
  """The PLY file of BR model `name` (the one `.ply` in `models/<name>/`).

  Args:
    name: one of `BR_MODELS`.
    root: data root (None: search $LRF_DATA, `<repo>/data`).

  Returns:
    The file's path.
  """
  if name not in BR_MODELS:
    raise ValueError(f"BR model: expected one of {BR_MODELS}, found {name!r}")
  folder = require(_folder(root) / "models" / name, FOLDER, f"model folder {name}")
  files = sorted(folder.glob("*.ply"))
  if len(files) != 1:
    raise ValueError(f"{folder}: expected exactly one .ply file, found {[f.name for f in files]}")
  return files[0]


def load_br_model(name: str, root: str | os.PathLike | None = None) -> Mesh:
  """A BR model (cached: parsed once per process).

  Args:
    name: one of `BR_MODELS`.
    root: data root.

  Returns:
    Mesh with (n, 3) float64 points in metres, (f, 3) faces and mr = mean edge length.
  """
  return load_mesh(br_model_path(name, root))


def br_ground_truth(scene: int, root: str | os.PathLike | None = None) -> np.ndarray:
  """The (4, 4) ground truth of BR scene `scene` (model -> scene, metres)."""
  _check_scene(scene)
  return read_xf(require(_folder(root) / "scenes" / f"Scene{scene}-rs0.xf", FOLDER,
                         f"ground truth of scene {scene}"))


def load_br_pair(scene: int, noise: float = 0.0, root: str | os.PathLike | None = None, *,
                 seed: int = 0) -> Pair:
  """One BR model/scene pair at one noise level.

  Args:
    scene: scene index 0..17.
    noise: per-axis noise sigma in mr, one of `BR_NOISE_LEVELS`.
    root: data root.
    seed: seed of the synthesised levels (0.2, 0.4); the noise of scene i at level l is drawn
      from `np.random.default_rng([seed, i, round(1000 * l)])`.

  Returns:
    Pair with index correspondence; `meta` holds scene, model, noise_mr, noise_source
    ("none", "file" or "synthesised") and the files used.
  """
  _check_scene(scene)
  level = _check_noise(noise)
  name = BR_SCENE_MODELS[scene]
  model = load_br_model(name, root)
  transform = br_ground_truth(scene, root)
  meta = {"scene": scene, "model": name, "noise_mr": level, "model_file": str(model.path),
          "units": "m"}
  if level in STORED_NOISE_LEVELS:
    path = require(_folder(root) / "scenes" / f"Scene{scene}_{level}.ply", FOLDER,
                   f"scene {scene} at noise {level}")
    mesh = read_ply(path)
    if len(mesh.points) != len(model.points):
      raise ValueError(f"{path}: element 'vertex': expected {len(model.points)} vertices (the "
                       f"model's, for index correspondence), found {len(mesh.points)}")
    scene_points, scene_faces = mesh.points, mesh.faces
    meta.update(noise_source="file", scene_file=str(path))
  else:
    scene_points = transform_points(transform, model.points)
    scene_faces = model.faces
    if level == 0.0:
      meta.update(noise_source="none")
    else:
      rng = np.random.default_rng([seed, scene, round(1000 * level)])
      scene_points = add_gaussian_noise(scene_points, level, model.mr, rng)
      meta.update(noise_source="synthesised", seed=seed)
  return Pair(name=f"Scene{scene}/noise{level}", dataset="BR", model_points=model.points,
              scene_points=scene_points, model_faces=model.faces, scene_faces=scene_faces,
              transform=transform, mr=model.mr, mr_definition=model.mr_definition,
              correspondence="index", meta=meta)


def load_br(root: str | os.PathLike | None = None, noise: float = 0.0, *,
            scenes: tuple[int, ...] | None = None, seed: int = 0) -> list[Pair]:
  """All (or some) BR pairs at one noise level.

  Args:
    root: data root (None: search $LRF_DATA, `<repo>/data`).
    noise: per-axis noise sigma in mr, one of `BR_NOISE_LEVELS`.
    scenes: scene indices (default all 18).
    seed: seed of the synthesised levels (see `load_br_pair`).

  Returns:
    One Pair per scene, in scene order.
  """
  return [load_br_pair(i, noise, root, seed=seed)
          for i in (range(len(BR_SCENE_MODELS)) if scenes is None else scenes)]


def _check_scene(scene: int) -> None:
  if not 0 <= int(scene) < len(BR_SCENE_MODELS):
    raise ValueError(f"BR scene: expected 0..{len(BR_SCENE_MODELS) - 1}, found {scene}")


def _check_noise(noise: float) -> float:
  for level in BR_NOISE_LEVELS:
    if abs(float(noise) - level) < 1e-9:
      return level
  raise ValueError(f"BR noise: expected one of {BR_NOISE_LEVELS} (mr), found {noise}")
