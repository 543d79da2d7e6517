"""Reproduce the paper's repeatability experiments for LRF-Net and the hand-crafted LRFs.

    python evaluate.py                                   # main experiment on the data it finds
    python evaluate.py --data /path/to/data --experiments repeatability noise decimation
    python evaluate.py --checkpoint runs/default --methods lrf_net toldi shot --out out/
    python evaluate.py --experiments points_only         # frames from the points alone
    python evaluate.py --engine ray --address HOST:PORT  # the pairs spread over a Ray cluster
    python evaluate.py --scans my_sweeps/ my_rooms/ --methods lrf_net toldi   # your own scans
    python evaluate.py --scans my_sweeps/ --datasets bunny BR@0.3   # beside the paper's sets

With no data (no --data, LRF_DATA unset, nothing under data/) it runs on the procedural demo set.
--scans DIR ...: each folder of scans with its pose file (poses.txt, gt.log or a .conf; see
docs/own_scans.md) is a data set of its own, named by the folder, in the same tables and
figures; without --datasets only the scan sets run.
Writes results.json, report.md and PNG figures to --out (each atomically) and prints the summary
table. With --engine ray the pairs run as Ray tasks (the same records, in the same order; only
this process writes files); a pair that the engine could not run is one `error:` line naming it
and exit code 1. Every bad argument (checked before any work; a Ray --address that nothing
answers at included), missing parameter file or checkpoint and unwritable output is one
`error:` line and exit code 2. This file is intentionally kept short;
the logic lives in lrf_jax/evaluation/.
"""

import argparse
import math
import os
import sys
import time
from pathlib import Path

from lrf_jax import evaluation, extras
from lrf_jax.checks import validate_seed
from lrf_jax.batch.engines import ENGINES
from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.cli.help import DefaultsHelpFormatter
from lrf_jax.evaluation import runner
from lrf_jax.evaluation.experiments import (DATASETS, EXPERIMENTS, POINTS_ONLY_DATASETS,
                                            POINTS_ONLY_HANDCRAFTED, POINTS_ONLY_PAIRS)
from lrf_jax.datasets.scan_sets import MIN_OVERLAP
from lrf_jax.defaults import RADIUS_MR
from lrf_jax.frames import METHODS

REAL = ["BR@0.1", "BR@0.3", "BR@0.5", "UWA3M", "UWAOR", "bunny"]


def build_parser() -> argparse.ArgumentParser:
  """evaluate.py's options (each default shown by --help)."""
  ap = argparse.ArgumentParser(description="LRF repeatability experiments (MeanCos). Writes "
                               "results.json, report.md and PNG figures to --out.",
                               formatter_class=DefaultsHelpFormatter)
  ap.add_argument("--data", default=None, help="data root (default: $LRF_DATA, then data/)")
  ap.add_argument("--datasets", nargs="+", default=None, choices=sorted(DATASETS),
                  help="default: every real dataset found, else demo (points_only: "
                       f"{' '.join(POINTS_ONLY_DATASETS)})")
  ap.add_argument("--scans", nargs="+", default=[], metavar="DIR",
                  help="scan-set folders (scans + poses.txt, gt.log or a .conf), each a data "
                       "set named by its folder; without --datasets only these run")
  ap.add_argument("--min-overlap", type=float, default=MIN_OVERLAP, metavar="FRACTION",
                  help=f"the overlap a --scans pair needs, as a fraction of the source's points "
                       f"(default {MIN_OVERLAP}; 3DLoMatch-style pairs: 0.1)")
  ap.add_argument("--experiments", nargs="+", default=["repeatability"],
                  choices=EXPERIMENTS + ("description", "pose"),
                  help="experiments to run; points_only: every cloud moved by a seeded random "
                       "rigid motion, lrf_net_plus with its sensor position and from the points "
                       "alone, the hand-crafted methods from the points alone, MeanCos and the "
                       "z flip rate")
  ap.add_argument("--methods", nargs="+", default=None,
                  help=f"default: all of {sorted(METHODS)} (points_only: lrf_net_plus and "
                       f"{' '.join(POINTS_ONLY_HANDCRAFTED)})")
  ap.add_argument("--checkpoint", default=None,
                  help="a train.py workdir: its best checkpoint is 'lrf_net', its final "
                       "parameters 'lrf_net[final]' (default: the shipped weights)")
  ap.add_argument("--params", nargs="+", default=[], metavar="LABEL=PATH",
                  help="extra learned columns from parameter files: LABEL=PATH[@METHOD] (METHOD "
                       "defaults to lrf_net), e.g. mine=w.msgpack or p=w.msgpack@lrf_net_plus")
  ap.add_argument("--weights", nargs="+", default=[], metavar="KIND|PATH",
                  help="extra lrf_net_plus columns with these weights: rooms, streets, objects "
                       "(the default column's) or a parameter file, read with the options the "
                       "weights were trained under")
  ap.add_argument("--keypoints", type=int, default=1000, help="keypoints per pair (the paper's: 1000)")
  ap.add_argument("--max-pairs", type=int, default=None,
                  help=f"at most N pairs per dataset (default: all; {POINTS_ONLY_PAIRS} with "
                       "points_only)")
  ap.add_argument("--radius-mr", type=float, default=RADIUS_MR,
                  help="support radius in mesh resolutions")
  ap.add_argument("--seed", type=int, default=0, help="seed of keypoints and subsamples")
  ap.add_argument("--max-neighbors", type=int, default=evaluation.MAX_NEIGHBORS,
                  help="cap on all-neighbour patches (dense scans); 0 = no cap")
  ap.add_argument("--cache-dir", default=None, help="keep neighbourhoods on disk here")
  ap.add_argument("--out", default="out/eval", help="output folder")
  ap.add_argument("--engine", default="local", choices=ENGINES,
                  help="where the pairs run: local = in this process, one after another; ray "
                       "= Ray tasks of 1 CPU each (needs the [ray] extra), the same records in "
                       "the same order")
  ap.add_argument("--address", default=None,
                  help="the Ray cluster of --engine ray: HOST:PORT of a running cluster, or "
                       "'local' (a new Ray instance of this machine on 127.0.0.1) (default: "
                       "$RAY_ADDRESS, else 'local'); the workers need --data at the same path "
                       "only for the BR noise sweep")
  return ap


