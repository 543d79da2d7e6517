"""Register two scans with LRF-Net frames: `python -m lrf_jax.cli.register SRC TGT [--out T.txt]`.

Prints the 4 x 4 transform that maps SRC onto TGT (rows, 9 significant digits), the inlier count
of the coarse estimate, the final overlap (fitness) and RMSE and the verdict
(`Registration.success`; exit code 3 when it failed); `--out` also writes the matrix as text
(`numpy.loadtxt` reads it back), atomically; it may not be one of the inputs, and must be a
regular file or a new name (a FIFO, a device such as /dev/null or a symbolic link loop is
refused); on a "not sure" verdict (exit 3) it writes nothing unless `--best-guess` is given (then
it writes the transform and still exits 3), so a script that ignores exit codes never reads a
wrong pose. `--init`
gives an initial source->target transform (a 4x4 text file as `lrf_jax.io.read_xf` reads, or
a (4, 4) .npy) that `register` refines by ICP and judges on the same evidence as its own pose. Inputs: any cloud or mesh
`lrf_jax.io.read_cloud` reads (PLY, PCD, XYZ/TXT(.gz), NPY, .bin sweeps; LAS/LAZ and E57
with the `formats` extra); `--bin-layout xyz` reads 12-byte .bin sweeps. Every length is in mesh
resolutions (the working resolution `register` measures, `--mr` to set it). Every bad argument
or unreadable input is one `error:` line and exit code 2, an output that cannot be written (a
full disk, a read-only file system) one `error:` line and exit code 74
(`lrf_jax.cli.exits.EXIT_CODES`). `--png` draws the correspondences the estimate
used (inliers and outliers joining the two clouds side by side). This file is intentionally
thin; the pipeline is
`lrf_jax.registration.register`.

    python -m lrf_jax.cli.register bun000.ply bun045.ply --out bun000_to_bun045.txt
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from lrf_jax.cli.exits import EXIT_NOT_SURE, EXIT_OK, EXIT_USAGE, refuse, write_failed
from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.cli.help import DefaultsHelpFormatter
from lrf_jax.batch.scan_frames import INPUT_FORMATS
from lrf_jax.cli.options import (KEYPOINT_DETECTORS, add_bin_layout_flag, add_register_flags,
                                 parse_keypoints, register_overrides, register_problem)


def build_parser(*, suppress_defaults: bool = False) -> argparse.ArgumentParser:
  """lrf-register's parser (two scans). With `suppress_defaults` an option not given leaves no
  attribute in the parsed namespace (`add_register_flags`): `lrf-batch register` reads the
  options a user gave that way, and names the ones it cannot take."""
  ap = argparse.ArgumentParser(prog="lrf-register", allow_abbrev=False,
                               argument_default=argparse.SUPPRESS if suppress_defaults else None,
                               description="Rigid registration of two scans with learned LRFs "
                                           "(LRF-Net frames, TOLDI matching, a compatibility "
                                           "graph of correspondences and their LRF poses, "
                                           "point-to-plane ICP). Given more than two scans (or "
                                           "--out-dir) it registers them all into one model "
                                           "(multiway; lrf-register a b c --out-dir D --help "
                                           "lists its options).",
                               formatter_class=DefaultsHelpFormatter)
  ap.add_argument("source", help=f"the cloud to move ({INPUT_FORMATS})")
  ap.add_argument("target", help="the cloud to align it to")
  ap.add_argument("--out",
                  help="write the 4x4 source->target matrix here (only on success, exit 0, "
                       "unless --best-guess)")
  ap.add_argument("--best-guess", action="store_true",
                  help="write --out even when the verdict is 'not sure' (the exit code is "
                       "still 3)")
  add_register_flags(ap, suppress_defaults=suppress_defaults)
  add_bin_layout_flag(ap)
  # Deprecated spelling of `--keypoints iss` (kept working, hidden): with a count in
  # --keypoints, ISS keypoints at most that many.
  ap.add_argument("--detector", choices=KEYPOINT_DETECTORS, help=argparse.SUPPRESS)
  ap.add_argument("--checkpoint",
                  help="a train.py workdir whose best LRF-Net parameters to use "
                       "(default: the shipped weights)")
  ap.add_argument("--init", metavar="FILE",
                  help="initial source->target transform to refine (and judge on the same "
                       "evidence): a 4x4 text file (.xf, .txt) or a (4, 4) .npy")
  ap.add_argument("--png", metavar="FILE",
                  help="also draw the correspondences here: inliers and outliers joining the "
                       "two clouds side by side")
  return ap


def keypoint_options(args: argparse.Namespace) -> dict[str, Any]:
  """The keywords `--keypoints` and the deprecated `--detector` (where present) set.

  Raises:
    ValueError: a bad --keypoints, or two detectors named.
  """
  out: dict[str, Any] = {}
  if getattr(args, "keypoints", None) is not None:
    out = parse_keypoints(args.keypoints)
  detector = getattr(args, "detector", None)
  if detector is not None:
    if out.get("keypoints", detector) != detector:
      raise ValueError(f"--keypoints {args.keypoints} and --detector {detector}: give one "
                       "detector (--detector is the old spelling of --keypoints NAME)")
    out["keypoints"] = detector
  return out


def register_options(args: argparse.Namespace) -> dict[str, Any]:
  """The keywords of `lrf_jax.register` that the options present in `args` set (an option
  parsed with its default suppressed and not given is left out).

  Raises:
    ValueError: a bad --keypoints, or two detectors named.
  """
  return {**register_overrides(args), **keypoint_options(args)}


def check_options(args: argparse.Namespace) -> str | None:
  """What is wrong with the options present in `args`, checked before any work (None: fine):
  --keypoints, --detector and every value `lrf_jax.register` would refuse (named by its flag)."""
  try:
    keypoint_options(args)
  except ValueError as e:
    return str(e)
  return register_problem(args)


def _check_paths(args: argparse.Namespace) -> str | None:
  """What is wrong with --out, --checkpoint, --init, --seed or --keypoints, checked before any
  work is done (None: fine)."""
  from pathlib import Path

  from lrf_jax.io.atomic import loop_problem, output_problem, path_problem
  from lrf_jax.io.validation import SymlinkLoopError
  for name, value in (("--checkpoint", args.checkpoint), ("--init", args.init)):
    if value is not None and path_problem(value):  # before the checks that look at the disk
      return f"{name}: {value} {path_problem(value)}"
  for name, value in (("", args.source), ("", args.target), ("--init: ", args.init)):
    loop = loop_problem(value) if value is not None else None
    if loop:  # the reader would say so too, but only after the kernels are loaded
      return f"{name}{SymlinkLoopError(value, loop)}"
  problem = check_options(args)
  if problem:
    return problem
  if args.out:
    inputs = [("SOURCE", args.source), ("TARGET", args.target), ("--init", args.init)]
    problem = output_problem(args.out, "--out", inputs)
    if problem:
      return problem
  if args.png:
    if Path(args.png).suffix.lower() not in (".png", ".pdf", ".svg", ".jpg", ".jpeg"):
      return f"--png: {args.png!r} has no figure suffix (.png, .pdf, .svg, .jpg)"
    from lrf_jax.extras import MissingExtraError, require
    try:  # before the registration, not after it
      require("plot", "--png")
    except MissingExtraError as e:
      return str(e)
    problem = output_problem(args.png, "--png",
                             [("SOURCE", args.source), ("TARGET", args.target),
                              ("--init", args.init), ("--out", args.out)])
    if problem:
      return problem
  if args.checkpoint:
    workdir = Path(args.checkpoint).expanduser()
    if getattr(args, "weights", "objects") not in ("objects", None):
      return ("--checkpoint and --weights: give one (both name the LRF's weights: a train.py "
              "workdir's best checkpoint, or rooms, streets, objects or a parameter file)")
    if not workdir.is_dir():
      return (f"--checkpoint: {args.checkpoint} is not a folder; expected a train.py workdir "
              "(the one passed to train.py --workdir)")
    if not (workdir / "checkpoints").is_dir():
      return (f"--checkpoint: {args.checkpoint} has no checkpoints/ folder; expected a train.py "
              "workdir (the one passed to train.py --workdir)")
  if args.init is not None and not Path(args.init).expanduser().is_file():
    return f"--init: {args.init} is not a file; expected a 4x4 text file or a (4, 4) .npy"
  return None


def read_init(path: str) -> np.ndarray:
  """The (4, 4) rigid transform of `--init`: a .npy holding one, else a text file of 4 rows of
  4 numbers (`lrf_jax.io.read_xf`); a rotation block within
  `lrf_jax.registration.refine.INIT_PROJECT` of orthonormal is projected to the nearest
  rotation, with one note line on stderr giving the figure.

  Raises:
    ValueError: not a readable (4, 4) rigid matrix; the message names the file and the figure.
  """
  import warnings

  from lrf_jax.batch.scan_frames import read_transform
  from lrf_jax.io.validation import ProjectedRotation
  from lrf_jax.registration.refine import INIT_PROJECT
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always", ProjectedRotation)
    t = read_transform(path, "--init", project=INIT_PROJECT)
  for w in caught:
    print(f"note: --init: {w.message}", file=sys.stderr)
  return t


@interruptible("no partial file is left")
def main(argv: list[str] | None = None) -> int:
  from lrf_jax.cli import multiway as multiway_cli
  if multiway_cli.wanted(build_parser(), argv):  # more than two scans, or --out-dir
    return multiway_cli.main(argv)
  args = build_parser().parse_args(argv)
  problem = _check_paths(args)
  if problem:
    return refuse(problem)
  if args.detector is not None:
    print(f"# --detector is deprecated: --keypoints takes a detector name (--keypoints "
          f"{args.detector})", file=sys.stderr)
  from lrf_jax import compilation_cache
  compilation_cache.enable()  # a second run loads the compiled functions instead of recompiling
  from lrf_jax.cli import parallel_compile
  with parallel_compile.compiling("register"):  # a cold cache: workers compile beside us
    return _register_and_report(args)


def _register_and_report(args: argparse.Namespace) -> int:
  """The registration of `main` and its outputs; the exit code."""
  from lrf_jax.registration import register

  params = None
  extra: dict[str, Any] = {}  # keyword arguments of `register`
  try:
    if args.init is not None:
      extra["init"] = read_init(args.init)  # passed only when given
    if args.checkpoint:
      from lrf_jax.learning.checkpoints import restore_params
      try:
        params, _ = restore_params(args.checkpoint, "best")
      except (ValueError, FileNotFoundError) as e:
        raise ValueError(f"--checkpoint: {e}") from None
    from lrf_jax.io.reader import cloud_source
    source, target = (cloud_source(p, args.bin_layout) for p in (args.source, args.target))
    reg = register(source, target, params=params, **register_options(args), **extra)
  except (ValueError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return EXIT_USAGE
  except OSError as e:  # an unreadable input (permissions, an I/O error)
    print(f"error: could not read {e.filename or 'an input'}: {e.strerror or e}",
          file=sys.stderr)
    return EXIT_USAGE
  from lrf_jax.io.poses import format_matrix
  text = format_matrix(reg.transform)
  print(text)
  print("\n".join(f"# {line}" for line in reg.summary().splitlines()), file=sys.stderr)
  if args.png:
    failure = correspondence_figure(args, reg)
    if failure:
      return write_failed(failure)
  if args.out and not (reg.success or args.best_guess):
    print(f"# --out {args.out} not written: the verdict is not sure (pass --best-guess to "
          "write the transform anyway)", file=sys.stderr)
  elif args.out:
    from lrf_jax.io.atomic import WriteError, atomic_write
    try:
      with atomic_write(args.out, "w") as f:
        f.write(text + "\n")
    except WriteError as e:
      return write_failed(e)
  return EXIT_OK if reg.success else EXIT_NOT_SURE


def correspondence_figure(args: argparse.Namespace, reg) -> Exception | None:
  """`--png`: the correspondences of `reg` (a `Registration`) joining the two clouds side by
  side, inliers green, outliers red (`lrf_jax.cli.plot.correspondences`); None, or the
  `WriteError` that kept it from being written."""
  from pathlib import Path

  from lrf_jax.cli import plot
  from lrf_jax.geometry.cloud import as_cloud
  from lrf_jax.io.atomic import WriteError
  from lrf_jax.io.reader import cloud_source
  src, dst = (as_cloud(cloud_source(p, args.bin_layout), name).points
              for p, name in ((args.source, "SOURCE"), (args.target, "TARGET")))
  verdict = "success" if reg.success else "not sure"
  title = (f"{Path(args.source).name} -> {Path(args.target).name}: {verdict}, estimated "
           f"overlap {reg.overlap:.0%}, {reg.n_inliers} of {len(reg.correspondences)} "
           "correspondences are inliers")
  try:
    plot.correspondences(src, dst, reg.correspondences, reg.inliers, reg.transform, args.png,
                         seed=args.seed, title=title,
                         names=(Path(args.source).name, Path(args.target).name))
  except WriteError as e:
    return e
  print(f"# correspondences figure: {args.png}", file=sys.stderr)
  return None


if __name__ == "__main__":
  exit_with(main())
