"""Register many scans into one model: `lrf-register a.ply b.ply c.ply ... --out-dir D`.

`lrf-register` hands over to this module when it is given more than two scans or `--out-dir`
(`wanted`). It runs `lrf_jax.multiway.register_all` and writes, into D (created if missing,
every file atomically): `<stem>.txt` per scan in the model (the 4x4 that maps that scan into
the reference scan's frame: the first scan's, unless the first scan is left out, then the
first scan that is in the model), `poses.txt` (every scan's pose in KITTI's pose-file layout:
line k holds scan k's 3x4 [R|t] in that frame, 12 numbers row-major, 12 `nan` for a scan left
out: the trajectory of a sweep sequence), `merged.ply` (the merged cloud coloured by scan,
thinned by voxels of S mr with `--merge-voxel-mr S`, named `--voxel` before 0.9 and still
accepted), `edges.tsv` (pair, verdict, inliers, overlap, residual, accepted or rejected,
placement: whether a scan is placed only through "not sure" edges, also said on stderr; the
table is also printed), the figures `merged.png` and `graph.png`, and `manifest.json`, the list
of these files. D must be new, empty or an earlier run's output folder (it holds that run's
manifest): the files the earlier run listed are replaced or removed, so that D holds this run's
files only (a folder of other files is refused). Without `--out-dir` the edge table and the
poses are only printed. No output may be one of the inputs, or a FIFO or a device.

Exit code 0: every scan is in the model; 3: some scans were left out (named on stderr; their
poses are not written); 2: bad input or an unwritable output (one `error:` line naming it).
This file is intentionally thin.

    lrf-register bun000.ply bun045.ply bun090.ply bun180.ply --out-dir model/
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from lrf_jax.checks import validate_seed
from lrf_jax.cli.exits import EXIT_USAGE, EXIT_WRITE_FAILED, refuse
from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.cli.options import (AliasedFlag, add_bin_layout_flag, add_multiway_flags, alias_help,
                                 as_typed, option_message, register_overrides, register_problem)

# The old names of --merge-voxel-mr, still accepted in 0.9.
MERGE_VOXEL_OLD = ("--voxel",)
# The flags whose meaning is the job's, not one pair's: their help on this command line.
_HELPS = {
    "mr": "mesh resolution in the clouds' units (default: median over the scans)",
    "icp_mr": "overlap and ICP pairing distance of the pairs and the joint ICP, in mr",
    "seed": "seed of the pairwise registrations, the samples and the pose graph"}


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(
      prog="lrf-register", allow_abbrev=False,
      description="Register several scans into one model: pairwise LRF registration over a "
                  "candidate graph, a robust pose graph (wrong edges rejected), joint ICP.")
  ap.add_argument("scans", nargs="+", help="the scans (PLY, PCD, XYZ/TXT(.gz), NPY, .bin "
                                           "sweeps, LAS/LAZ, E57), each in its own frame; the "
                                           "first one's frame is the model's")
  ap.add_argument("--out-dir", default=None, metavar="D",
                  help="write D/<stem>.txt, D/poses.txt (KITTI layout), D/merged.ply, "
                       "D/edges.tsv, D/merged.png, D/graph.png")
  # Not an option of `register_all` (no options class holds it): merged.ply's voxel, in mr.
  ap.add_argument("--merge-voxel-mr", *MERGE_VOXEL_OLD, dest="merge_voxel_mr", type=float,
                  default=None, metavar="S", action=AliasedFlag,
                  help=alias_help("thin merged.ply by voxels of S mr (default: every point)",
                                  MERGE_VOXEL_OLD))
  add_multiway_flags(ap, helps=_HELPS)
  add_bin_layout_flag(ap)
  ap.add_argument("--viewpoint", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                  help="sensor position of every scan, in each scan's own frame")
  ap.add_argument("--engine", choices=("local", "ray"), default="local",
                  help="where the scans are described and the pairs registered: this process "
                       "(local) or a Ray cluster (ray); the result is the same")
  ap.add_argument("--address", default=None,
                  help="the Ray cluster (HOST:PORT) with --engine ray; default: RAY_ADDRESS if "
                       "set, else a Ray instance of this machine started for the job")
  ap.add_argument("--force", action="store_true",
                  help="take over --out-dir's lock of a job of another host that is gone (a "
                       "shared file system); a dead job of this host's is taken over without it")
  ap.add_argument("--no-figures", action="store_true", help="do not draw the PNG figures")
  ap.add_argument("--quiet", action="store_true", help="no progress bar")
  return ap


def multiway_overrides(args: argparse.Namespace) -> dict[str, Any]:
  """The `register_all` keywords (`MultiwayOptions` fields) the flags in `args` set."""
  from lrf_jax.multiway.options import FIELDS
  kw = register_overrides(args)
  kw.update({name: getattr(args, name) for name in FIELDS if hasattr(args, name)
             and name not in kw and name not in ("keypoints", "n_keypoints")})
  return {k: v for k, v in kw.items() if k in FIELDS}


def wanted(pairwise_parser: argparse.ArgumentParser, argv: list[str] | None) -> bool:
  """Whether a command line of `lrf-register` asks for several scans: more than two positional
  arguments or `--out-dir` (parsed with the two-scan `pairwise_parser`, so that option values
  are not counted as scans)."""
  args = sys.argv[1:] if argv is None else list(argv)
  if any(a == "--out-dir" or a.startswith("--out-dir=") for a in args):
    return True
  if any(a in ("-h", "--help") for a in args):
    return False
  try:
    _, extra = pairwise_parser.parse_known_args(args)
  except SystemExit:  # too few arguments etc.: the two-scan parser reports it
    return False
  return any(not a.startswith("-") for a in extra)


def _check(args: argparse.Namespace) -> str | None:
  """What is wrong with the arguments, before any work (None: fine)."""
  from pathlib import Path

  from lrf_jax.io.atomic import output_problem, path_problem, same_file
  from lrf_jax.io.validation import file_problem
  from lrf_jax.multiway.outputs import check_out_dir, output_paths, scan_names
  if len(args.scans) < 2:
    return f"expected at least 2 scans, got {len(args.scans)}"
  if args.address and args.engine != "ray":
    return f"--address: {args.address!r} is for --engine ray; the local engine runs here"
  try:
    validate_seed(args.seed, "--seed")
  except ValueError as e:
    return str(e)
  for name in ("merge_voxel_mr", "mr", "reject_mr"):
    val = getattr(args, name)
    if val is not None and not (np.isfinite(val) and val > 0):
      return f"--{name.replace('_', '-')}: expected a positive number, got {val}"
  problem = _check_register_options(args)
  if problem:
    return problem
  for s in args.scans:
    if path_problem(s):
      return f"{s}: {path_problem(s)}"
    problem = file_problem(s)
    if problem:
      return f"{s}: {problem}"
  if args.out_dir is None:
    return None
  try:  # new, empty, or an earlier run's (its manifest lists the files it wrote)
    earlier = check_out_dir(args.out_dir, "--out-dir")
  except ValueError as e:
    return str(e)
  d = Path(args.out_dir).expanduser()
  inputs = [(f"scan {k + 1}", s) for k, s in enumerate(args.scans)]
  for name in earlier:  # an earlier run's file, replaced or removed
    clash = next((f"--out-dir: {d / name} is the input {n} ({s}), a file an earlier run wrote "
                  "there; refusing to overwrite it" for n, s in inputs
                  if same_file(d / name, s)), None)
    if clash:
      return clash
  for path in output_paths(scan_names(args.scans), d).values():
    if d.is_dir():
      problem = output_problem(path, "--out-dir", inputs)
    else:  # created later: only the inputs can clash
      problem = next((f"--out-dir: {path} is the input {n} ({s}); refusing to overwrite it"
                      for n, s in inputs if Path(s).expanduser().resolve() == path.resolve()),
                     None)
    if problem:
      return problem
  return None


def _check_register_options(args: argparse.Namespace) -> str | None:
  """What is wrong with the graph's options and the options passed to every pairwise
  registration (the register flags, --viewpoint), before any work (None: fine)."""
  from lrf_jax.multiway.options import GRAPH_FIELDS, GraphOptions
  try:
    GraphOptions(**{name: getattr(args, name) for name in GRAPH_FIELDS})
  except ValueError as e:
    return option_message(str(e), {name: name for name in GRAPH_FIELDS})
  view = argparse.Namespace(**vars(args), source_viewpoint=args.viewpoint)
  return register_problem(view, {"source_viewpoint": "viewpoint"})


def _print_result(res, out) -> None:
  from lrf_jax.multiway.outputs import edges_table
  print(edges_table(res), end="", file=out)
  for line in res.summary().splitlines():
    print(f"# {line}", file=sys.stderr)


def _register(args: argparse.Namespace, clouds: list, names: list[str], mr: float | None):
  """`register_all` as the flags say, on the engine they name; with --out-dir its state
  folder (`STATE`) keeps every finished pair for the next run."""
  from pathlib import Path

  from lrf_jax.multiway.outputs import STATE
  from lrf_jax.multiway.pipeline import register_all
  engine = None
  if args.engine == "ray":
    from lrf_jax.batch import make_engine
    engine = make_engine("ray", args.address)
  state = None if args.out_dir is None else Path(args.out_dir).expanduser() / STATE
  try:
    return register_all(clouds, names=names, viewpoints=args.viewpoint,
                        progress=not args.quiet, engine=engine, state_dir=state,
                        **{**multiway_overrides(args), "mr": mr})
  finally:
    if engine is not None:
      engine.close()


@interruptible("no partial file is left; the same command runs again (finished pairs are "
               "kept in the output folder and not registered again)")
def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  problem = _check(args)
  if problem:
    return refuse(as_typed(problem, args))  # a flag named as typed: --voxel, its old name
  from lrf_jax.extras import MissingExtraError, require
  figures, skipped = args.out_dir is not None and not args.no_figures, None
  if figures:
    try:  # checked before the work: a base install writes everything but the figures
      require("plot", "the figures merged.png and graph.png")
    except MissingExtraError as e:
      figures, skipped = False, str(e)
  from lrf_jax import compilation_cache, records
  compilation_cache.enable()
  if args.out_dir is None:
    return _run(args, figures, skipped)
  from pathlib import Path

  from lrf_jax.multiway.outputs import STATE
  lock = records.JobLock(Path(args.out_dir).expanduser() / STATE / "lock", force=args.force,
                         folder=f"--out-dir {args.out_dir}")
  try:
    lock.acquire()
  except records.FolderInUse as e:
    return refuse(str(e))
  try:
    return _run(args, figures, skipped)
  finally:
    lock.release()


def _voxel_message(args: argparse.Namespace, message: str) -> str:
  """A "voxel: ..." message of `write_outputs` or `check_voxel` (about the voxel in cloud
  units) as the flag gave it, in mr, named as typed: "--merge-voxel-mr: 1e-20 mr = ..."."""
  return as_typed(f"--merge-voxel-mr: {args.merge_voxel_mr:g} mr = "
                  + message[len("voxel: "):], args)


def _run(args: argparse.Namespace, figures: bool, skipped: str | None) -> int:
  """The registration and its outputs, once the arguments are checked (and with --out-dir, its
  lock held)."""
  from lrf_jax.io.atomic import WriteError
  from lrf_jax.multiway.outputs import check_voxel, scan_names, write_outputs
  from lrf_jax.io.reader import cloud_source
  from lrf_jax.multiway.pipeline import load_scans, median_mr
  try:
    names = scan_names(args.scans)
    clouds = load_scans([cloud_source(s, args.bin_layout) for s in args.scans], names)
    mr = args.mr
    if args.merge_voxel_mr is not None:  # a voxel too small whatever the poses: before the work
      mr = median_mr(clouds, names) if mr is None else mr  # register_all's own
      try:
        check_voxel([c.points for c in clouds], args.merge_voxel_mr * mr)
      except ValueError as e:
        raise ValueError(_voxel_message(args, str(e))) from None
    res = _register(args, clouds, names, mr)
  except (ValueError, FileNotFoundError) as e:
    print(f"error: {as_typed(str(e), args)}", file=sys.stderr)
    return 2
  except OSError as e:
    if e.filename is None or str(e.filename) not in map(str, args.scans):
      print(f"error: {e}", file=sys.stderr)  # not an input's: a disk, a cache, a worker
      return EXIT_WRITE_FAILED if isinstance(e, WriteError) else EXIT_USAGE
    print(f"error: could not read {e.filename}: {e.strerror or e}", file=sys.stderr)
    return EXIT_USAGE
  _print_result(res, sys.stdout)
  if args.out_dir is None:
    for k, name in enumerate(res.names):
      if res.in_model[k]:
        print(f"# {name}\n" + "\n".join(" ".join(f"{v:.9g}" for v in row)
                                        for row in res.poses[k]))
  else:
    try:
      voxel = args.merge_voxel_mr
      write_outputs(res, [c.points for c in clouds], args.out_dir,
                    voxel=None if voxel is None else voxel * res.mr, figures=figures)
    except (WriteError, ValueError) as e:  # e.g. the folder changed during the run
      message = str(e).replace("out_dir: ", "--out-dir: ", 1)
      if message.startswith("voxel: "):
        message = _voxel_message(args, message)
      print(f"error: {message}", file=sys.stderr)
      write = isinstance(e, WriteError) and not isinstance(e, ValueError)
      return EXIT_WRITE_FAILED if write else EXIT_USAGE
    if skipped:
      print(f"# figures skipped: {skipped} (or pass --no-figures)", file=sys.stderr)
  return 3 if res.left_out else 0


if __name__ == "__main__":
  exit_with(main())
