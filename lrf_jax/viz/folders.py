"""The output folders the viewer reads: a multiway model (`lrf-register A B C ... --out-dir D`:
manifest.json, poses.txt, <name>.txt per scan, merged.ply, edges.tsv; `read_model_folder`) and
an `lrf-batch register` folder (results.tsv and <name>.txt per pair; `read_batch_folder`).

A model's scans are shown from merged.ply (the scans at their poses, each point labelled with
its scan); a scan's name is the pose file whose 3x4 block is its line of poses.txt (both are
written with the same digits), and edges.tsv gives each edge's verdict and whether the pose
graph accepted it. A batch folder's pairs are read from their files when picked.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from lrf_jax.viz.scenes import (EDGE_KINDS, MAX_POINTS, ModelScene, PairScene, Thinning,
                                edge_kind, pair_scene, thin)

__all__ = ["BatchPair", "folder_kind", "read_batch_folder", "read_model_folder"]

# results.tsv's columns a register folder has (some of `lrf_jax.batch.jobs.REGISTER_COLUMNS`).
BATCH_COLUMNS = ("name", "source", "target", "status", "success", "reason")
NEITHER = ("is neither a multiway output folder (no manifest.json of `lrf-register ... "
           "--out-dir`) nor an lrf-batch register folder (no results.tsv of `lrf-batch "
           "register`)")


def folder_kind(folder: str | os.PathLike) -> str:
  """"model" for a multiway output folder, "batch" for an `lrf-batch register` folder.

  Raises:
    ValueError: `folder` is not a folder, or is neither kind (the message says what each kind
      holds), or is an `lrf-batch frames` folder.
  """
  from lrf_jax.multiway.outputs import MANIFEST, MANIFEST_KIND
  d = Path(folder).expanduser()
  if not d.is_dir():
    what = "no such folder" if not d.exists() else "not a folder"
    raise ValueError(f"{folder}: {what}; expected a multiway output folder, an lrf-batch "
                     "register folder, or two clouds")
  manifest = d / MANIFEST
  if manifest.is_file():
    try:
      data = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
      raise ValueError(f"{manifest}: not a manifest of lrf-register --out-dir ({e})") from None
    if isinstance(data, dict) and data.get("kind") == MANIFEST_KIND:
      return "model"
  columns = _header(d / "results.tsv")
  if columns is not None:
    if all(c in columns for c in BATCH_COLUMNS):
      return "batch"
    if "scan" in columns:
      raise ValueError(f"{folder}: an lrf-batch frames folder (its results.tsv lists scans); "
                       "lrf-view shows lrf-batch register folders (pairs)")
  raise ValueError(f"{folder}: {NEITHER}")


def _header(path: Path) -> list[str] | None:
  """The columns of a TSV's first line, None when it cannot be read."""
  try:
    with open(path, encoding="utf-8") as f:
      return f.readline().rstrip("\r\n").split("\t")
  except (OSError, UnicodeDecodeError):
    return None


def _poses(path: Path) -> np.ndarray:
  """poses.txt: (n, 12) [R|t] rows, NaN rows for the scans left out."""
  rows = []
  for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
    if not line.strip():
      continue
    try:
      row = [float(v) for v in line.split()]
    except ValueError:
      row = []
    if len(row) != 12:
      raise ValueError(f"{path}: line {k}: expected 12 numbers (a 3x4 pose, KITTI's layout)")
    rows.append(row)
  if not rows:
    raise ValueError(f"{path}: no poses")
  return np.array(rows)


def _names(d: Path, files: list[str], poses: np.ndarray) -> list[str | None]:
  """Each scan's name: the pose file (listed in the manifest, in the scans' order) whose 3x4
  block is the scan's line of poses.txt; None where none is."""
  from lrf_jax.multiway.outputs import POSES_FILE
  names: list[str | None] = [None] * len(poses)
  for file in files:
    if not file.endswith(".txt") or file == POSES_FILE:
      continue
    try:
      pose = np.loadtxt(d / file, ndmin=2)
    except (OSError, ValueError):
      continue
    if pose.shape != (4, 4):
      continue
    match = [k for k in range(len(poses)) if names[k] is None
             and np.array_equal(pose[:3, :4].ravel(), poses[k])]
    if match:
      names[match[0]] = file[:-len(".txt")]
  return names


def _edges(path: Path) -> list[tuple[str, str, str]]:
  """edges.tsv's (source, target, kind) rows ([] without the file)."""
  if not path.is_file():
    return []
  lines = path.read_text(encoding="utf-8").splitlines()
  header = lines[0].split("\t") if lines else []
  if not all(c in header for c in ("source", "target", "verdict", "graph")):
    raise ValueError(f"{path}: expected the columns source, target, verdict and graph")
  col = {c: header.index(c) for c in ("source", "target", "verdict", "graph")}
  out = []
  for line in lines[1:]:
    f = line.split("\t")
    if len(f) >= len(header):
      out.append((f[col["source"]], f[col["target"]],
                  edge_kind(f[col["graph"]] == "accepted", f[col["verdict"]])))
  return out


