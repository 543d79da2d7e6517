"""Scan sets: a folder of a user's own scans and their poses, as model/scene `Pair`s.

A scan set is one folder holding scans in any format `lrf_jax.io.read_cloud` reads and ONE pose
file, in one of three layouts::

    poses.txt          KITTI's pose-file layout: line k is the 3x4 pose [R|t] (12 numbers,
                       row-major) of the k-th scan in name order, mapping it into one common
                       frame (p_common = R p_k + t). A single `poses_<anything>.txt` (e.g. this
                       project's `poses_DERIVED.txt`) is read the same way when there is no
                       poses.txt. Lines starting with '#' and blank lines are skipped; a line of
                       12 `nan` (`lrf-register`'s trajectory for a scan it left out) gives that
                       scan no pose: it takes part in no pair.
    gt.log             3DMatch's ground truth beside fragments `cloud_bin_<k>.<ext>`: records
                       "i j n" (n is not read) and a 4x4 matrix mapping fragment j onto
                       fragment i. Records naming a fragment that is not in the folder are
                       skipped (a subset of a scene's fragments may be copied).
    <name>.conf        a Stanford scan-alignment file (`bmesh FILE tx ty tz qx qy qz qw`,
                       `lrf_jax.io.read_stanford_conf`: world = R(q)ᵀ p + t); the scans are the
                       files it names.

"Name order" compares the digits in names as numbers (scan2 before scan10; zero-padded names
such as KITTI's 000000.bin sort the same either way). With poses.txt the scans are the files of
the folder's most common cloud suffix (.bin, .ply, ...; other files, e.g. a README.txt beside
.bin sweeps, are ignored and listed in `ScanSet.ignored`). The published poses are printed with
a few digits (3DMatch's gt.log: up to 5e-4 off orthonormal): a rotation within `POSE_PROJECT`
(1e-2, the rule of `register(init=...)`) of orthonormal is projected to the nearest rotation,
with one `ProjectedRotation` warning per file.

Resolution: each scan is read by `cache.load_scan`, at its working resolution
(`lrf_jax.geometry.resolution.working_resolution`: the mean nearest-neighbor distance of a
clean scan or fragment -- what the other data sets' `mesh_resolution` gives -- the mean edge
length of a mesh, and for an uneven cloud such as a raw LiDAR sweep the area-weighted median
spacing, the sweep then thinned to it by voxel averaging as `compute_frames` thins). A pair's mr
is `resolution.pair_resolution` of its two scans (the source's, unless one is uneven or they
differ more than 2-fold: the coarser).

Pairs: every candidate (with pose files: each two scans i < j in name order, source i and target
j; with gt.log: each record, source j and target i) whose overlap -- the fraction of the source's
points within `OVERLAP_MR` (2) mr of the target under the ground truth -- is at least
`MIN_OVERLAP` (30 %). The overlap is measured on a seeded subsample of at most
`OVERLAP_POINTS` (2000) source points (`np.random.default_rng(0)`, so it depends only on the
number of points), after a bounding-box test that settles most distant pairs at once.

Each pair is a `Pair`: model = source, scene = target, transform source -> target,
correspondence "nearest", dataset = the folder's name. Sensor positions (`model_viewpoint`,
`scene_viewpoint`) are set where the layout says each scan is in its sensor's frame: KITTI's
layout (each sweep in its Velodyne's frame: the origin) and 3DMatch's (each fragment in its first
camera's frame: the origin, approximately, since a fragment fuses 50 frames); a .conf says
nothing about where its scanner stood, so those pairs carry none. An optional `viewpoint.txt`
in the folder overrides this for every scan: three numbers, the sensor position in each scan's
own coordinates (the Stanford bunny's Cyberware scans: 0 0 1), or `none`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lrf_jax.datasets.cache import Scan, load_scan
from lrf_jax.datasets.pair import Pair, repeatability_keypoints, transform_points
from lrf_jax.geometry.resolution import pair_resolution
from lrf_jax.io import read_3dmatch_log, read_stanford_conf
from lrf_jax.io.validation import ProjectedRotation, bad_input, check_rigid

MIN_OVERLAP = 0.30
OVERLAP_MR = 2.0
OVERLAP_POINTS = 2000
OVERLAP_SEED = 0
# As `lrf_jax.registration.refine.INIT_PROJECT`: published poses are printed with a few digits.
POSE_PROJECT = 1e-2
# The share of a folder's scans (the last in name order, at least 2) `split_by_scan` holds out.
HELD_OUT = 0.2

KITTI_POSES = "poses.txt"
THREEDMATCH_LOG = "gt.log"
VIEWPOINT_FILE = "viewpoint.txt"
FORMATS = ("kitti", "3dmatch", "stanford")
_FRAGMENT = re.compile(r"^cloud_bin_(\d+)(\..+)$")
_TEXT = (".xyz", ".txt", ".pts", ".asc")
_SUFFIXES = (".ply", ".pcd", ".npy", ".bin", ".las", ".laz", ".e57") + _TEXT  # read_cloud's


@dataclasses.dataclass(frozen=True, eq=False)
class ScanSet:
  """A folder of scans, its poses and its overlapping pairs.

  Attributes:
    name: the data set's name: the folder's name (`folder_name`).
    folder: the folder.
    format: "kitti" (poses.txt), "3dmatch" (gt.log) or "stanford" (.conf).
    pose_file: the pose file read.
    scans: the scans' file names, in name order (`natural_key`).
    poses: (n, 4, 4) float64 scan -> common frame, NaN for a scan without a pose; None for
      gt.log (pairwise ground truth only).
    candidates: (source, target, overlap) of every candidate pair, as indices into `scans`;
      overlap is the measured fraction (0 where the bounding boxes already exclude it).
    pairs: the candidates with overlap >= the rule's minimum, as `Pair`s.
    ignored: files of the folder that are neither a scan, the pose file nor viewpoint.txt.
    viewpoint: the sensor position every pair carries on both sides (in each scan's own
      coordinates), or None.
    notes: what was skipped and why (gt.log records naming absent fragments, scans without a
      pose).
  """

  name: str
  folder: Path
  format: str
  pose_file: Path
  scans: tuple[str, ...]
  poses: np.ndarray | None
  candidates: tuple[tuple[int, int, float], ...]
  pairs: tuple[Pair, ...]
  ignored: tuple[str, ...] = ()
  notes: tuple[str, ...] = ()
  viewpoint: np.ndarray | None = None


def folder_name(folder: str | os.PathLike) -> str:
  """A scan set's name: its folder's last component as given (".", a trailing slash and ".."
  resolved, symbolic links not: a link names the set it points to)."""
  return Path(os.path.abspath(os.path.expanduser(folder))).name


def natural_key(name: str) -> tuple:
  """Sort key comparing the digit runs of `name` as numbers ("scan2" < "scan10")."""
  return tuple((0, int(t), t) if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name)
               if t)


def cloud_suffix(name: str) -> str | None:
  """The cloud suffix of a file name (".bin", ".ply", ".txt.gz", ...; lower case), or None for a
  name `read_cloud` does not read."""
  lower = name.lower()
  for s in _TEXT:
    if lower.endswith(s + ".gz"):
      return s + ".gz"
  suffix = Path(lower).suffix
  return suffix if suffix in _SUFFIXES and not lower.endswith(".pcd.bin") else None


def scan_stem(name: str) -> str:
  """A scan's name without its cloud suffix ("000000.bin" -> "000000")."""
  suffix = cloud_suffix(name)
  return name[:-len(suffix)] if suffix else name


