"""UWA object recognition (UWAOR): four models placed in the cluttered scene rs1.

Layout under the data root::

    uwa_object_recognition/GroundTruth_3Dscenes/{object}-rs{k}.xf   model -> scene, mm
    uwa_object_recognition/GroundTruth_3Dscenes/occlusion.txt
    uwa_object_recognition/models/{cheff_simple,chicken2,parasaurolophus_low_normals2,
                                   trex_small}.ply                  ascii, mm, with faces
    uwa_object_recognition/models/trex_small_offset_DERIVED.txt    (optional, see below)
    uwa_object_recognition/scenes/rs1_full_uwaframe_mm_DERIVED.npy (or rs1_pcltutorial.pcd)
    uwa_object_recognition/scenes/rs1_normals2.ply                 (variant "downsampled")

Model files: the finest meshed copy of each object (chef 16k vertices, chicken 33k,
parasaurolophus 28k, T-rex 9k). `trex_small.ply` is translated: the ground-truth frame is
`p - TREX_SMALL_OFFSET_MM` (the offset file, when present, must agree).

Scene rs1, variant "full" (default): the full-resolution scan (289,541 points, 0.33 mm
spacing). It is the PCL tutorial's `rs1.pcd` (metres, axes permuted: pcd = 1e-3 (-y, -x, -z)
of the UWA frame) mapped back to the UWA frame; the `_DERIVED.npy` holds exactly that and is
used when present, else the PCD is decoded here. With it the ground truth puts 24 / 15 / 35 /
30 % of the chef / chicken / parasaurolophus / T-rex model points within 1 mm of the scene,
the visible parts (SOURCE.txt). Variant "downsampled" (`rs1_normals2.ply`, 12,345 points,
about 3 mm apart) is coarser than every model's mr, so few model points have a scene point
within 0.5 mr: it is offered, not used by default.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np

from lrf_jax.datasets.cache import Mesh, load_mesh
from lrf_jax.datasets.pair import Pair
from lrf_jax.datasets.root import dataset_dir, require
from lrf_jax.io import read_cloud, read_pcd, read_xf

FOLDER = "uwa_object_recognition"
UWAOR_OBJECTS = ("chef", "chicken", "parasaurolophus", "T-rex")
UWAOR_MODEL_FILES = {"chef": "cheff_simple.ply", "chicken": "chicken2.ply",
                     "parasaurolophus": "parasaurolophus_low_normals2.ply",
                     "T-rex": "trex_small.ply"}
# trex_small.ply = UWA frame + this offset (mm); from models/trex_small_offset_DERIVED.txt.
TREX_SMALL_OFFSET_MM = np.array([-17.73522328, 51.06395583, 607.36875364])
_OCCLUSION_NAMES = {"chef": "chef", "chicken": "chicken", "para": "parasaurolophus",
                    "trex": "T-rex"}

SceneVariant = Literal["full", "pcd", "downsampled"]


def _folder(root: str | os.PathLike | None) -> Path:
  return dataset_dir(FOLDER, root)


def trex_offset(root: str | os.PathLike | None = None) -> np.ndarray:
  """The (3,) offset (mm) of `trex_small.ply` from the UWA frame: p_uwa = p_file - offset.

  Read from `models/trex_small_offset_DERIVED.txt` when present (the last non-comment line),
  else `TREX_SMALL_OFFSET_MM`.
  """
  path = _folder(root) / "models" / "trex_small_offset_DERIVED.txt"
  if not path.exists():
    return TREX_SMALL_OFFSET_MM.copy()
  rows = [line.split() for line in path.read_text().splitlines()
          if line.strip() and not line.lstrip().startswith("#")]
  if len(rows) != 1 or len(rows[0]) != 3:
    raise ValueError(f"{path}: offset: expected one line 'tx ty tz', found {rows}")
  return np.array([float(v) for v in rows[0]])


def load_uwaor_model(name: str, root: str | os.PathLike | None = None) -> Mesh:
  """A UWAOR model in the ground-truth (UWA) frame, mm (cached).

  Args:
    name: one of `UWAOR_OBJECTS`.
    root: data root.

  Returns:
    Mesh with points (n, 3) mm (T-rex offset removed), faces, mr = mean edge length.
  """
  if name not in UWAOR_MODEL_FILES:
    raise ValueError(f"UWAOR model: expected one of {UWAOR_OBJECTS}, found {name!r}")
  path = require(_folder(root) / "models" / UWAOR_MODEL_FILES[name], FOLDER, f"model {name}")
  mesh = load_mesh(path)
  if name != "T-rex":
    return mesh
  points = mesh.points - trex_offset(root)
  points.flags.writeable = False
  return Mesh(points, mesh.faces, mesh.mr, mesh.mr_definition, mesh.path)


def uwaor_ground_truth(name: str, scene: str = "rs1",
                       root: str | os.PathLike | None = None) -> np.ndarray:
  """The (4, 4) ground truth of model `name` in `scene` (model -> scene, mm)."""
  return read_xf(require(_folder(root) / "GroundTruth_3Dscenes" / f"{name}-{scene}.xf", FOLDER,
                         f"ground truth {name}-{scene}.xf"))


def uwaor_occlusion(root: str | os.PathLike | None = None) -> dict[tuple[int, str], float]:
  """`occlusion.txt` as {(scene number, object): occlusion percent}."""
  path = require(_folder(root) / "GroundTruth_3Dscenes" / "occlusion.txt", FOLDER,
                 "occlusion.txt")
  out = {}
  for number, line in enumerate(path.read_text().splitlines(), start=1):
    tokens = line.split()
    if len(tokens) != 3 or not tokens[0].isdigit():
      continue  # the header line
    obj = _OCCLUSION_NAMES.get(tokens[1], tokens[1])
    try:
      out[(int(tokens[0]), obj)] = float(tokens[2])
    except ValueError as e:
      raise ValueError(f"{path}: line {number}: expected 'scene object percent', found "
                       f"{line!r}") from e
  return out


def load_uwaor_scene(scene: str = "rs1", root: str | os.PathLike | None = None, *,
                     variant: SceneVariant = "full") -> np.ndarray:
  """A UWAOR scene's points in the UWA frame, mm (only rs1 is available).

  Args:
    scene: "rs1".
    root: data root.
    variant: "full" (derived .npy, else decoded from the PCD), "pcd" (always decode the PCD)
      or "downsampled" (rs1_normals2.ply).

  Returns:
    (m, 3) float64 points, mm.
  """
  if scene != "rs1":
    raise ValueError(f"UWAOR scene: expected 'rs1' (the only scene available; see "
                     f"data/README.md), found {scene!r}")
  folder = _folder(root) / "scenes"
  if variant == "downsampled":
    return read_cloud(require(folder / "rs1_normals2.ply", FOLDER, "rs1_normals2.ply")).points
  if variant not in ("full", "pcd"):
    raise ValueError(f"variant: expected 'full', 'pcd' or 'downsampled', found {variant!r}")
  npy = folder / "rs1_full_uwaframe_mm_DERIVED.npy"
  if variant == "full" and npy.exists():
    return read_cloud(npy).points
  pcd = read_pcd(require(folder / "rs1_pcltutorial.pcd", FOLDER, "rs1_pcltutorial.pcd")).points
  return -1000.0 * pcd[:, [1, 0, 2]]  # pcd = 1e-3 (-y, -x, -z)_uwa


def load_uwaor(root: str | os.PathLike | None = None, *, scene: str = "rs1",
               variant: SceneVariant = "full",
               objects: tuple[str, ...] | None = None) -> list[Pair]:
  """UWAOR model -> scene pairs for every model with a ground truth in `scene`.

  Args:
    root: data root.
    scene: "rs1".
    variant: scene variant (see `load_uwaor_scene`).
    objects: subset of `UWAOR_OBJECTS` (default: all with a ground-truth file).

  Returns:
    One Pair per object: model mesh (mm) -> the scene cloud, correspondence "nearest",
    mr = the model's mean edge length; meta holds the occlusion percent from occlusion.txt.
    The scene is a single view with the scanner at the origin of the UWA frame (the scene lies at
    z = -746 to -566 mm): `scene_viewpoint` is (0, 0, 0).
  """
  scene_points = load_uwaor_scene(scene, root, variant=variant)
  gt_dir = _folder(root) / "GroundTruth_3Dscenes"
  names = [o for o in (objects or UWAOR_OBJECTS) if (gt_dir / f"{o}-{scene}.xf").exists()]
  occlusion = uwaor_occlusion(root) if (gt_dir / "occlusion.txt").exists() else {}
  pairs = []
  for name in names:
    model = load_uwaor_model(name, root)
    pairs.append(Pair(
        name=f"{name}-{scene}", dataset="UWAOR", model_points=model.points,
        scene_points=scene_points, model_faces=model.faces, scene_faces=None,
        transform=uwaor_ground_truth(name, scene, root), mr=model.mr,
        mr_definition=model.mr_definition, correspondence="nearest",
        meta={"object": name, "scene": scene, "scene_variant": variant, "units": "mm",
              "model_file": str(model.path),
              "occlusion_percent": occlusion.get((int(scene[2:]), name))},
        scene_viewpoint=np.zeros(3)))
  return pairs