@interruptible("no partial file is left")
def main(argv=None) -> int:
  args = build_parser().parse_args(argv)
  problem = _check(args)
  if problem:
    print(f"error: {problem}", file=sys.stderr)
    return 2
  try:  # matplotlib, fast-simplification, flax: the [eval] extra
    extras.require("eval", "evaluate.py")
    if args.engine == "ray":
      extras.require("ray", "evaluate.py --engine ray")
  except extras.MissingExtraError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2

  t0 = time.perf_counter()
  points_only = "points_only" in args.experiments
  names = args.datasets or ([] if args.scans else (
      list(dict.fromkeys(([] if args.experiments == ["points_only"] else REAL)
                         + list(POINTS_ONLY_DATASETS))) if points_only else REAL))
  max_pairs = args.max_pairs or (POINTS_ONLY_PAIRS if points_only else None)
  ok, missing = evaluation.available(names, args.data, DATASETS)
  if missing:  # the whole message (where we looked, how to get the data) before any work
    _, full = evaluation.available(names, args.data, DATASETS, full=True)
    print("\n\n".join(full), file=sys.stderr)
    if args.datasets:
      print("error: data not found for the --datasets asked for (above)", file=sys.stderr)
      return 2
  try:
    scan_sets = _scan_sets(args.scans, args.min_overlap)
  except (ValueError, OSError) as e:  # a folder without poses, a bad pose line: named
    print(f"error: --scans: {e}", file=sys.stderr)
    return 2
  ok += list(scan_sets)
  missing += [note for notes in scan_sets.values() for note in notes]
  if not ok:
    ok = ["demo"]
    missing.append("no real data found: ran on the procedural demo set (synthetic, labelled)")
  try:
    runs, notes = runner.method_runs(args.methods, checkpoint=args.checkpoint,
                                     params=tuple(args.params), weights=tuple(args.weights))
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  opts = evaluation.EvalOptions(data_root=args.data, n_keypoints=args.keypoints, seed=args.seed,
                                radius_mr=args.radius_mr, max_pairs=max_pairs,
                                max_neighbors=args.max_neighbors or None,
                                scans=tuple(args.scans), min_overlap=args.min_overlap)
  plan = runner.EvalPlan(ok, args.experiments, runs, opts, notes=missing + notes,
                         cache_dir=args.cache_dir, meta={"args": vars(args)},
                         methods_named=args.methods is not None, engine=args.engine,
                         address=args.address)
  out = Path(args.out)
  try:
    text = runner.evaluate(plan, out)
  except runner.JobError as e:  # a pair the engine could not run: named, never dropped
    print(f"error: {e}", file=sys.stderr)
    return 1
  except ConnectionError as e:  # no Ray cluster at --address (one that answered the check)
    where = args.address or f"{os.environ.get('RAY_ADDRESS')} ($RAY_ADDRESS)"
    print(f"error: --address {where}: {e}", file=sys.stderr)
    return 2
  except OSError as e:  # a WriteError (full disk, read-only --out): earlier files are intact
    print(f"error: {e}", file=sys.stderr)
    return 2
  print(text)
  print(f"wrote {out / 'results.json'}, {out / 'report.md'} and figures "
        f"({time.perf_counter() - t0:.0f} s)")
  print(NEXT_STEPS)
  return 0


