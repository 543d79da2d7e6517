"""UWA 3D modelling (UWA3M): raw range views of chef, parasaurolophus and T-rex.

Layout under the data root::

    uwa_3d_modeling_views/{object}_view{001..}.txt.gz   x y z per line, mm, scanner frame
    uwa_3d_modeling_views/pseudo_gt_DERIVED.txt         pose of each view (see below)

The official ground truth is not available. `pseudo_gt_DERIVED.txt` (computed for this project:
FPFH + RANSAC + point-to-plane ICP of each view onto the UWAOR model of the same object) holds,
per line, ``object view fitness rmse_mm T00 T01 ... T33``: T (row-major 4x4) maps the view's
points into the UWAOR model frame (= almost view 1's frame). Two pair kinds:

* "consecutive": view v -> view v+1 with T = inv(T_{v+1}) @ T_v (view 10 and view 1 do not
  overlap, so there is no wrap-around). Both sides are raw scans; mr = the mean NN distance of
  the model-side view.
* "view_to_model": the UWAOR model (a decimated mesh: a labelled *stand-in* for the UWA3M
  model, which is not available) -> view v, with T = inv(T_v); mr = the model's mean edge
  length.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Literal

import numpy as np

from lrf_jax.datasets.cache import load_mesh
from lrf_jax.datasets.pair import Pair
from lrf_jax.datasets.root import dataset_dir, require
from lrf_jax.datasets.uwaor import UWAOR_MODEL_FILES, load_uwaor_model
from lrf_jax.io import check_rigid

FOLDER = "uwa_3d_modeling_views"
UWA3M_OBJECTS = ("chef", "parasaurolophus", "T-rex")
PSEUDO_GT_FILE = "pseudo_gt_DERIVED.txt"
# Each raw view is in its Minolta scanner's frame, camera at the origin looking down -z (the views
# lie at z = -550 to -700 mm): scan normals are oriented towards the origin.
SENSOR_ORIGIN = np.zeros(3)


@dataclasses.dataclass(frozen=True)
class ViewPose:
  """One line of the pseudo ground truth.

  Attributes:
    transform: (4, 4) float64, maps view points into the model (view 1 / UWAOR) frame, mm.
    fitness: fraction of view points within 1.5 mm of the model after registration.
    rmse_mm: RMS residual of those points, mm.
  """

  transform: np.ndarray
  fitness: float
  rmse_mm: float


def read_pseudo_gt(path: str | os.PathLike) -> dict[tuple[str, int], ViewPose]:
  """Parses `pseudo_gt_DERIVED.txt`.

  Args:
    path: the file.

  Returns:
    {(object, view number): ViewPose}.

  Raises:
    ValueError: a line without 20 fields, non-numbers, or a non-rigid matrix.
  """
  p = Path(path)
  out = {}
  for number, line in enumerate(p.read_text().splitlines(), start=1):
    tokens = line.split()
    if not tokens or tokens[0].startswith("#"):
      continue
    field = f"line {number}"
    if len(tokens) != 20:
      raise ValueError(f"{p}: {field}: expected 20 fields 'object view fitness rmse_mm "
                       f"T00..T33', found {len(tokens)}")
    try:
      view, values = int(tokens[1]), np.array([float(t) for t in tokens[2:]])
    except ValueError as e:
      raise ValueError(f"{p}: {field}: expected numbers after the object name, found "
                       f"{line!r}") from e
    t = check_rigid(values[2:].reshape(4, 4), p, f"{field} matrix")
    out[(tokens[0], view)] = ViewPose(t, float(values[0]), float(values[1]))
  return out


def uwa3m_views(obj: str, root: str | os.PathLike | None = None) -> dict[int, Path]:
  """The view files of one object, {view number: path}, sorted by number."""
  if obj not in UWA3M_OBJECTS:
    raise ValueError(f"UWA3M object: expected one of {UWA3M_OBJECTS}, found {obj!r}")
  pattern = re.compile(rf"{re.escape(obj)}_view(\d+)\.txt(\.gz)?$")
  found = {int(m.group(1)): f for f in dataset_dir(FOLDER, root).iterdir()
           if (m := pattern.match(f.name))}
  return dict(sorted(found.items()))


def load_uwa3m(root: str | os.PathLike | None = None, *,
               kind: Literal["consecutive", "view_to_model"] = "consecutive",
               objects: tuple[str, ...] | None = None) -> list[Pair]:
  """UWA3M pairs with the pseudo ground truth.

  Args:
    root: data root.
    kind: "consecutive" (view v -> view v+1) or "view_to_model" (UWAOR model -> view v).
    objects: subset of `UWA3M_OBJECTS` (default all).

  Returns:
    Pairs (correspondence "nearest"), ordered by object then view. meta holds the views,
    the pseudo-GT fitness/rmse, "ground_truth": "pseudo" and, for view_to_model, the
    "model_stand_in" label.
  """
  if kind not in ("consecutive", "view_to_model"):
    raise ValueError(f"kind: expected 'consecutive' or 'view_to_model', found {kind!r}")
  folder = dataset_dir(FOLDER, root)
  gt = read_pseudo_gt(require(folder / PSEUDO_GT_FILE, FOLDER, PSEUDO_GT_FILE))
  pairs = []
  for obj in objects or UWA3M_OBJECTS:
    views = {v: f for v, f in uwa3m_views(obj, root).items() if (obj, v) in gt}
    if kind == "consecutive":
      for v in views:
        if v + 1 not in views:
          continue
        a, b = load_mesh(views[v]), load_mesh(views[v + 1])
        pa, pb = gt[(obj, v)], gt[(obj, v + 1)]
        pairs.append(Pair(
            name=f"{obj}/view{v:03d}->view{v + 1:03d}", dataset="UWA3M",
            model_points=a.points, scene_points=b.points, model_faces=None, scene_faces=None,
            transform=np.linalg.inv(pb.transform) @ pa.transform, mr=a.mr,
            mr_definition=a.mr_definition, correspondence="nearest",
            meta={"object": obj, "views": (v, v + 1), "ground_truth": "pseudo", "units": "mm",
                  "pseudo_gt_rmse_mm": (pa.rmse_mm, pb.rmse_mm)},
            model_viewpoint=SENSOR_ORIGIN, scene_viewpoint=SENSOR_ORIGIN))
    else:
      model = load_uwaor_model(obj, root)
      for v, path in views.items():
        view = load_mesh(path)
        pose = gt[(obj, v)]
        pairs.append(Pair(
            name=f"{obj}/model->view{v:03d}", dataset="UWA3M", model_points=model.points,
            scene_points=view.points, model_faces=model.faces, scene_faces=None,
            transform=np.linalg.inv(pose.transform), mr=model.mr,
            mr_definition=model.mr_definition, correspondence="nearest",
            meta={"object": obj, "views": (v,), "ground_truth": "pseudo", "units": "mm",
                  "pseudo_gt_fitness": pose.fitness, "pseudo_gt_rmse_mm": (pose.rmse_mm,),
                  "model_stand_in": f"stand-in: UWAOR model {UWAOR_MODEL_FILES[obj]} (decimated "
                                    "mesh), not the UWA3M model"},
            scene_viewpoint=SENSOR_ORIGIN))
  return pairs
