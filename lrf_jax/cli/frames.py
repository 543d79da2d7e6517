"""`lrf-frames CLOUD --out F.npz`: local reference frames for the keypoints of one's own file.

Reads any cloud or mesh `lrf_jax.io.read_cloud` reads (PLY, PCD, XYZ/TXT(.gz), NPY), picks
keypoints (N seeded random points, all points, ISS keypoints, or with --voxel-mr one point per
voxel of S mr; --voxel-mr and --keypoints exclude each other), computes their frames (and
optionally a descriptor) and writes an .npz with `keypoints` (indices), `positions`,
`frames` (m, 3, 3, rows x, y, z), `valid` (m,), `radius`, `mr`, `method`, `weights`,
`confidence` (m,) for a method that defines one (lrf_net_plus: how sure each z sign is, in
[0, 1], `compute_frames(..., return_confidence=True)`) and `descriptors` when asked; `--png`
draws the frames on the cloud. With `--pair B --gt T` (T the
4x4 ground truth mapping the cloud onto B: a text file as `lrf_jax.io.read_xf` reads, or a
(4, 4) .npy) the keypoints are drawn among the points whose image under T has a point of B
within 0.5 mr, their frames are also computed on B at the corresponding points (same radius),
the .npz also holds `pair_keypoints`, `pair_frames`, `pair_valid`, `pair_confidence` (where
`confidence` is), `meancos` (per keypoint) and `gt`, the mean MeanCos is printed, and `--png`
draws the repeatability figure
(`lrf_jax.cli.plot.repeatability`). `--out` gets the suffix .npz
when it has none (the path printed is the one written). Outputs are written atomically (a
failed write leaves the previous file) and may not be the input file; every bad argument or
unwritable output is one `error:` line and exit code 2, checked before any work where it can
be. This file is intentionally thin: the work is `lrf_jax.compute_frames`.

    lrf-frames scan.ply --out scan_frames.npz --keypoints 2000 --viewpoint 0 0 0 --png f.png
    lrf-frames a.ply --pair b.ply --gt a_to_b.txt --out ab.npz --png repeatability.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.cli.help import DefaultsHelpFormatter


# Smallest --voxel-mr: voxels of a tenth of the point spacing already hold one point each.
MIN_VOXEL_MR = 0.1
FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
_ASCII_DIGITS = frozenset("0123456789")


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(prog="lrf-frames", description="Local reference frames of the "
                               "keypoints of a cloud or mesh file, written to an .npz; with "
                               "--pair and --gt, also their repeatability on a second scan.",
                               formatter_class=DefaultsHelpFormatter)
  ap.add_argument("cloud", help="PLY, PCD, XYZ/TXT(.gz) or NPY file")
  ap.add_argument("--out", required=True,
                  help="the .npz to write: keypoints, positions, frames (m, 3, 3; rows x, y, "
                       "z), valid, radius, mr, method, weights; confidence (m,) in [0, 1] for "
                       "methods that define one (lrf_net_plus: how sure each z sign is; 0: a "
                       "guess, e.g. a flat patch without --viewpoint); descriptors with "
                       "--descriptor; with --pair also pair_keypoints, pair_frames, pair_valid, "
                       "pair_confidence, meancos, gt")
  ap.add_argument("--keypoints", default=None,
                  help="N seeded random points, 'all', or 'iss' (ISS keypoints); none given: "
                       "1000")
  ap.add_argument("--voxel-mr", type=float, default=None,
                  help=f"keypoints: the point nearest each voxel centre, voxels of S mr, "
                       f"S >= {MIN_VOXEL_MR:g} (instead of --keypoints)")
  ap.add_argument("--method", default="lrf_net_plus",
                  help="a key of lrf_jax.METHODS (print(lrf_jax.METHODS) lists them)")
  ap.add_argument("--radius-mr", type=float, default=15.0,
                  help="support radius in mesh resolutions (15: the paper's)")
  ap.add_argument("--viewpoint", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                  help="sensor position of a single-view scan (orients normals and z)")
  ap.add_argument("--descriptor", default=None,
                  help="also a descriptor on the frames (snapshots, shot, rops, toldi)")
  ap.add_argument("--seed", type=int, default=0, help="seed of keypoints and subsamples")
  ap.add_argument("--png", default=None, help="also draw the frames on the cloud here (with "
                  "--pair: the repeatability figure)")
  ap.add_argument("--pair", default=None, metavar="B",
                  help="a second scan of the same object: frames at the corresponding points "
                       "and their MeanCos (needs --gt)")
  ap.add_argument("--gt", default=None, metavar="T",
                  help="the 4x4 transform mapping CLOUD onto B (text as read_xf reads, or .npy)")
  ap.add_argument("--pair-viewpoint", type=float, nargs=3, default=None,
                  metavar=("X", "Y", "Z"), help="sensor position of the scan B")
  return ap


def npz_path(out: str) -> str:
  """The file `--out` names: `out`, with ".npz" appended when it has another suffix or none
  (as `numpy.savez` does)."""
  return out if out.endswith(".npz") else out + ".npz"


def _check(args: argparse.Namespace) -> str | None:
  """What is wrong with the arguments, before any work (None: fine)."""
  from lrf_jax.io.atomic import output_problem, path_problem, same_file
  problem = check_options(args)
  if problem:
    return problem
  inputs = [("cloud", args.cloud), ("--pair", args.pair), ("--gt", args.gt)]
  for name, value in (("--out", npz_path(args.out)), ("--png", args.png)):
    if value is not None and path_problem(value):  # before the checks that look at the disk
      return f"{name}: {value} {path_problem(value)}"
  if Path(args.out).expanduser().is_dir():
    return f"--out: {args.out} is a folder; expected a file path (e.g. {Path(args.out) / 'frames.npz'})"
  problem = output_problem(npz_path(args.out), "--out", inputs)
  if problem is None and args.png is not None:
    problem = output_problem(args.png, "--png", inputs)
    if problem is None and same_file(args.png, npz_path(args.out)):
      problem = f"--png: {args.png} is also the --out file; pick two paths"
  return problem


def check_options(args: argparse.Namespace) -> str | None:
  """What is wrong with the options of `args` other than the output paths (None: fine)."""
  from lrf_jax.descriptors import DESCRIPTORS
  from lrf_jax.frames import METHODS
  from lrf_jax.io.atomic import path_problem
  if args.method not in METHODS:
    return f"--method: unknown method {args.method!r}; expected one of {sorted(METHODS)}"
  if args.descriptor is not None and args.descriptor not in DESCRIPTORS:
    return f"--descriptor: unknown {args.descriptor!r}; expected one of {sorted(DESCRIPTORS)}"
  if args.voxel_mr is not None and args.keypoints is not None:
    return ("--voxel-mr and --keypoints: give one of them (--voxel-mr picks one keypoint per "
            "voxel, --keypoints a number, 'all' or 'iss')")
  kp = args.keypoints
  if kp is not None and kp not in ("all", "iss") and (
      not kp or not set(kp) <= _ASCII_DIGITS or int(kp) < 1):
    return f"--keypoints: expected a positive integer, 'all' or 'iss', got {kp!r}"
  for name in ("radius_mr", "voxel_mr"):
    v = getattr(args, name)
    if v is not None and not (np.isfinite(v) and v > 0):
      return f"--{name.replace('_', '-')}: expected a positive number, got {v!r}"
  if args.voxel_mr is not None and args.voxel_mr < MIN_VOXEL_MR:
    return (f"--voxel-mr: {args.voxel_mr:g} mr is below {MIN_VOXEL_MR:g} mr (voxels that small "
            "hold one point each; use --keypoints all)")
  if not 0 <= args.seed < 2**32:
    return f"--seed: expected an integer in [0, 2**32), got {args.seed}"
  if args.png is not None and Path(args.png).suffix.lower() not in FIGURE_SUFFIXES:
    return (f"--png: {args.png!r} has no figure suffix; expected one of "
            f"{', '.join(FIGURE_SUFFIXES)}")
  if args.png is not None:
    from lrf_jax.extras import MissingExtraError, require
    try:  # before any work, not after the frames
      require("plot", "--png")
    except MissingExtraError as e:
      return str(e)
  if (args.pair is None) != (args.gt is None):
    return ("--pair and --gt go together: --pair B names the second scan, --gt T the 4x4 "
            "transform mapping the cloud onto it")
  for name, value in (("--pair", args.pair), ("--gt", args.gt)):
    if value is not None and path_problem(value):
      return f"{name}: {value} {path_problem(value)}"
    if value is not None and not Path(value).expanduser().is_file():
      return f"{name}: {value} is not a file"
  return None


def select_keypoints(points: np.ndarray, how: str, voxel: float | None, seed: int,
                     mr: float | None = None) -> np.ndarray:
  """Sorted keypoint indices: every point ('all'), ISS keypoints ('iss', at resolution `mr`),
  N seeded random ones, or with `voxel` (cloud units) the point nearest the centre of each
  occupied voxel.

  Raises:
    ValueError: `voxel` too small for the cloud's extent; 'iss' where this version has no ISS
      detector."""
  n = len(points)
  if voxel is not None:
    cells = np.floor((points - points.min(0)) / voxel)
    if not (np.isfinite(voxel) and voxel > 0 and np.all(np.isfinite(cells))
            and cells.max(initial=0) < 2**40):
      raise ValueError(f"--voxel-mr: a voxel of {voxel:g} (cloud units) is too small for a "
                       f"cloud of extent {np.ptp(points, axis=0).max():g}")
    cells = cells.astype(np.int64)
    centre = (cells + 0.5) * voxel + points.min(0)
    d = np.linalg.norm(points - centre, axis=1)
    _, inv = np.unique(cells, axis=0, return_inverse=True)
    order = np.lexsort((d, inv.ravel()))
    first = np.r_[True, np.diff(inv.ravel()[order]) != 0]
    return np.sort(order[first])
  if how == "all":
    return np.arange(n)
  if how == "iss":
    try:
      from lrf_jax.geometry.keypoints import iss_keypoints
    except ImportError:
      raise ValueError("--keypoints iss: this version of lrf_jax has no ISS detector "
                       "(lrf_jax.geometry.keypoints.iss_keypoints)") from None
    return np.sort(np.asarray(iss_keypoints(points, mr=mr), np.int64))
  m = min(int(how), n)
  return np.sort(np.random.default_rng(seed).choice(n, m, replace=False))


def read_transform(path: str, option: str) -> np.ndarray:
  """The (4, 4) rigid transform in `path`: a .npy holding one, else a text file of 4 rows of 4
  numbers (`lrf_jax.io.read_xf`).

  Raises:
    ValueError: not a readable (4, 4) rigid matrix; the message names `option` and the file.
  """
  from lrf_jax.io import check_rigid, read_xf
  if path.lower().endswith(".npy"):
    try:
      t = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
      raise ValueError(f"{option} {path}: not a readable .npy file ({e})") from None
    if not np.issubdtype(t.dtype, np.number):
      raise ValueError(f"{option} {path}: expected a numeric (4, 4) array, got dtype {t.dtype}")
    return check_rigid(t, path, f"{option} matrix")
  try:
    return read_xf(path)
  except ValueError as e:
    raise ValueError(f"{option}: {e}") from None


def pair_keypoints(points: np.ndarray, pair_points: np.ndarray, transform: np.ndarray,
                   mr: float, how: str, voxel: float | None, seed: int,
                   max_dist_mr: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """Keypoints of `points` (n, 3) that the other scan `pair_points` (n', 3) also saw, and their
  correspondences: a point is eligible when its image under `transform` (4, 4) has a point of
  the other scan within `max_dist_mr` * `mr` (cloud units); N seeded eligible points for a
  number `how` (the repeatability protocol's draw), else `select_keypoints`' choice
  restricted to the eligible ones.

  Returns:
    (keypoints (m,), pair_keypoints (m,)) int64, keypoints sorted; pair_keypoints[i] is the
    point of the other scan nearest keypoint i's image.

  Raises:
    ValueError: no point of `points` lands near the other scan (wrong --gt?)."""
  from scipy.spatial import cKDTree

  from lrf_jax.datasets.pair import transform_points
  dist, nearest = cKDTree(pair_points).query(transform_points(transform, points),
                                             distance_upper_bound=max_dist_mr * mr, workers=-1)
  eligible = np.isfinite(dist)
  if not eligible.any():
    raise ValueError(f"--gt: no point of the cloud lands within {max_dist_mr:g} mr of a point "
                     "of --pair under this transform (is it the cloud -> pair transform?)")
  if voxel is None and how not in ("all", "iss"):
    idx = np.flatnonzero(eligible)
    kp = np.sort(np.random.default_rng(seed).choice(idx, min(int(how), len(idx)),
                                                    replace=False))
  else:
    kp = select_keypoints(points, how, voxel, seed, mr)
    kp = kp[eligible[kp]]
  return kp.astype(np.int64), nearest[kp].astype(np.int64)


def frames_outputs(args: argparse.Namespace) -> tuple[dict, object, object]:
  """Read the inputs, compute what `args` asks for; (npz fields, cloud, pair cloud or None)."""
  import lrf_jax
  from lrf_jax.geometry.cloud import as_cloud
  cloud = as_cloud(args.cloud, "cloud")
  try:
    mr = lrf_jax.mesh_resolution(cloud.points, cloud.faces)
  except ValueError as e:  # "points: the cloud has no spacing ...": name the file
    raise ValueError(f"{args.cloud}: {str(e).removeprefix('points: ')}") from None
  voxel = None if args.voxel_mr is None else args.voxel_mr * mr
  how = args.keypoints or "1000"
  other = gt = None
  if args.pair is not None:
    gt = read_transform(args.gt, "--gt")
    other = as_cloud(args.pair, "--pair")
    kp, kp_b = pair_keypoints(cloud.points, other.points, gt, mr, how, voxel, args.seed)
  else:
    kp = select_keypoints(cloud.points, how, voxel, args.seed, mr)
  radius = args.radius_mr * mr
  spec = lrf_jax.METHODS[args.method]
  conf = spec.confidence is not None
  frames, valid, *confidence = lrf_jax.compute_frames(
      cloud, kp, radius, args.method, seed=args.seed, viewpoint=args.viewpoint,
      progress=len(kp) > 20000, return_confidence=conf)
  out = dict(keypoints=kp, positions=cloud.points[kp], frames=np.asarray(frames),
             valid=np.asarray(valid), radius=radius, mr=mr, method=args.method,
             weights=spec.weights if spec.needs_params else "")
  if conf:
    out["confidence"] = np.asarray(confidence[0])
  if args.descriptor:
    from lrf_jax.descriptors import compute_descriptors
    desc, _ = compute_descriptors(cloud.points, kp, radius, frames, valid, args.descriptor,
                                  faces=cloud.faces, seed=args.seed)
    out["descriptors"] = np.asarray(desc)
  if other is not None:
    fb, vb, *conf_b = lrf_jax.compute_frames(
        other, kp_b, radius, args.method, seed=args.seed, viewpoint=args.pair_viewpoint,
        progress=len(kp) > 20000, return_confidence=conf)
    if conf:
      out["pair_confidence"] = np.asarray(conf_b[0])
    out.update(pair_keypoints=kp_b, pair_frames=np.asarray(fb), pair_valid=np.asarray(vb),
               gt=gt, meancos=np.asarray(lrf_jax.meancos(frames, fb, gt, valid, vb)))
  return out, cloud, other


def _figure(args: argparse.Namespace, out: dict, cloud, other) -> None:
  """The --png figure: the repeatability figure with --pair, else the frames on the cloud."""
  from lrf_jax.cli import plot
  what = f"{args.method} frames at {args.radius_mr:g} mr"
  if other is None:
    plot.frames(cloud.points, out["keypoints"], out["frames"], args.png, valid=out["valid"],
                title=f"{Path(args.cloud).name}: {what}")
    return
  mc = out["meancos"]
  plot.repeatability(cloud.points, other.points, out["keypoints"], out["pair_keypoints"],
                     out["frames"], out["pair_frames"], mc, out["gt"], args.png,
                     names=(Path(args.cloud).name, Path(args.pair).name), seed=args.seed,
                     title=f"{Path(args.cloud).name} vs {Path(args.pair).name}: {what}, "
                           f"{len(mc)} keypoints, mean MeanCos {mc.mean():.3f}")


@interruptible("no partial file is left")
def main(argv: list[str] | None = None) -> int:
  """Run lrf-frames with `argv` (default: the command line); returns the exit code (0 done,
  2 a bad argument, unreadable input or unwritable output: one `error:` line)."""
  args = build_parser().parse_args(argv)
  problem = _check(args)
  if problem:
    print(f"error: {problem}", file=sys.stderr)
    return 2
  from lrf_jax import compilation_cache
  compilation_cache.enable()
  from lrf_jax.io.atomic import WriteError, atomic_write
  out_path = npz_path(args.out)
  try:
    out, cloud, other = frames_outputs(args)
  except (ValueError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  except OSError as e:  # unreadable input (permissions, a folder, an I/O error)
    print(f"error: cloud: could not read {e.filename or args.cloud}: "
          f"{e.strerror or e}", file=sys.stderr)
    return 2
  try:
    with atomic_write(out_path) as f:
      np.savez(f, **out)
    if args.png:
      _figure(args, out, cloud, other)
  except WriteError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  kp = out["keypoints"]
  print(f"{len(kp)} keypoints, {int(out['valid'].sum())} valid frames ({args.method}, r = "
        f"{args.radius_mr:g} mr = {out['radius']:.6g}) -> {out_path}"
        + (f", {args.png}" if args.png else ""), file=sys.stderr)
  if other is not None:
    from lrf_jax.cli.plot import REPEATED_MEANCOS
    mc = out["meancos"]
    print(f"repeatability on {Path(args.pair).name}: mean MeanCos {mc.mean():.3f}, "
          f"{np.mean(mc > REPEATED_MEANCOS):.0%} of the keypoints above {REPEATED_MEANCOS:g}, "
          f"{int(out['pair_valid'].sum())} valid frames there", file=sys.stderr)
  return 0


if __name__ == "__main__":
  exit_with(main())
