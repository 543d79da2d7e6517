"""3DMatch fragment pairs (RGB-D fragments of indoor scenes) with their ground truth.

Layout under the data root::

    threedmatch_scenes/pairs.tsv                 one row per pair (tab-separated, header below)
    threedmatch_scenes/<fragment>.ply            fused RGB-D fragment, metres, 2.5 cm voxels
    threedmatch_scenes/gt_<scene>_<i>_<j>.txt    4x4 text: maps the SOURCE onto the TARGET

`pairs.tsv` has the header ``pair scene benchmark source target gt_source_to_target``: the pair's
name, the 3DMatch scene, the benchmark it comes from ("3DMatch": > 30 % overlap, "3DLoMatch":
10-30 %), the source and target fragment files and the ground-truth file. The ground truth maps
source points into the target: ``target ≈ R source + t`` (the benchmark's gt.log record
``i j n`` with source = fragment j, target = fragment i).

Fragments are clouds (no faces): mr is the mean nearest-neighbor distance of the source (about
1.2 cm at 2.5 cm voxels). A fused fragment has no single sensor position, so the pairs carry no
viewpoint. The benchmark counts a pair as registered when the rotation error is below 15 degrees
and the translation error below 30 cm (`SUCCESS_RE_DEG`, `SUCCESS_TE_M`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lrf_jax.datasets.cache import load_mesh
from lrf_jax.datasets.pair import Pair
from lrf_jax.datasets.root import ENV_VAR, DataNotFoundError, candidate_roots
from lrf_jax.io import read_xf

FOLDER = "threedmatch_scenes"
PAIRS_FILE = "pairs.tsv"
PAIRS_COLUMNS = ("pair", "scene", "benchmark", "source", "target", "gt_source_to_target")
BENCHMARKS = ("3DMatch", "3DLoMatch")
OBTAIN = ("3DMatch test set (Zeng et al., CVPR 2017): fragments cloud_bin_<k> of the scenes, "
          "e.g. as voxelised in github.com/yewzijian/RegTR (data/indoor/test), ground truth "
          "gt.log of github.com/prs-eth/OverlapPredator (configs/benchmarks/{3DMatch,3DLoMatch}); "
          "one PLY per fragment, one 4x4 text file per pair and pairs.tsv")
# The benchmark's registration-recall thresholds.
SUCCESS_RE_DEG = 15.0
SUCCESS_TE_M = 0.30


def threedmatch_dir(root: str | os.PathLike | None = None) -> Path:
  """The `threedmatch_scenes` folder under an explicit root, else $LRF_DATA, else `<repo>/data`.

  Args:
    root: an explicit data root (searched alone), or the `threedmatch_scenes` folder itself.

  Returns:
    The folder.

  Raises:
    DataNotFoundError: no candidate holds it; the message lists every place looked at and how
      to obtain the data.
  """
  looked = []
  for base, origin in candidate_roots(root):
    if origin == "argument" and base.name == FOLDER and base.is_dir():
      return base
    if (base / FOLDER).is_dir():
      return base / FOLDER
    looked.append(f"  {origin}: {base}" + ("" if base.is_dir() else " (does not exist)"))
  if root is None and not os.environ.get(ENV_VAR):
    looked.append(f"  ${ENV_VAR}: not set")
  raise DataNotFoundError(
      f"data set {FOLDER} not found. Looked in:\n" + "\n".join(looked)
      + f"\nPut {FOLDER}/ under one data root and set {ENV_VAR}=<that root> (or pass the root "
      f"explicitly).\n  {FOLDER}/  -- 3DMatch fragment pairs\n      obtain: {OBTAIN}\n"
      "See data/README.md for the layout inside the folder.")


def _require(path: Path, what: str) -> Path:
  if not path.is_file():
    raise DataNotFoundError(f"{FOLDER}: {what} not found at {path}; obtain: {OBTAIN} "
                            "(see data/README.md)")
  return path


def read_pairs_tsv(path: str | os.PathLike) -> list[dict[str, str]]:
  """Parses `pairs.tsv`: a header naming `PAIRS_COLUMNS` (any order), then one row per pair.

  Args:
    path: the file.

  Returns:
    One {column: value} dict per row, in file order.

  Raises:
    ValueError: a header without the required columns, a row with the wrong number of fields
      or an empty field, an unknown benchmark, a repeated pair name, or no row at all; the
      message names the file, the line and the field.
  """
  p = Path(path)
  lines = [(k, line) for k, line in enumerate(p.read_text(errors="replace").splitlines(), 1)
           if line.strip() and not line.lstrip().startswith("#")]
  if not lines:
    raise ValueError(f"{p}: header: expected the columns {'/'.join(PAIRS_COLUMNS)}, found an "
                     "empty file")
  header = [h.strip() for h in lines[0][1].split("\t")]
  missing = [c for c in PAIRS_COLUMNS if c not in header]
  if missing:
    raise ValueError(f"{p}: header (line {lines[0][0]}): expected the tab-separated columns "
                     f"{'/'.join(PAIRS_COLUMNS)}, found {header} (missing {missing})")
  rows, seen = [], set()
  for number, line in lines[1:]:
    fields = [f.strip() for f in line.split("\t")]
    if len(fields) != len(header):
      raise ValueError(f"{p}: line {number}: expected {len(header)} tab-separated fields "
                       f"({'/'.join(header)}), found {len(fields)}")
    row = dict(zip(header, fields))
    for col in PAIRS_COLUMNS:
      if not row[col]:
        raise ValueError(f"{p}: line {number}: field {col}: expected a value, found an empty "
                         "field")
    if row["benchmark"] not in BENCHMARKS:
      raise ValueError(f"{p}: line {number}: field benchmark: expected one of {BENCHMARKS}, "
                       f"found {row['benchmark']!r}")
    if row["pair"] in seen:
      raise ValueError(f"{p}: line {number}: field pair: expected each pair once, found "
                       f"{row['pair']!r} again")
    seen.add(row["pair"])
    rows.append(row)
  if not rows:
    raise ValueError(f"{p}: rows: expected at least one pair after the header, found none")
  return rows


def load_threedmatch_scenes(root: str | os.PathLike | None = None) -> list[Pair]:
  """The 3DMatch fragment pairs listed in `pairs.tsv`, with their ground truth.

  Args:
    root: data root (or the `threedmatch_scenes` folder); None searches $LRF_DATA, then
      `<repo>/data`.

  Returns:
    One Pair per row of pairs.tsv, in file order: model = the source fragment, scene = the
    target fragment, transform = the ground truth (source -> target, metres), dataset
    "3DMatch", correspondence "nearest", mr = the source's mean nearest-neighbor distance.
    meta holds "scene", "benchmark" ("3DMatch" or "3DLoMatch"), "files" (source, target, gt)
    and "units": "m".

  Raises:
    DataNotFoundError: the folder, pairs.tsv, a fragment or a ground-truth file is missing.
    ValueError: a bad pairs.tsv row (`read_pairs_tsv`), a ground truth that is not a rigid 4x4
      matrix (`lrf_jax.io.read_xf`), or a fragment that is not a non-empty (n, 3) cloud.
  """
  folder = threedmatch_dir(root)
  rows = read_pairs_tsv(_require(folder / PAIRS_FILE, PAIRS_FILE))
  pairs = []
  for row in rows:
    src = load_mesh(_require(folder / row["source"], f"source fragment of {row['pair']}"))
    dst = load_mesh(_require(folder / row["target"], f"target fragment of {row['pair']}"))
    gt = read_xf(_require(folder / row["gt_source_to_target"], f"ground truth of {row['pair']}"))
    pairs.append(Pair(
        name=row["pair"], dataset="3DMatch", model_points=src.points, scene_points=dst.points,
        model_faces=None, scene_faces=None, transform=np.array(gt), mr=src.mr,
        mr_definition=src.mr_definition, correspondence="nearest",
        meta={"scene": row["scene"], "benchmark": row["benchmark"], "units": "m",
              "files": (row["source"], row["target"], row["gt_source_to_target"])}))
  return pairs
