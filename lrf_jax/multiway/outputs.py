"""A multiway registration's outputs: the scans' names (each names a pose file), the merged
cloud, edges.tsv, merged.ply, the poses (one file per scan and KITTI's poses.txt) and the manifest
of an output folder, every file written atomically (`write_outputs`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Sequence

import numpy as np

if TYPE_CHECKING:
  from lrf_jax.multiway.result import MultiwayResult

__all__ = ["EDGE_COLUMNS", "MANIFEST", "POSES_FILE", "check_names", "check_out_dir",
           "check_voxel", "edges_table", "kitti_poses", "merged_cloud", "output_paths",
           "scan_names", "write_merged_ply", "write_outputs"]

# merged_cloud's voxel keys are float64 cell indices cast to int64: exact below 2**53.
MAX_VOXELS_PER_AXIS = float(2**53)
SUFFIXES = (".gz", ".ply", ".pcd", ".xyz", ".txt", ".pts", ".asc", ".npy", ".bin")
# The trajectory in KITTI's pose-file layout; no scan may be named so that its pose file is it.
POSES_FILE = "poses.txt"
RESERVED_NAMES = ("poses",)


def _apply(t: np.ndarray, p: np.ndarray) -> np.ndarray:
  return p @ t[:3, :3].T + t[:3, 3]


# The longest name: its pose file "<name>.txt" fits in one file name (`atomic.NAME_MAX` bytes).
NAME_BYTES = 251


def _fit(name: str, tail: str = "") -> str:
  """`name` cut (whole characters) so that name + tail is at most NAME_BYTES bytes, + tail."""
  room = NAME_BYTES - len(os.fsencode(tail))
  while len(os.fsencode(name)) > room:
    name = name[:-1]
  return name + tail


def _natural_name(scan: Any, k: int) -> str:
  """A path's file name without its cloud suffixes and leading dots, control characters as
  "_", cut to NAME_BYTES; else (an array, or a path without a usable name) "scan<k>"."""
  if isinstance(scan, (str, os.PathLike)):
    name = Path(scan).name
    while Path(name).suffix.lower() in SUFFIXES and Path(name).stem:
      name = Path(name).stem
    name = _fit("".join("_" if ord(c) < 32 or ord(c) == 127 else c for c in name))
    name = name.lstrip(".")  # a hidden file's name would write hidden outputs
    if name:
      return name
  return f"scan{k}"


def scan_names(scans: Sequence[Any]) -> list[str]:
  """Distinct names, each usable as a file name (`check_names`): a path's file name without its
  cloud suffixes (".txt.gz" included; control characters replaced by "_", cut to fit a file
  name), else "scan<k>". Each natural name is kept by its first scan; a later scan with the
  same name (equal ignoring case: one file on a case-insensitive file system) gets "_2", "_3",
  ..., the first of them that is no scan's natural name and not given yet: `d/a.ply d/a_2.ply
  e/a.ply` are a, a_2, a_3. A scan named as a reserved output ("poses": its pose file would be
  poses.txt, the trajectory) gets "poses_2" and so on."""
  natural = [_natural_name(s, k) for k, s in enumerate(scans)]
  taken = {n.casefold() for n in natural} | set(RESERVED_NAMES)
  out: list[str] = []
  given: set[str] = set(RESERVED_NAMES)
  for name in natural:
    if name.casefold() not in given:
      out.append(name)
    else:
      k = 2
      while _fit(name, f"_{k}").casefold() in taken:
        k += 1
      out.append(_fit(name, f"_{k}"))
      taken.add(out[-1].casefold())
    given.add(out[-1].casefold())
  return out


def check_names(names: Sequence[Any], argument: str = "names") -> list[str]:
  """`names` as a list, when each can name its pose file "<name>.txt" in the output folder.

  Raises:
    ValueError: naming `argument`: a name that is not a non-empty string, is "." or "..",
      holds a path separator or a control character (a tab or a newline would also break
      edges.tsv), is longer than NAME_BYTES bytes in UTF-8 (its file name would exceed 255
      bytes), is "poses" (ignoring case: its pose file would be the trajectory poses.txt), or
      equals another one (ignoring case: one file on a case-insensitive file system).
  """
  out = list(names)
  seen: dict[str, int] = {}
  for k, name in enumerate(out):
    problem = None
    if not isinstance(name, str) or not name:
      problem = "expected a non-empty string"
    elif name in (".", "..") or any(sep and sep in name for sep in ("/", os.sep, os.altsep)):
      problem = "expected a file name without a path separator, not '.' or '..'"
    elif any(ord(c) < 32 or ord(c) == 127 for c in name):
      problem = "expected a name without control characters (tabs, newlines)"
    elif len(name.encode("utf-8", "surrogateescape")) > NAME_BYTES:
      problem = (f"is {len(name.encode('utf-8', 'surrogateescape'))} bytes long; expected at "
                 f"most {NAME_BYTES} (its file <name>.txt may be at most 255 bytes)")
    elif name.casefold() in RESERVED_NAMES:
      problem = (f"is reserved (its pose file would be {POSES_FILE}, the trajectory of every "
                 "scan); expected another name")
    elif name.casefold() in seen:
      problem = (f"is the name of scan {seen[name.casefold()]} too (ignoring case); expected "
                 "distinct names, one pose file each")
    if problem:
      shown = name if not isinstance(name, str) or len(name) <= 40 else name[:40] + "..."
      raise ValueError(f"{argument}[{k}]: {shown!r} {problem}")
    seen[name.casefold()] = k
  return out




def check_voxel(clouds: Sequence[np.ndarray], voxel: float) -> None:
  """Refuse, before any registration, a voxel of `merged_cloud` that is too small whatever the
  poses: the merged cloud spans at least the largest scan's diameter / sqrt(3) along some axis.

  Raises:
    ValueError: as `merged_cloud` does ("voxel: ... too small ...").
  """
  if not (np.isfinite(voxel) and voxel > 0):
    raise ValueError(f"voxel: expected a positive size, got {voxel!r}")
  extent = max(float(np.linalg.norm(np.ptp(np.asarray(c), axis=0))) for c in clouds) / np.sqrt(3)
  if extent / voxel >= MAX_VOXELS_PER_AXIS:
    raise ValueError(f"voxel: {voxel:.6g} is too small for the scans' extent (at least "
                     f"{extent:.6g} along an axis): {extent / voxel:.3g} voxels, at most "
                     f"{MAX_VOXELS_PER_AXIS:.3g} (2**53); choose a larger voxel")


def merged_cloud(clouds: Sequence[np.ndarray], result: MultiwayResult, *,
                 voxel: float | None = None) -> tuple[np.ndarray, np.ndarray]:
  """The model's scans in the reference frame, one cloud.

  Args:
    clouds: the n scans' (m_k, 3) points, as given to `register_all`.
    result: its result.
    voxel: optional voxel size (cloud units): one point per occupied voxel, the mean of its
      points, labelled with the scan most of them came from (ties: the earliest).

  Raises:
    ValueError: `voxel` is not positive, or so small that the merged cloud spans 2**53 voxels
      or more along an axis (their integer keys would overflow).

  Returns:
    (points (m, 3) float64, scan (m,) int64 index of the scan each point came from); the scans
    left out contribute nothing.
  """
  pts = [_apply(result.poses[k], np.asarray(clouds[k], np.float64))
         for k in range(len(clouds)) if result.in_model[k]]
  lab = [np.full(len(clouds[k]), k, np.int64) for k in range(len(clouds)) if result.in_model[k]]
  points, scan = np.concatenate(pts), np.concatenate(lab)
  if voxel is None:
    return points, scan
  if not (np.isfinite(voxel) and voxel > 0):
    raise ValueError(f"voxel: expected a positive size, got {voxel!r}")
  extent = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
  if extent / voxel >= MAX_VOXELS_PER_AXIS:  # the int64 voxel keys would overflow or round
    raise ValueError(f"voxel: {voxel:.6g} is too small for the merged cloud's extent "
                     f"({extent:.6g}): {extent / voxel:.3g} voxels along an axis, at most "
                     f"{MAX_VOXELS_PER_AXIS:.3g} (2**53); choose a larger voxel")
  keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
  _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
  inverse = inverse.ravel()
  # float64: numpy's stubs type every bincount as integer, the weighted one included
  mean: np.ndarray = np.stack([np.bincount(inverse, points[:, d]) for d in range(3)], axis=1)
  mean /= counts[:, None]
  n_scans = len(clouds)
  votes = np.bincount(inverse * n_scans + scan, minlength=len(counts) * n_scans)
  return mean, np.argmax(votes.reshape(len(counts), n_scans), axis=1).astype(np.int64)


def kitti_poses(poses: np.ndarray) -> str:
  """Poses as KITTI's pose files hold them: line k is pose k's top 3x4 block [R|t], 12 numbers
  row-major (9 significant digits), so that a point p of scan k is R p + t in the reference
  frame; a pose that is not finite (a scan left out) is a line of 12 `nan`.

  Args:
    poses: (n, 4, 4) poses (`MultiwayResult.poses`).

  Returns:
    n lines, each ending in a newline.
  """
  lines = []
  for pose in np.asarray(poses, np.float64):
    row = pose[:3, :4].ravel() if np.isfinite(pose).all() else np.full(12, np.nan)
    lines.append(" ".join(f"{v:.9g}" for v in row))
  return "".join(line + "\n" for line in lines)


EDGE_COLUMNS = ("source", "target", "verdict", "reason_code", "inliers", "overlap", "residual_mr",
                "graph", "placement", "reason")


def placement(result: MultiwayResult, i: int, j: int) -> str:
  """How an edge's two scans are placed: "-" when one is not in the model; "confident" when
  both are linked to the reference by "success" edges alone; else which of them is placed only
  through "not sure" edges: "source_not_sure", "target_not_sure" or "both_not_sure"."""
  if not (result.in_model[i] and result.in_model[j]):
    return "-"
  sure = (np.ones(len(result.names), bool) if result.confident is None
          else np.asarray(result.confident, bool))
  return {(True, True): "confident", (False, True): "source_not_sure",
          (True, False): "target_not_sure", (False, False): "both_not_sure"}[
              (bool(sure[i]), bool(sure[j]))]


def edges_table(result: MultiwayResult) -> str:
  """The edges as tab-separated text, a header line first (`EDGE_COLUMNS`): the pair (source
  moved onto target), the pairwise verdict and its `reason_code` ("-" when none), inliers,
  overlap, the residual under the final
  poses in mr ("-" when a scan is not in the model), "accepted" or "rejected", the placement of
  its two scans (`placement`) and the pairwise reason."""
  lines = ["\t".join(EDGE_COLUMNS)]
  for e in result.edges:
    res = f"{e.residual_mr:.3f}" if np.isfinite(e.residual_mr) else "-"
    lines.append("\t".join([result.names[e.i], result.names[e.j], e.verdict,
                            e.reason_code or "-", str(e.n_inliers),
                            f"{e.overlap:.3f}", res, "accepted" if e.accepted else "rejected",
                            placement(result, e.i, e.j), " ".join(e.reason.split())]))
  return "\n".join(lines) + "\n"


def write_merged_ply(path: str | os.PathLike, points: np.ndarray, scan: np.ndarray,
                     n_scans: int) -> Path:
  """Binary PLY of the merged cloud with per-point red/green/blue by scan
  (`multiway_figures.scan_colours`) and a `scan` index property, written atomically."""
  import plyfile

  from lrf_jax.io.atomic import atomic_path
  from lrf_jax.multiway.figures import scan_colours
  colours = scan_colours(n_scans)[scan]
  vertex = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                                        ("green", "u1"), ("blue", "u1"), ("scan", "i4")])
  for k, name in enumerate("xyz"):
    vertex[name] = points[:, k]
  for k, name in enumerate(("red", "green", "blue")):
    vertex[name] = colours[:, k]
  vertex["scan"] = scan
  with atomic_path(path) as tmp:
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], text=False,
                    byte_order="<").write(str(tmp))
  return Path(path)


# The list of the files a run wrote into its folder (`write_outputs`), and what it says it is.
MANIFEST = "manifest.json"
MANIFEST_KIND = "lrf_jax multiway outputs"
FIXED_OUTPUTS = (POSES_FILE, "merged.ply", "edges.tsv", "merged.png", "graph.png")
# The job's state in the output folder: the records of the finished pairs (`register_all`'s
# `state_dir`), kept between runs so that a rerun registers no pair twice.
STATE = ".lrf-multiway"


def output_paths(names: Sequence[str], out_dir: str | os.PathLike) -> dict[str, Path]:
  """Every file `write_outputs` may write, keyed by role: "<name>.txt" per scan, "poses.txt",
  "merged.ply", "edges.tsv", "merged.png", "graph.png" and the manifest ("manifest.json").

  Raises:
    ValueError: a name `check_names` refuses (the message names "names").
  """
  d = Path(out_dir)
  out = {f"pose:{n}": d / f"{n}.txt" for n in check_names(names)}
  out.update({k: d / k for k in FIXED_OUTPUTS})
  out["manifest"] = d / MANIFEST
  return out


def _read_manifest(path: Path) -> list[str] | None:
  """The file names a manifest lists; None when it is not one `write_outputs` wrote (unreadable,
  not its JSON, or an entry that is not a plain file name: nothing outside the folder is ever
  listed)."""
  import json
  try:
    data = json.loads(path.read_text(encoding="utf-8"))
  except (OSError, ValueError):
    return None
  if not isinstance(data, dict) or data.get("kind") != MANIFEST_KIND:
    return None
  files = data.get("files")
  if not isinstance(files, list):
    return None
  for f in files:
    if (not isinstance(f, str) or f in ("", ".", "..", MANIFEST) or "\0" in f
        or any(sep and sep in f for sep in ("/", os.sep, os.altsep))):
      return None
  return list(files)


def check_out_dir(out_dir: str | os.PathLike, argument: str = "out_dir") -> list[str]:
  """The files an earlier run listed in `out_dir`'s manifest (what `write_outputs` replaces or
  removes); [] for a new or empty folder (or one holding only a stopped run's `STATE`).

  Raises:
    ValueError: naming `argument`: `out_dir` is not a folder, its name is too long, or it holds
      files but no manifest of an earlier run (a folder of other files is never written into:
      afterwards it would hold a mix of this run's files and files no run wrote), or a manifest
      that is not one `write_outputs` wrote.
  """
  from lrf_jax.io.atomic import path_problem
  d = Path(out_dir).expanduser()
  problem = path_problem(d)
  if problem:
    raise ValueError(f"{argument}: {out_dir} {problem}")
  if not d.exists():
    return []
  if not d.is_dir():
    raise ValueError(f"{argument}: {out_dir} is not a folder")
  manifest = d / MANIFEST
  if not manifest.exists() and not manifest.is_symlink():
    try:  # a run stopped before its outputs leaves only its state: still this job's folder
      empty = next((p for p in d.iterdir() if p.name != STATE), None) is None
    except OSError as e:
      raise ValueError(f"{argument}: could not list {out_dir}: {e.strerror or e}") from None
    if empty:
      return []
    raise ValueError(f"{argument}: {out_dir} is not empty and holds no {MANIFEST} of an earlier "
                     "run; expected a new or empty folder, or one an earlier run wrote (its "
                     "files are then replaced)")
  files = _read_manifest(manifest) if manifest.is_file() else None
  if files is None:
    raise ValueError(f"{argument}: {manifest} is not a manifest of an earlier run's outputs; "
                     "expected a new or empty folder, or one an earlier run wrote")
  return files


def write_outputs(result: MultiwayResult, clouds: Sequence[np.ndarray],
                  out_dir: str | os.PathLike, *, voxel: float | None = None,
                  figures: bool = True) -> list[Path]:
  """Write the model (every file atomically; the folder is created if missing).

  `<name>.txt`: the (4, 4) pose mapping that scan into the reference scan's frame (rows, 9
  significant digits; `numpy.loadtxt` reads it), for the scans in the model only;
  `poses.txt`: the trajectory in KITTI's pose-file layout (`kitti_poses`): line k holds scan
  k's 3x4 pose [R|t] in the reference scan's frame, 12 numbers row-major, 12 `nan` for a scan
  left out;
  `merged.ply`: the merged cloud (`merged_cloud`, `voxel` in cloud units), coloured by scan;
  `edges.tsv`: `edges_table`; with `figures`, `merged.png` and `graph.png`
  (`lrf_jax.multiway.figures`); `manifest.json`: the list of these files.

  The folder ends up holding this run's files only: `out_dir` must be new, empty, or a folder
  an earlier run wrote (`check_out_dir`: it holds that run's manifest). The files the earlier
  run listed and this one does not write (the pose of a scan left out this time, figures) are
  removed, the others replaced; files that no manifest lists are never touched. At every
  moment the manifest lists every file a run may have left, so a run interrupted midway is
  cleaned up by the next one.

  Args:
    result: `register_all`'s result.
    clouds: the scans' (m_k, 3) points.
    out_dir: the folder.
    voxel: optional voxel size of merged.ply (cloud units).
    figures: also draw the two figures.

  Returns:
    The paths written.

  Raises:
    ValueError: `out_dir` as `check_out_dir` refuses it, a name `check_names` refuses, or an
      output path that is a folder, a FIFO, a device or a socket (the message names `out_dir`
      and the path); nothing is written then.
    WriteError: a file could not be written or an earlier run's file removed (the message
      names it).
  """
  import json

  from lrf_jax.io.atomic import WriteError, file_kind, write_text
  d = Path(out_dir)
  check_names(result.names, "result.names")
  earlier = check_out_dir(d)
  paths = output_paths(result.names, d)
  if figures:  # before anything is written
    from lrf_jax.extras import require
    require("plot", "register_all's figures (figures=False skips them)")
  wanted = [paths[f"pose:{n}"] for n, m in zip(result.names, result.in_model) if m]
  wanted += [paths[POSES_FILE], paths["merged.ply"], paths["edges.tsv"]]
  if figures:
    wanted += [paths["merged.png"], paths["graph.png"]]
  for path in wanted + [paths["manifest"]]:
    kind = file_kind(path)
    if kind:
      raise ValueError(f"out_dir: {path} is {kind}; expected a regular file or a new name")
  points, scan = merged_cloud(clouds, result, voxel=voxel)
  try:
    d.mkdir(parents=True, exist_ok=True)
  except OSError as e:
    raise WriteError(d, e) from e

  def manifest(files: list[str]) -> None:
    write_text(paths["manifest"], json.dumps({"kind": MANIFEST_KIND, "files": files},
                                             indent=1) + "\n")

  new = [p.name for p in wanted]
  manifest(list(dict.fromkeys(earlier + new)))  # covers both runs' files until the end
  for name in earlier:  # an earlier run's file this run does not write: removed
    old = d / name
    if name not in new and (old.is_symlink() or old.is_file()):
      try:
        old.unlink()
      except FileNotFoundError:
        pass
      except OSError as e:
        raise WriteError(old, e) from e
  written = []
  for k, name in enumerate(result.names):
    if result.in_model[k]:
      text = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in result.poses[k]) + "\n"
      written.append(write_text(paths[f"pose:{name}"], text))
  written.append(write_text(paths[POSES_FILE], kitti_poses(result.poses)))
  written.append(write_merged_ply(paths["merged.ply"], points, scan, len(result.names)))
  written.append(write_text(paths["edges.tsv"], edges_table(result)))
  if figures:
    from lrf_jax.multiway import figures as multiway_figures
    written.append(multiway_figures.merged_figure(points, scan, result, paths["merged.png"]))
    written.append(multiway_figures.graph_figure(result, clouds, paths["graph.png"]))
  manifest(new)
  return written