def find_pose_file(folder: Path) -> tuple[str, Path]:
  """The folder's pose file and its format ("kitti", "3dmatch" or "stanford").

  Raises:
    FileNotFoundError: not a folder, or no pose file in it (the message lists the layouts).
    ValueError: more than one pose file.
  """
  if not folder.is_dir():
    raise FileNotFoundError(f"{folder}: scan set: expected a folder of scans and a pose file, "
                            "found " + ("a file" if folder.exists() else "no such folder"))
  names = sorted(p.name for p in folder.iterdir() if p.is_file())
  found: list[tuple[str, str]] = []
  kitti = [n for n in names if n.startswith("poses_") and n.endswith(".txt")]
  if KITTI_POSES in names:
    found.append(("kitti", KITTI_POSES))
  elif kitti:
    found += [("kitti", n) for n in kitti]
  if THREEDMATCH_LOG in names:
    found.append(("3dmatch", THREEDMATCH_LOG))
  found += [("stanford", n) for n in names if n.endswith(".conf")]
  if not found:
    raise FileNotFoundError(
        f"{folder}: pose file: expected one of {KITTI_POSES} (KITTI's layout: one 3x4 pose per "
        f"scan in name order), {THREEDMATCH_LOG} beside cloud_bin_<k> fragments (3DMatch) or a "
        f"Stanford .conf, found none among {len(names)} files"
        + (f" ({', '.join(names[:8])}{', ...' if len(names) > 8 else ''})" if names else ""))
  if len(found) > 1:
    raise ValueError(f"{folder}: pose file: expected one, found {len(found)} "
                     f"({', '.join(n for _, n in found)}); keep one per folder")
  return found[0][0], folder / found[0][1]


