"""`lrf-batch frames SCANS... --out DIR` and `lrf-batch register PAIRS.tsv --out DIR`: a data set's
frames or registrations, on this machine (`--engine local`) or a Ray cluster (`--engine ray`).

`frames` writes `DIR/<scan>.npz` as `lrf-frames` writes it and takes lrf-frames' options;
`register` writes `DIR/<name>.txt` (the 4 x 4 source->target, as `lrf-register --out` writes it,
for every done pair whatever its verdict) and takes lrf-register's options except --out, --png,
--checkpoint and --init (a pair's init is PAIRS.tsv's `init` column). Both write `DIR/results.tsv` after each item and skip, when run again,
every item whose inputs (by content) and options are unchanged. One job at a time writes a
folder: a second is refused before any work. Exit codes: 0 every item done, 3 some failed (their
rows say why), 2 a bad command line or a job refused before any work, 74 an output that could not
be written, 130 interrupted (`lrf_jax.cli.exits`). This file is thin: the
work is `lrf_jax.batch`.

    lrf-batch register pairs.tsv --out reg/ --engine ray --address 127.0.0.1:6379
    lrf-batch frames scans/*.ply --out frames/ --keypoints 2000
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from lrf_jax.cli.exits import EXIT_USAGE, refuse, write_failed
from lrf_jax.cli.help import DefaultsHelpFormatter
from lrf_jax.cli.interrupt import interruptible
from lrf_jax.cli.options import add_frame_flags, as_typed

# lrf-register options a job cannot take
_NOT_BATCH = ("out", "png", "checkpoint", "init", "best_guess")


# The job's on/off flags and their help.
_SWITCHES = (
    ("--no-progress", "no progress bar"),
    ("--retry-errors", "run again the items whose last run failed on their inputs (default: "
                       "keep their error; a failure of the machine, status 'transient', is "
                       "always run again)"),
    ("--keep-versions", "keep the results of another lrf_jax version (default: redo them; "
                        "results.tsv's version column names each row's)"),
    ("--force", "take over the folder's lock of a job of another host that is gone (a shared "
                "file system); a dead job of this host's is taken over without it"),
)


def _common(p: argparse.ArgumentParser) -> None:
  p.add_argument("--out", required=True, metavar="DIR", help="the output folder (created)")
  p.add_argument("--engine", choices=("local", "ray"), default="local",
                 help="local: in this process; ray: tasks on a Ray cluster")
  p.add_argument("--address", default=None,
                 help="the Ray cluster (HOST:PORT) with --engine ray; default: RAY_ADDRESS if "
                      "set, else a new Ray instance of this machine on 127.0.0.1")
  for flag, text in _SWITCHES:
    p.add_argument(flag, action="store_true", help=text)


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(prog="lrf-batch", allow_abbrev=False, description="Frames of every scan, or "
                               "registrations of every listed pair, of a data set; resumable.",
                               formatter_class=DefaultsHelpFormatter)
  sub = ap.add_subparsers(dest="job", required=True)
  fr = sub.add_parser("frames", help="frames (and descriptors) of every scan, as lrf-frames",
                      formatter_class=DefaultsHelpFormatter, allow_abbrev=False)
  fr.add_argument("scans", nargs="+", metavar="SCAN", help="cloud or mesh files")
  _common(fr)
  add_frame_flags(fr, skip=("pair", "gt", "pair_viewpoint"), suppress_defaults=True)
  rg = sub.add_parser("register", help="registration of every pair of a PAIRS.tsv",
                      formatter_class=DefaultsHelpFormatter, allow_abbrev=False,
                      epilog="Any option of lrf-register but --out, --best-guess, --png, "
                             "--checkpoint and --init may follow (lrf-register --help lists them); options not "
                             "given keep register's defaults. PAIRS.tsv: tab-separated, a "
                             "header with the columns source and target (paths, relative to "
                             "the TSV's folder), optionally name (default: the row number), "
                             "gt (a 4x4 source->target file as lrf-register --out writes it) "
                             "and init (the same kind of file: the pair is registered from it, "
                             "as lrf-register --init does; a changed init file redoes the "
                             "pair).")
  rg.add_argument("pairs", metavar="PAIRS.tsv", help="the pairs to register")
  _common(rg)
  rg.add_argument("--criteria", default=None, metavar="DEG,DIST",
                  help="a pair with a ground truth (PAIRS.tsv's gt column) is right when its "
                       "rotation error is at most DEG degrees and its translation error at most "
                       "DIST (the clouds' units); results.tsv's right column and the last line "
                       "count right pairs, claims and false claims")
  return ap


def _register_options(rest: list[str]) -> dict[str, Any]:
  """register's keywords from lrf-register options in `rest` (only those given)."""
  from lrf_jax.cli import register as register_cli
  p = register_cli.build_parser(suppress_defaults=True)
  p.prog = "lrf-batch register"
  args = p.parse_args(["SOURCE", "TARGET", *rest])
  given = [d for d in _NOT_BATCH if hasattr(args, d)]
  if given:
    p.error(f"--{given[0].replace('_', '-')} is not an option of lrf-batch register (each "
            "pair's transform is DIR/<name>.txt, whatever its verdict)")
  problem = register_cli.check_options(args)
  if problem:
    p.error(problem)
  options = register_cli.register_options(args)
  if getattr(args, "bin_layout", None) is not None:  # how the items read .bin inputs
    options["bin_layout"] = args.bin_layout
  return options


