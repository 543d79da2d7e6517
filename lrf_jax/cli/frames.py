"""`lrf-frames CLOUD --out F.npz`: local reference frames for the keypoints of one's own file.

Reads any cloud or mesh `lrf_jax.io.read_cloud` reads (PLY, PCD, XYZ/TXT(.gz), NPY, .bin sweeps
with `--bin-layout` for 12-byte ones; LAS/LAZ and E57 with the `formats` extra), picks
keypoints (N seeded random points, all points, ISS keypoints, or with --keypoint-voxel-mr S
one point per voxel of S mr; it and --keypoints exclude each other; --voxel-mr is its name
before 0.9, still accepted), computes their frames (and optionally a descriptor) on the
support `--voxel-size` gives (the cloud thinned by voxel averaging, voxels in cloud units: by
default an uneven cloud such as a raw LiDAR sweep, to its working resolution mr;
`compute_frames(voxel_size=)`) and writes an .npz with `keypoints` (indices into the input
cloud), `positions`, `frames` (m, 3, 3, rows x, y, z), `valid` (m,), `radius`, `mr` (the working
resolution), `voxel_size` (the voxel the support was thinned at, 0: none), `method`, `weights`,
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
input is one `error:` line and exit code 2, checked before any work where it can be, and an
output that cannot be written (a full disk, a read-only file system) one `error:` line and exit
code 74 (`lrf_jax.cli.exits.EXIT_CODES`). This file is intentionally thin: the work is `lrf_jax.compute_frames`.

    lrf-frames scan.ply --out scan_frames.npz --keypoints 2000 --viewpoint 0 0 0 --png f.png
    lrf-frames a.ply --pair b.ply --gt a_to_b.txt --out ab.npz --png repeatability.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lrf_jax.batch.items import FRAMES_OPTIONS
from lrf_jax.batch.scan_frames import INPUT_FORMATS
from lrf_jax.cli.options import add_frame_flags, as_typed
from lrf_jax.cli.exits import EXIT_OK, EXIT_USAGE, refuse, write_failed
from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.cli.help import DefaultsHelpFormatter


FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(prog="lrf-frames", allow_abbrev=False, description="Local reference frames of the "
                               "keypoints of a cloud or mesh file, written to an .npz; with "
                               "--pair and --gt, also their repeatability on a second scan.",
                               formatter_class=DefaultsHelpFormatter)
  ap.add_argument("cloud", help=f"{INPUT_FORMATS} file")
  ap.add_argument("--out", required=True,
                  help="the .npz to write: keypoints, positions, frames (m, 3, 3; rows x, y, "
                       "z), valid, radius, mr, method, weights; confidence (m,) in [0, 1] for "
                       "methods that define one (lrf_net_plus: how sure each z sign is; 0: a "
                       "guess, e.g. a flat patch without --viewpoint); descriptors with "
                       "--descriptor; with --pair also pair_keypoints, pair_frames, pair_valid, "
                       "pair_confidence, meancos, gt")
  add_frame_flags(ap, skip=("pair", "gt", "pair_viewpoint"))
  ap.add_argument("--png", default=None, help="also draw the frames on the cloud here (with "
                  "--pair: the repeatability figure)")
  add_frame_flags(ap, skip=tuple(FRAMES_OPTIONS))  # the second scan: --pair, --gt, ...
  return ap


def npz_path(out: str) -> str:
  """The file `--out` names: `out`, with ".npz" appended when it has another suffix or none
  (as `numpy.savez` does)."""
  return out if out.endswith(".npz") else out + ".npz"


def _check(args: argparse.Namespace) -> str | None:
  """What is wrong with the arguments, before any work (None: fine)."""
  from lrf_jax.io.atomic import loop_problem, output_problem, path_problem, same_file
  from lrf_jax.io.validation import SymlinkLoopError
  inputs = [("cloud", args.cloud), ("--pair", args.pair), ("--gt", args.gt)]
  for name, value in inputs:
    loop = loop_problem(value) if value is not None else None
    if loop:  # before the options' "is not a file"
      return f"{name}: {SymlinkLoopError(value, loop)}"
  problem = check_options(args)
  if problem:
    return problem
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
  from lrf_jax.batch.scan_frames import FrameOptions
  problem = FrameOptions.from_args(args).problem()
  if problem or args.png is None:
    return problem
  if Path(args.png).suffix.lower() not in FIGURE_SUFFIXES:
    return (f"--png: {args.png!r} has no figure suffix; expected one of "
            f"{', '.join(FIGURE_SUFFIXES)}")
  from lrf_jax.extras import MissingExtraError, require
  try:  # before any work, not after the frames
    require("plot", "--png")
  except MissingExtraError as e:
    return str(e)
  return None


def frames_outputs(args: argparse.Namespace) -> tuple[dict, object, object]:
  """Read the inputs, compute what `args` asks for (`scan_frames.frames_of_scan`); (npz fields,
  cloud, pair cloud or None)."""
  from lrf_jax.batch.scan_frames import FrameOptions, frames_of_scan
  return frames_of_scan(FrameOptions.from_args(args))


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
  2 a bad argument or unreadable input, 74 an output that cannot be written: one `error:`
  line; `lrf_jax.cli.exits.EXIT_CODES`)."""
  args = build_parser().parse_args(argv)
  problem = _check(args)
  if problem:
    return refuse(as_typed(problem, args))  # a flag named as typed: --voxel-mr, its old name
  from lrf_jax import compilation_cache
  compilation_cache.enable()
  from lrf_jax.cli import parallel_compile
  with parallel_compile.compiling("frames"):  # a cold cache: workers compile beside us
    return _frames_and_report(args)


def _frames_and_report(args: argparse.Namespace) -> int:
  """The frames of `main` and their outputs; the exit code."""
  from lrf_jax.io.atomic import WriteError, atomic_write
  out_path = npz_path(args.out)
  try:
    out, cloud, other = frames_outputs(args)
  except (ValueError, FileNotFoundError) as e:
    print(f"error: {as_typed(str(e), args)}", file=sys.stderr)
    return EXIT_USAGE
  except OSError as e:  # unreadable input (permissions, a folder, an I/O error)
    print(f"error: cloud: could not read {e.filename or args.cloud}: "
          f"{e.strerror or e}", file=sys.stderr)
    return EXIT_USAGE
  try:
    with atomic_write(out_path) as f:
      np.savez(f, **out)
    if args.png:
      _figure(args, out, cloud, other)
  except WriteError as e:
    return write_failed(e)
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
  return EXIT_OK


if __name__ == "__main__":
  exit_with(main())