def read_kitti_poses(path: str | os.PathLike) -> tuple[np.ndarray, list[int]]:
  """Poses in KITTI's pose-file layout: per line 12 numbers, the 3x4 [R|t] row-major.

  Blank lines and lines starting with '#' are skipped; a line of 12 `nan` is a scan without a
  pose (a NaN matrix). Rotations within `POSE_PROJECT` of orthonormal are projected.

  Args:
    path: the file.

  Returns:
    ((n, 4, 4) float64 poses, the file's line number of each).

  Raises:
    ValueError: a line that is not 12 numbers, partly NaN, or not a rigid pose; the message
      names the file and the line.
  """
  p = Path(path)
  poses, lines = [], []
  for number, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
    text = line.strip()
    if not text or text.startswith("#"):
      continue
    field = f"line {number}"
    try:
      values = np.array([float(t) for t in text.split()])
    except ValueError:
      raise bad_input(p, field, "12 numbers (a 3x4 pose [R|t], row-major: KITTI's layout)",
                      f"a non-numeric token in {text[:60]!r}") from None
    if len(values) != 12:
      raise bad_input(p, field, "12 numbers (a 3x4 pose [R|t], row-major: KITTI's layout)",
                      f"{len(values)} numbers")
    if np.isnan(values).all():
      poses.append(np.full((4, 4), np.nan))
    else:
      if not np.isfinite(values).all():
        raise bad_input(p, field, "12 finite numbers, or 12 nan (a scan without a pose)",
                        f"{int(np.sum(~np.isfinite(values)))} non-finite numbers")
      poses.append(check_rigid(np.vstack([values.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]]), p,
                               field, project=POSE_PROJECT))
    lines.append(number)
  if not poses:
    raise bad_input(p, "lines", "one 3x4 pose per scan", "no pose")
  return np.stack(poses), lines


def read_viewpoint(path: str | os.PathLike) -> np.ndarray | None:
  """A scan set's `viewpoint.txt`: 3 numbers x y z (the sensor position in each scan's own
  coordinates) or the word `none`; '#' starts a comment.

  Raises:
    ValueError: anything else (the message names the file).
  """
  p = Path(path)
  tokens = [t for line in p.read_text(errors="replace").splitlines()
            for t in line.split("#", 1)[0].split()]
  if [t.lower() for t in tokens] == ["none"]:
    return None
  try:
    values = np.array([float(t) for t in tokens])
  except ValueError:
    values = np.array([np.nan])
  if values.shape != (3,) or not np.isfinite(values).all():
    raise bad_input(p, "viewpoint", "3 finite numbers x y z (the sensor position in each scan's "
                    "own coordinates) or 'none'", repr(" ".join(tokens)[:60]))
  return values


def _one_warning(fn, *args, **kwargs):
  """`fn(*args, **kwargs)` with its `ProjectedRotation` warnings (one per pose) folded into one
  that gives how many were projected and the largest deviation; other warnings pass."""
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    out = fn(*args, **kwargs)
  projected = []
  for w in caught:
    if issubclass(w.category, ProjectedRotation):
      projected.append(str(w.message))
    else:
      warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
  if projected:
    figures = [float(m) for text in projected
               for m in re.findall(r"is ([0-9.eE+-]+) off orthonormal", text)]
    worst = f" (at most {max(figures):.3g})" if figures else ""
    source = projected[0].split(": ", 1)[0]
    warnings.warn(ProjectedRotation(
        f"{source}: {len(projected)} pose(s) off orthonormal{worst}, beyond the readers' 1e-4 "
        f"but within {POSE_PROJECT:g}: projected to the nearest rotation"), stacklevel=3)
  return out