@interruptible("the finished items are kept; the same command resumes")
def main(argv: list[str] | None = None) -> int:
  """Run lrf-batch with `argv` (default: the command line); returns the exit code."""
  ap = build_parser()
  args, rest = ap.parse_known_args(argv)
  if args.job == "frames" and rest:
    ap.error(f"unrecognized arguments: {' '.join(rest)}")
  from lrf_jax import compilation_cache
  from lrf_jax.batch import items, jobs
  from lrf_jax.io.atomic import WriteError
  common = dict(engine=args.engine, address=args.address, progress=not args.no_progress,
                retry_errors=args.retry_errors, keep_versions=args.keep_versions,
                force=args.force)
  try:
    if args.job == "register":
      options = _register_options(rest)
      from lrf_jax.batch import scoring
      criteria = None if args.criteria is None else scoring.parse_criteria(args.criteria)
      compilation_cache.enable()
      result = jobs.run_register(args.pairs, args.out, criteria=criteria, **common, **options)
    else:
      options = {k: getattr(args, k) for k in items.FRAMES_OPTIONS if hasattr(args, k)}
      compilation_cache.enable()
      result = jobs.run_frames(args.scans, args.out, **common, **options)
  except (ValueError, FileNotFoundError, ImportError) as e:
    return refuse(as_typed(str(e), args))  # a flag named as typed: --voxel-mr, its old name
  except WriteError as e:  # a read-only or full disk: the finished items are kept
    return write_failed(e, "; the finished items are kept")
  except OSError as e:
    print(f"error: {e}; the finished items are kept", file=sys.stderr)
    return EXIT_USAGE
  done = sum(r["status"] == "done" for r in result.rows)
  claimed = sum(r.get("success") == "True" for r in result.rows)
  print(f"{len(result.rows)} items: {done} done"
        + (f" ({claimed} claimed)" if args.job == "register" else "")
        + f", {result.failed} failed; {result.ran} run, {result.skipped} already done "
        f"-> {result.out / 'results.tsv'} ({result.seconds:.1f} s)", file=sys.stderr)
  if args.job == "register":
    c = result.counts
    scored = (f"{c['right']} right of {c['scored']} scored, " if args.criteria is not None
              else "")
    false = f", {c['false_claims']} false claims" if args.criteria is not None else ""
    print(f"{c['pairs']} pairs: {scored}{c['claimed']} claimed{false}")
  return result.exit_code


if __name__ == "__main__":
  sys.exit(main())