def read_model_folder(folder: str | os.PathLike, *, max_points: int = MAX_POINTS,
                      seed: int = 0) -> ModelScene:
  """A multiway output folder as a `ModelScene`: merged.ply's points split by scan (each
  thinned to `max_points`), the names of the pose files, edges.tsv's edges.

  Raises:
    ValueError: not a multiway output folder (`folder_kind`), or a file the folder must hold
      is missing or not what `lrf-register --out-dir` writes (the message names it).
  """
  from lrf_jax.io.ply import read_ply
  from lrf_jax.multiway.figures import scan_colours
  from lrf_jax.multiway.outputs import MANIFEST, POSES_FILE
  if folder_kind(folder) != "model":
    raise ValueError(f"{folder}: an lrf-batch register folder, not a multiway output folder")
  d = Path(folder).expanduser()
  files = json.loads((d / MANIFEST).read_text(encoding="utf-8")).get("files") or []
  for required in (POSES_FILE, "merged.ply"):
    if not (d / required).is_file():
      raise ValueError(f"{folder}: holds no {required}; expected the outputs of lrf-register "
                       "--out-dir (rerun it)")
  poses = _poses(d / POSES_FILE)
  names = _names(d, [f for f in files if isinstance(f, str)], poses)
  try:
    ply = read_ply(d / "merged.ply", elements=False)
  except FileNotFoundError as e:
    raise ValueError(str(e)) from None
  scan = ply.vertex_attributes.get("scan")
  if scan is None:
    raise ValueError(f"{d / 'merged.ply'}: no `scan` property (expected lrf-register's merged "
                     "cloud)")
  scan = np.asarray(scan, np.int64)
  if len(scan) and (scan.min() < 0 or scan.max() >= len(poses)):
    raise ValueError(f"{d / 'merged.ply'}: scan indices outside [0, {len(poses)}) "
                     f"({POSES_FILE} has {len(poses)} poses)")
  edges = _edges(d / "edges.tsv")
  named = set(n for n in names if n)
  unnamed = list(dict.fromkeys(n for s, t, _ in edges for n in (s, t) if n not in named))
  in_model = np.isfinite(poses).all(axis=1)
  points: list[np.ndarray | None] = []
  thinned = []
  for k in range(len(poses)):
    if names[k] is None:  # left out (NaN pose), or a pose file that is missing
      names[k] = unnamed.pop(0) if not in_model[k] and unnamed else f"scan{k}"
    p = ply.points[scan == k]
    if not in_model[k] or not len(p):
      points.append(None)
      continue
    shown = thin(p, max_points, seed + k)
    if len(shown) < len(p):
      thinned.append(Thinning(str(names[k]), len(p), len(shown)))
    points.append(shown)
  index = {n: k for k, n in enumerate(names)}
  shown_edges = tuple((index[s], index[t], kind) for s, t, kind in edges
                      if s in index and t in index and points[index[s]] is not None
                      and points[index[t]] is not None)
  kinds = [kind for _, _, kind in edges]
  return ModelScene(tuple(str(n) for n in names), tuple(points), scan_colours(len(poses)),
                    shown_edges, {k: kinds.count(k) for k in EDGE_KINDS}, tuple(thinned),
                    str(folder))


@dataclasses.dataclass(frozen=True)
class BatchPair:
  """One pair of an `lrf-batch register` folder (a row of results.tsv).

  Attributes:
    name: the item's name (its transform is <name>.txt).
    source: the source's path; target: the target's.
    status: "done", "error" or "transient".
    verdict: one line: the verdict and reason, or the error.
    transform: the path of its transform file, None when there is none.
  """
  name: str
  source: str
  target: str
  status: str
  verdict: str
  transform: Path | None

  def label(self) -> str:
    """The pair as the picker lists it: its name and verdict."""
    head = self.verdict.split(":", 1)[0]
    return f"{self.name} ({head})"

  def scene(self, *, max_points: int = MAX_POINTS, seed: int = 0) -> PairScene:
    """The pair's clouds and transform, read now.

    Raises:
      ValueError, FileNotFoundError: a cloud or the transform cannot be read.
    """
    from lrf_jax.io.poses import read_xf
    t = None if self.transform is None else read_xf(self.transform)
    return pair_scene(self.source, self.target, t, name=self.name, verdict=self.verdict,
                      max_points=max_points, seed=seed,
                      labels=(f"{self.name}: source", f"{self.name}: target"))


def read_batch_folder(folder: str | os.PathLike) -> list[BatchPair]:
  """The pairs of an `lrf-batch register` folder, in results.tsv's order.

  Raises:
    ValueError: not an lrf-batch register folder (`folder_kind`), or its results.tsv cannot be
      read or lists no pair.
  """
  if folder_kind(folder) != "batch":
    raise ValueError(f"{folder}: a multiway output folder, not an lrf-batch register folder")
  d = Path(folder).expanduser()
  path = d / "results.tsv"
  try:
    lines = path.read_text(encoding="utf-8").splitlines()
  except (OSError, UnicodeDecodeError) as e:
    raise ValueError(f"{path}: cannot be read ({e})") from None
  header = lines[0].split("\t")
  col = {c: header.index(c) for c in BATCH_COLUMNS}
  pairs = []
  for line in lines[1:]:
    f = line.split("\t")
    if len(f) < len(header):
      continue
    cell = {c: f[k] for c, k in col.items()}
    if cell["status"] == "done":
      verdict = "success" if cell["success"] == "True" else "not sure"
      verdict += f": {cell['reason']}" if cell["reason"] else ""
    else:
      error = f[header.index("error")] if "error" in header else ""
      verdict = f"{cell['status']}: {error}" if error else cell["status"]
    t = d / f"{cell['name']}.txt"
    pairs.append(BatchPair(cell["name"], cell["source"], cell["target"], cell["status"],
                           verdict, t if cell["status"] == "done" and t.is_file() else None))
  if not pairs:
    raise ValueError(f"{path}: lists no pair")
  return pairs