def _scans_by_suffix(folder: Path, pose_file: Path) -> tuple[list[str], list[str]]:
  """(scans, ignored): the files of the folder's most common cloud suffix, in name order."""
  files = [p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
           and p.name not in (pose_file.name, VIEWPOINT_FILE)]
  by_suffix: dict[str, list[str]] = {}
  for name in files:
    suffix = cloud_suffix(name)
    if suffix:
      by_suffix.setdefault(suffix, []).append(name)
  if not by_suffix:
    raise FileNotFoundError(f"{folder}: scans: expected files read_cloud reads (.bin, .ply, "
                            f".pcd, .npy, .xyz/.txt) beside {pose_file.name}, found none")
  counts = sorted(((len(v), k) for k, v in by_suffix.items()), reverse=True)
  if len(counts) > 1 and counts[0][0] == counts[1][0]:
    raise ValueError(f"{folder}: scans: expected the scans in one format, found as many "
                     f"{counts[0][1]} as {counts[1][1]} files ({counts[0][0]} each); keep one "
                     "format per folder")
  scans = sorted(by_suffix[counts[0][1]], key=natural_key)
  return scans, sorted(set(files) - set(scans), key=natural_key)


def _kitti_layout(folder: Path, pose_file: Path):
  scans, ignored = _scans_by_suffix(folder, pose_file)
  poses, lines = _one_warning(read_kitti_poses, pose_file)
  if len(poses) != len(scans):
    shown = ", ".join(scans[:3]) + (f", ..., {scans[-1]}" if len(scans) > 3 else "")
    raise bad_input(pose_file, "lines", f"{len(scans)} poses, one per scan in name order "
                    f"({shown})", f"{len(poses)} (lines {lines[0]}-{lines[-1]})")
  missing = [s for s, t in zip(scans, poses) if not np.isfinite(t).all()]
  notes = [f"{len(missing)} scan(s) without a pose (a nan line): {', '.join(missing)}"] \
      if missing else []
  candidates = [(i, j) for i in range(len(scans)) for j in range(i + 1, len(scans))
                if np.isfinite(poses[i]).all() and np.isfinite(poses[j]).all()]
  truths = {(i, j): np.linalg.inv(poses[j]) @ poses[i] for i, j in candidates}
  return scans, poses, truths, ignored, notes


def _stanford_layout(folder: Path, pose_file: Path):
  conf = _one_warning(read_stanford_conf, pose_file)
  missing = [n for n in conf if not (folder / n).is_file()]
  if missing:
    raise FileNotFoundError(f"{pose_file}: scans: expected the files it names in {folder}, "
                            f"found no {', '.join(missing)}")
  scans = sorted(conf, key=natural_key)
  poses = np.stack([conf[n] for n in scans])
  truths = {(i, j): np.linalg.inv(poses[j]) @ poses[i]
            for i in range(len(scans)) for j in range(i + 1, len(scans))}
  ignored = sorted((p.name for p in folder.iterdir() if p.is_file() and p.name not in conf
                    and p != pose_file and p.name != VIEWPOINT_FILE), key=natural_key)
  return scans, poses, truths, ignored, []


def _threedmatch_layout(folder: Path, pose_file: Path):
  fragments: dict[int, str] = {}
  ignored = []
  for p in folder.iterdir():
    m = _FRAGMENT.match(p.name)
    if not (p.is_file() and m and cloud_suffix(p.name)):
      if p.is_file() and p != pose_file and p.name != VIEWPOINT_FILE:
        ignored.append(p.name)
      continue
    k = int(m.group(1))
    if k in fragments:
      raise ValueError(f"{folder}: fragment {k}: expected one file cloud_bin_{k}.<ext>, found "
                       f"{fragments[k]} and {p.name}")
    fragments[k] = p.name
  if not fragments:
    raise FileNotFoundError(f"{folder}: scans: expected fragments cloud_bin_<k>.<ext> beside "
                            f"{pose_file.name}, found none")
  entries = _one_warning(read_3dmatch_log, pose_file, project=POSE_PROJECT)
  scans = [fragments[k] for k in sorted(fragments)]
  index = {k: n for n, k in enumerate(sorted(fragments))}
  truths, absent = {}, 0
  for e in entries:
    if e.i not in index or e.j not in index:
      absent += 1
      continue
    if e.i == e.j:
      raise bad_input(pose_file, f"record 'i j n' = {e.i} {e.j} {e.n}",
                      "two different fragments", f"fragment {e.i} twice")
    truths[index[e.j], index[e.i]] = e.transform  # fragment j (source) onto fragment i (target)
  notes = [f"{absent} of {len(entries)} records of {pose_file.name} name a fragment that is "
           "not in the folder: skipped"] if absent else []
  return scans, None, truths, sorted(ignored, key=natural_key), notes


