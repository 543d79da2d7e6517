"""Reproduce the paper's repeatability experiments for LRF-Net and the hand-crafted LRFs.

    python evaluate.py                                   # main experiment on the data it finds
    python evaluate.py --data /path/to/data --experiments repeatability noise decimation
    python evaluate.py --checkpoint runs/default --methods lrf_net toldi shot --out out/

With no data (no --data, LRF_DATA unset, nothing under data/) it runs on the procedural demo set.
Writes results.json, report.md and PNG figures to --out and prints the summary table. This file
is intentionally kept short; the logic lives in lrf_jax/evaluation/.
"""

import argparse
import json
import sys
import time
from pathlib import Path

from tqdm.auto import tqdm

import lrf_jax
from lrf_jax import evaluation
from lrf_jax.evaluation import description, pose
from lrf_jax.evaluation.experiments import DATASETS, EXPERIMENTS

REAL = ["BR@0.1", "BR@0.3", "BR@0.5", "UWA3M", "UWAOR", "bunny"]


def main(argv=None) -> int:
  ap = argparse.ArgumentParser(description="LRF repeatability experiments (MeanCos).")
  ap.add_argument("--data", default=None, help="data root (default: $LRF_DATA, then data/)")
  ap.add_argument("--datasets", nargs="+", default=None, choices=sorted(DATASETS),
                  help="default: every real dataset found, else demo")
  ap.add_argument("--experiments", nargs="+", default=["repeatability"],
                  choices=EXPERIMENTS + ("description", "pose"))
  ap.add_argument("--methods", nargs="+", default=None,
                  help=f"default: all of {sorted(lrf_jax.METHODS)}")
  ap.add_argument("--checkpoint", default=None,
                  help="a train.py workdir: its best checkpoint is 'lrf_net', its final "
                       "parameters 'lrf_net[final]' (default: the shipped weights)")
  ap.add_argument("--params", nargs="+", default=[], metavar="LABEL=PATH",
                  help="extra learned columns from parameter files: LABEL=PATH[@METHOD] (METHOD "
                       "defaults to lrf_net), e.g. mine=w.msgpack or p=w.msgpack@lrf_net_plus")
  ap.add_argument("--keypoints", type=int, default=1000, help="keypoints per pair (paper: 1000)")
  ap.add_argument("--max-pairs", type=int, default=None, help="at most N pairs per dataset")
  ap.add_argument("--radius-mr", type=float, default=15.0)
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--max-neighbors", type=int, default=evaluation.MAX_NEIGHBORS,
                  help="cap on all-neighbour patches (dense scans); 0 = no cap")
  ap.add_argument("--cache-dir", default=None, help="keep neighbourhoods on disk here")
  ap.add_argument("--out", default="out/eval", help="output folder")
  args = ap.parse_args(argv)

  notes = []
  names = args.datasets or REAL
  ok, missing = evaluation.available(names, args.data, DATASETS)
  if missing:  # the whole message (where we looked, how to get the data) before any work
    _, full = evaluation.available(names, args.data, DATASETS, full=True)
    print("\n\n".join(full), file=sys.stderr)
    if args.datasets:
      print("error: data not found for the --datasets asked for (above)", file=sys.stderr)
      return 2
  notes += missing
  if not ok:
    ok = ["demo"]
    notes.append("no real data found: ran on the procedural demo set (synthetic, labelled)")
  # lrf_net_plus (the most repeatable) first; lrf_net_variant needs its own params.
  default_methods = ["lrf_net_plus"] + [m for m in lrf_jax.METHODS
                                        if m not in ("lrf_net_variant", "lrf_net_plus")]
  runs = [evaluation.MethodRun(m, m, options=evaluation.paper_options(m))
          for m in (args.methods or default_methods)]
  if args.checkpoint:
    from lrf_jax.train_lib import restore_params
    best, cfg = restore_params(args.checkpoint, "best")
    final, _ = restore_params(args.checkpoint, "latest")
    runs = [evaluation.MethodRun(r.label, r.method, params=best, options=r.options)
            if r.method == "lrf_net" else r for r in runs]
    runs.append(evaluation.MethodRun("lrf_net[final]", "lrf_net", params=final,
                                     options=evaluation.EXACT_NETWORK))
    notes.append(f"lrf_net: best checkpoint of {args.checkpoint} (config {cfg.name}); "
                 "lrf_net[final]: its latest")
  for item in args.params:
    label, sep, path = item.partition("=")
    path, _, method = path.partition("@")
    if not sep:
      raise SystemExit(f"--params: expected LABEL=PATH[@METHOD], got {item!r}")
    method = method or "lrf_net"
    runs.append(evaluation.MethodRun(label, method, params=lrf_jax.load_params(path),
                                     options=evaluation.paper_options(method)))
  opts = evaluation.EvalOptions(data_root=args.data, n_keypoints=args.keypoints, seed=args.seed,
                                radius_mr=args.radius_mr, max_pairs=args.max_pairs,
                                max_neighbors=args.max_neighbors or None)
  cache = evaluation.PatchCache(args.cache_dir)
  records, other = [], []
  out = Path(args.out)
  t0 = time.perf_counter()
  with tqdm(desc="evaluate", unit="record", dynamic_ncols=True) as bar:
    for exp in args.experiments:
      if exp in ("description", "pose"):  # descriptors / 6-DoF pose with LRF-Net frames
        lrf_params = next((r.params for r in runs if r.method == "lrf_net"), None)
        gen = (description.run_description(ok, opts, cache, params=lrf_params)
               if exp == "description" else pose.run_pose(ok, opts, cache, params=lrf_params))
        for rec in gen:
          other.append(rec)
          bar.set_postfix(exp=exp, ds=rec["dataset"])
          bar.update(1)
        continue
      for rec in evaluation.run_experiment(exp, ok, runs, opts, cache):
        records.append(rec)
        if len(records) % 50 == 0:  # keep what is done if the run is stopped
          out.mkdir(parents=True, exist_ok=True)
          (out / "partial_records.jsonl").write_text(
              "\n".join(json.dumps({k: v for k, v in r.items() if not k.startswith("_")})
                        for r in records))
        bar.set_postfix(exp=exp, ds=rec["dataset"], pair=rec["pair"][:18])
        bar.update(1)
  evaluation.write_results(records, out, notes=notes, meta={
      "args": vars(args), "seconds": time.perf_counter() - t0,
      "patch_cache": {"hits": cache.hits, "misses": cache.misses}})
  lrf = next((r for r in runs if r.method == "lrf_net"), None)
  if lrf is not None:  # the paper's weight visualisation, on the first dataset's first pair
    from lrf_jax.evaluation.experiments import DATASETS as _D
    first = _D[ok[0]][0](args.data, args.seed)[0]
    evaluation.report.weights_figure(first, lrf.params, out, radius_mr=args.radius_mr)
  if any(r.method in ("lrf_net", "lrf_net_plus") for r in runs):
    evaluation.report.weight_maps_figure(out)
  extra_md = []
  if any(r["experiment"] == "description" for r in other):
    desc = [r for r in other if r["experiment"] == "description"]
    extra_md.append(description.description_report(desc))
    description.plot_rpc(desc, out)
  if any(r["experiment"] == "pose" for r in other):
    extra_md.append(pose.pose_report([r for r in other if r["experiment"] == "pose"]))
  if other:
    (out / "report.md").write_text((out / "report.md").read_text() + "\n" + "\n".join(extra_md))
    (out / "results_description_pose.json").write_text(json.dumps(
        [{k: v for k, v in r.items() if not k.startswith("_")} for r in other], indent=1,
        default=float))
  print(evaluation.markdown_report(records, notes=notes))
  print("\n".join(extra_md))
  print(f"wrote {out / 'results.json'}, {out / 'report.md'} and figures "
        f"({time.perf_counter() - t0:.0f} s)")
  return 0


if __name__ == "__main__":
  sys.exit(main())