# Where a newcomer goes after the first command (printed last).
NEXT_STEPS = ("next: register two scans of your own with `lrf-register a.ply b.ply` (it prints "
              "the transform and a verdict you can trust); a data set: `lrf-batch register "
              "pairs.tsv --out results/`; the guide: docs/getting-started.md (`mkdocs serve` with "
              "the [docs] extra)")


# Files evaluate.py writes in --out besides figures (*.png).
OUTPUT_FILES = ("results.json", "report.md", "partial_records.jsonl",
                "results_description_pose.json")


def _scan_sets(folders: list[str], min_overlap: float) -> dict[str, list[str]]:
  """{data set name: notes for the report} of the --scans folders, each read once here (a bad
  folder stops the run before any work; the pairs stay in this process's scan cache)."""
  from lrf_jax.datasets.scan_sets import read_scan_set
  from lrf_jax.evaluation.experiments import scan_set_names
  out = {}
  for name, folder in scan_set_names(folders).items():
    s = read_scan_set(folder, min_overlap=min_overlap)
    kept = f"{len(s.pairs)} of {len(s.candidates)} candidate pairs overlap >= {min_overlap:.0%}"
    out[name] = [f"{name}: scan set {folder} ({s.format} layout, {len(s.scans)} scans; {kept})"]
    out[name] += [f"{name}: {note}" for note in s.notes]
  return out


def _check(args: argparse.Namespace) -> str | None:
  """What is wrong with the arguments, before any work (None: fine)."""
  from lrf_jax.io.atomic import path_problem, same_file
  unknown = [m for m in (args.methods or []) if m not in METHODS]
  if unknown:
    return f"--methods: unknown method(s) {unknown}; expected any of {sorted(METHODS)}"
  if not (0.0 < args.min_overlap <= 1.0):
    return f"--min-overlap: expected a fraction in (0, 1], got {args.min_overlap}"
  if args.keypoints < 1:
    return f"--keypoints: expected a positive integer, got {args.keypoints}"
  if args.max_pairs is not None and args.max_pairs < 1:
    return f"--max-pairs: expected a positive integer (omit it for every pair), got {args.max_pairs}"
  if args.max_neighbors < 0:
    return f"--max-neighbors: expected a non-negative integer (0: no cap), got {args.max_neighbors}"
  if not (math.isfinite(args.radius_mr) and args.radius_mr > 0):
    return f"--radius-mr: expected a positive finite number of mr, got {args.radius_mr}"
  try:
    validate_seed(args.seed, "--seed")
  except ValueError as e:
    return str(e)
  if args.address and args.engine == "local":
    return (f"--address: {args.address} is for --engine ray; the local engine runs in this "
            "process")
  for folder in args.scans:
    if not Path(folder).expanduser().is_dir():
      return f"--scans: {folder} is not a folder (expected scans and their pose file)"
  if args.cache_dir and args.engine != "local":
    return ("--cache-dir: the ray engine's workers keep neighbourhoods in memory (only this "
            "process writes files); drop --cache-dir or use --engine local")
  if args.engine == "ray" and _address_problem(args.address):
    return _address_problem(args.address)
  out = Path(args.out).expanduser()
  if path_problem(out):
    return f"--out: {args.out} {path_problem(out)}"
  if out.exists() and not out.is_dir():
    return f"--out: {args.out} is a file; expected a folder (it is created if missing)"
  existing = next(p for p in [out, *out.absolute().parents] if p.exists())
  if not os.access(existing, os.W_OK | os.X_OK):
    return f"--out: {existing} is not writable"
  if args.checkpoint:
    ckpt = Path(args.checkpoint).expanduser()
    if not (ckpt / "checkpoints").is_dir():
      return (f"--checkpoint: {args.checkpoint} is not a train.py workdir (no checkpoints/ "
              "folder in it)")
  for item in args.params:
    path = item.partition("=")[2].partition("@")[0]
    if path and (Path(path).suffix.lower() == ".png" and same_file(Path(path).parent, out)
                 or any(same_file(out / name, path) for name in OUTPUT_FILES)):
      return f"--params {item!r}: {path} is in --out under the name of an output; move it"
  return None


def _address_problem(address: str | None) -> str | None:
  """What is wrong with the Ray cluster address of --engine ray (`engines.address_problem`)."""
  from lrf_jax.batch.engines import address_problem
  return address_problem(address, "--address")


if __name__ == "__main__":
  exit_with(main())
