"""Where the real data lives: an explicit path, else $LRF_DATA, else `<repo>/data`.

A data root is a folder holding one sub-folder per data set, named as in `DATASETS`. When no
candidate holds the requested set, `DataNotFoundError` lists every place looked at and how to
obtain each set (data/README.md says the same at length).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

ENV_VAR = "LRF_DATA"
REPO_DATA = Path(__file__).resolve().parents[2] / "data"


@dataclasses.dataclass(frozen=True)
class DatasetInfo:
  """A real data set: its folder name under the data root and where to obtain it."""

  folder: str
  title: str
  obtain: str


DATASETS: dict[str, DatasetInfo] = {
    info.folder: info for info in (
        DatasetInfo(
            "bologna_retrieval",
            "Bologna retrieval (BR): 6 Stanford models, 18 scenes x 3 noise levels",
            "Tombari et al. 3D keypoint benchmark 'Retrieval' set; copy in "
            "github.com/tolgabirdal/ppf_matching (data/Stanford/<model>/*_0.ply -> "
            "models/<model>/, data/Retrieval1/* -> scenes/)"),
        DatasetInfo(
            "uwa_object_recognition", "UWA object recognition (UWAOR): models, ground truth, "
            "scene rs1",
            "Mian et al. (PAMI 2006, IJCV 2009); ground truth and models in "
            "github.com/tolgabirdal/ppf_matching (data/GroundTruth_3Dscenes, data/*.ply), scene "
            "rs1 as rs1.pcd of PCL's alignment_prerejective tutorial"),
        DatasetInfo(
            "uwa_3d_modeling_views", "UWA 3D modelling (UWA3M): raw range views",
            "Mian et al. (IJCV 2006); views {chef,parasaurolophus,T-rex}_view*.txt in "
            "github.com/ohirose/bcpd-dataset (gzip them); pseudo_gt_DERIVED.txt comes with "
            "this project's data bundle"),
        DatasetInfo(
            "stanford_bunny_scans", "Stanford bunny: 10 raw range scans + bun.conf",
            "Stanford 3D Scanning Repository, graphics.stanford.edu/data/3Dscanrep "
            "(bunny.tar.gz: bunny/data/*.ply and bun.conf)"),
    )
}


class DataNotFoundError(FileNotFoundError):
  """No candidate data root holds the requested data set (the message says where to get it)."""


def candidate_roots(path: str | os.PathLike | None = None) -> list[tuple[Path, str]]:
  """The data roots searched, in order, each with where it came from.

  Args:
    path: an explicit root. When given, it is the only candidate.

  Returns:
    [(root, origin)], origin one of "argument", "$LRF_DATA", "<repo>/data".
  """
  if path is not None:
    return [(Path(path).expanduser(), "argument")]
  out = []
  env = os.environ.get(ENV_VAR)
  if env:
    out.append((Path(env).expanduser(), f"${ENV_VAR}"))
  out.append((REPO_DATA, "<repo>/data"))
  return out


def find_data_root(path: str | os.PathLike | None = None, dataset: str | None = None) -> Path:
  """Finds the data root holding `dataset` (or any known set when `dataset` is None).

  Args:
    path: an explicit data root (searched alone). It may also be the data set's own folder,
      e.g. `.../bologna_retrieval`; its parent is then returned.
    dataset: a folder name from `DATASETS`, or None for "any of them".

  Returns:
    The data root (the folder that contains the data set's folder).

  Raises:
    ValueError: `dataset` is not a known name.
    DataNotFoundError: no candidate holds it; the message lists every place looked at and how
      to obtain each missing set.
  """
  if dataset is not None and dataset not in DATASETS:
    raise ValueError(f"dataset: expected one of {sorted(DATASETS)}, found {dataset!r}")
  wanted = [dataset] if dataset else list(DATASETS)
  looked = []
  for root, origin in candidate_roots(path):
    if origin == "argument" and root.name in wanted and root.is_dir():
      return root.parent
    for name in wanted:
      if (root / name).is_dir():
        return root
    looked.append(f"  {origin}: {root}" + ("" if root.is_dir() else " (does not exist)"))
  if path is None and not os.environ.get(ENV_VAR):
    looked.append(f"  ${ENV_VAR}: not set")
  how = "\n".join(f"  {name}/  -- {DATASETS[name].title}\n      obtain: {DATASETS[name].obtain}"
                  for name in wanted)
  raise DataNotFoundError(
      f"data set {' or '.join(wanted)} not found. Looked in:\n" + "\n".join(looked)
      + f"\nPut the folder(s) below under one data root and set {ENV_VAR}=<that root> (or pass "
      "the root explicitly):\n" + how + "\nSee data/README.md for the layout inside each folder.")


def dataset_dir(dataset: str, root: str | os.PathLike | None = None) -> Path:
  """The folder of one data set: `find_data_root(root, dataset) / dataset`.

  Args:
    dataset: a folder name from `DATASETS`.
    root: an explicit data root, or None to search $LRF_DATA and `<repo>/data`.

  Returns:
    The data set's folder.

  Raises:
    DataNotFoundError: as `find_data_root`.
  """
  return find_data_root(root, dataset) / dataset


def require(path: Path, dataset: str, what: str) -> Path:
  """`path` if it exists, else DataNotFoundError naming the missing file of `dataset`.

  Args:
    path: a file or folder inside a data set.
    dataset: the data set's folder name.
    what: a short description of the file, for the message.

  Returns:
    `path`.
  """
  if not path.exists():
    raise DataNotFoundError(f"{dataset}: {what} not found at {path}; obtain: "
                            f"{DATASETS[dataset].obtain} (see data/README.md)")
  return path