def overlap(source: np.ndarray, target: np.ndarray, transform: np.ndarray, distance: float, *,
            tree: cKDTree | None = None, n_points: int = OVERLAP_POINTS) -> float:
  """The fraction of the source's points within `distance` of the target once moved by
  `transform`, measured on a seeded subsample of at most `n_points` source points.

  Args:
    source: (n, 3) source points.
    target: (m, 3) target points.
    transform: (4, 4) source -> target.
    distance: the distance (the points' units).
    tree: a cKDTree of `target`, if already built.
    n_points: the subsample's size (`np.random.default_rng(OVERLAP_SEED)`, by index).

  Returns:
    The fraction in [0, 1].
  """
  n = len(source)
  rng = np.random.default_rng(OVERLAP_SEED)
  pick = np.sort(rng.choice(n, size=min(n, n_points), replace=False))
  moved = transform_points(transform, source[pick])
  lo, hi = target.min(axis=0) - distance, target.max(axis=0) + distance
  if np.any(moved.max(axis=0) < lo) or np.any(moved.min(axis=0) > hi):
    return 0.0
  inside = np.all((moved >= lo) & (moved <= hi), axis=1)
  if not inside.any():
    return 0.0
  tree = tree if tree is not None else cKDTree(target)
  dist, _ = tree.query(moved[inside], distance_upper_bound=distance)
  return float(np.isfinite(dist).sum() / len(moved))


def _pair(name: str, scans: list[str], loaded: dict[int, Scan], i: int, j: int,
          transform: np.ndarray, fmt: str, fraction: float,
          viewpoint: np.ndarray | None) -> Pair:
  a, b = loaded[i], loaded[j]
  mr = pair_resolution(a.resolution, b.resolution, (scans[i], scans[j]))
  definition = a.resolution.definition if mr == a.resolution.mr else b.resolution.definition
  return Pair(
      name=f"{scan_stem(scans[i])}->{scan_stem(scans[j])}", dataset=name,
      model_points=a.points, scene_points=b.points, model_faces=a.faces, scene_faces=b.faces,
      transform=np.array(transform, np.float64), mr=float(mr), mr_definition=definition,
      correspondence="nearest",
      meta={"scans": (scans[i], scans[j]), "scan_index": (i, j), "overlap": fraction,
            "format": fmt, "thinned_voxel": (a.voxel, b.voxel),
            "raw_points": (a.raw_count, b.raw_count)},
      model_viewpoint=viewpoint, scene_viewpoint=viewpoint)


def read_scan_set(folder: str | os.PathLike, *, min_overlap: float = MIN_OVERLAP,
                  overlap_mr: float = OVERLAP_MR, overlap_points: int = OVERLAP_POINTS,
                  cache_dir: str | os.PathLike | None = None,
                  use_cache: bool = True) -> ScanSet:
  """Reads a scan set: its pose file, its scans (`cache.load_scan`) and its overlapping pairs.

  Args:
    folder: the folder (see the module docstring for its layouts).
    min_overlap: the smallest overlap a pair is kept with (fraction of the source's points).
    overlap_mr: the distance, in the pair's mr, a source point must lie within of the target.
    overlap_points: the size of the source subsample the overlap is measured on.
    cache_dir: the scans' disk cache (default `cache.default_cache_dir()`).
    use_cache: read and write that disk cache.

  Returns:
    The `ScanSet`; its pairs in candidate order.

  Raises:
    FileNotFoundError: not a folder, no pose file, no scan, a scan a .conf names is absent.
    ValueError: several pose files, a malformed pose file (file, line and what was expected), a
      pose count other than the scan count, fewer than 2 scans with poses, a bad scan file, or
      no pair reaching `min_overlap` (the message gives the largest overlap found).
  """
  folder = Path(folder).expanduser()
  if not (0.0 < min_overlap <= 1.0 and overlap_mr > 0 and overlap_points >= 1):
    raise ValueError(f"scan set {folder}: expected min_overlap in (0, 1], overlap_mr > 0 and "
                     f"overlap_points >= 1, got {min_overlap}, {overlap_mr}, {overlap_points}")
  fmt, pose_file = find_pose_file(folder)
  layout = {"kitti": _kitti_layout, "stanford": _stanford_layout,
            "3dmatch": _threedmatch_layout}[fmt]
  scans, poses, truths, ignored, notes = layout(folder, pose_file)
  used = sorted({k for ij in truths for k in ij})
  if len(used) < 2:
    raise ValueError(f"{pose_file}: pairs: expected poses for at least 2 scans of {folder}, "
                     f"found {len(used)}")
  name = folder_name(folder)
  viewpoint = np.zeros(3) if fmt in ("kitti", "3dmatch") else None
  if (folder / VIEWPOINT_FILE).is_file():
    viewpoint = read_viewpoint(folder / VIEWPOINT_FILE)
  loaded = {k: load_scan(folder / scans[k], cache_dir=cache_dir, use_cache=use_cache)
            for k in used}
  trees: dict[int, cKDTree] = {}
  candidates, pairs = [], []
  for (i, j), transform in truths.items():
    a, b = loaded[i], loaded[j]
    mr = pair_resolution(a.resolution, b.resolution, (scans[i], scans[j]))
    if j not in trees:
      trees[j] = cKDTree(b.points)
    fraction = overlap(a.points, b.points, transform, overlap_mr * mr, tree=trees[j],
                       n_points=overlap_points)
    candidates.append((i, j, fraction))
    if fraction >= min_overlap:
      pairs.append(_pair(name, scans, loaded, i, j, transform, fmt, fraction, viewpoint))
  if not pairs:
    best = max(candidates, key=lambda c: c[2])
    raise ValueError(
        f"{folder}: pairs: expected at least one pair of scans overlapping by {min_overlap:.0%} "
        f"(source points within {overlap_mr:g} mr of the target under the poses), found none "
        f"among {len(candidates)} candidates; the largest is {best[2]:.1%} "
        f"({scans[best[0]]} -> {scans[best[1]]}). Check that the poses map each scan into the "
        "common frame (not the inverse) and follow the scans' name order")
  return ScanSet(name, folder, fmt, pose_file, tuple(scans), poses, tuple(candidates),
                 tuple(pairs), tuple(ignored), tuple(notes), viewpoint)


def load_scan_set(folder: str | os.PathLike, **kwargs) -> list[Pair]:
  """The overlapping pairs of a scan set (`read_scan_set(folder, **kwargs).pairs`)."""
  return list(read_scan_set(folder, **kwargs).pairs)


def split_by_scan(scan_set: ScanSet, held_out: float = HELD_OUT) -> tuple[list[Pair], list[Pair]]:
  """Training and held-out pairs of one folder, split by scan.

  The last `held_out` of the scans in name order (at least 2) are held out: the pairs between
  two held-out scans validate, the pairs between two other scans train, and the pairs joining
  the two parts are used by neither (no validation pair shares a scan with a training pair).

  Returns:
    (training pairs, held-out pairs).

  Raises:
    ValueError: either part is empty (the message says what to do instead).
  """
  n = len(scan_set.scans)
  first = n - max(2, math.ceil(held_out * n))
  train = [p for p in scan_set.pairs if max(p.meta["scan_index"]) < first]
  val = [p for p in scan_set.pairs if min(p.meta["scan_index"]) >= first]
  if not train or not val:
    raise ValueError(
        f"{scan_set.folder}: split by scan: holding out its last {n - first} of {n} scans "
        f"({', '.join(scan_set.scans[first:first + 3])}{', ...' if n - first > 3 else ''}) "
        f"leaves {len(train)} training and {len(val)} validation pair(s); give held-out scans "
        "of their own (val_scans=DIR), or no validation (val_pairs=0)")
  return train, val


def training_correspondences(pair: Pair, *, max_dist_mr: float = 0.5, exclude_n: int = 1000,
                             exclude_seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """Every model point of a scan pair with a ground-truth counterpart: its scene point nearest
  to it under the ground truth, when within `max_dist_mr` mr (the repeatability protocol's rule),
  each scene point used once (by the first model point in index order), the evaluation
  keypoints (`repeatability_keypoints(pair, exclude_n, exclude_seed)`) left out.

  Returns:
    (model_idx, scene_idx): (k,) int64 each, model_idx ascending; scene point scene_idx[i]
    corresponds to model point model_idx[i].
  """
  dist, nearest = cKDTree(pair.scene_points).query(
      pair.model_in_scene(), distance_upper_bound=max_dist_mr * pair.mr)
  ok = np.isfinite(dist)
  if exclude_n > 0:
    ok[repeatability_keypoints(pair, exclude_n, exclude_seed, max_dist_mr)[0]] = False
  model_idx = np.flatnonzero(ok)
  _, first = np.unique(nearest[model_idx], return_index=True)
  model_idx = np.sort(model_idx[first])
  return model_idx.astype(np.int64), nearest[model_idx].astype(np.int64)
