"""Wall time of the default evaluation (`python evaluate.py`: repeatability of every method on
every real dataset), per dataset and method, cold and then again with a warm patch cache.

    LRF_DATA=/path/to/data python benchmarks/bench_eval.py [--max-pairs 2] [--datasets ...]

The baseline in the same run is the second pass, which finds every neighborhood in the patch
cache (disk cache in a temporary folder) and compiled functions in memory: the difference is
what the search and compilation cost. `--results out/eval/results.json` instead summarises the
per-record `seconds` of an evaluation that already ran (e.g. the full default one).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lrf_jax import METHODS, evaluation  # noqa: E402

REAL = ["BR@0.1", "BR@0.3", "BR@0.5", "UWA3M", "UWAOR", "bunny"]


def _table(records: list[dict], title: str) -> None:
  per = collections.defaultdict(float)
  methods, datasets = [], []
  for r in records:
    if r.get("seconds") is None:
      continue
    per[(r["dataset"], r["method"])] += r["seconds"]
    methods += [r["method"]] if r["method"] not in methods else []
    datasets += [r["dataset"]] if r["dataset"] not in datasets else []
  print(f"\n### {title}\n")
  print("| dataset | " + " | ".join(methods) + " | total |")
  print("|---|" + "---:|" * (len(methods) + 1))
  for d in datasets:
    row = [per[(d, m)] for m in methods]
    print(f"| {d} | " + " | ".join(f"{x:.1f}" for x in row) + f" | {sum(row):.1f} |")
  tot = [sum(per[(d, m)] for d in datasets) for m in methods]
  print("| all | " + " | ".join(f"{x:.1f}" for x in tot) + f" | {sum(tot):.1f} |")


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--datasets", nargs="+", default=REAL)
  ap.add_argument("--methods", nargs="+", default=[m for m in METHODS if m != "lrf_net_variant"])
  ap.add_argument("--max-pairs", type=int, default=2)
  ap.add_argument("--results", default=None, help="summarise this results.json instead")
  args = ap.parse_args()
  print(f"machine: {platform.machine()}, {os.cpu_count()} cores")
  if args.results:
    data = json.loads(Path(args.results).read_text())
    recs = [r for r in data["records"] if r["experiment"] == "repeatability"]
    _table(recs, f"seconds per dataset and method, {args.results} "
                 f"(wall {data.get('meta', {}).get('seconds', float('nan')):.0f} s)")
    return
  ok, missing = evaluation.available(args.datasets, args.data, evaluation.DATASETS)
  for m in missing:
    print(m)
  runs = [evaluation.MethodRun(m, m) for m in args.methods]
  opts = evaluation.EvalOptions(data_root=args.data, max_pairs=args.max_pairs)
  with tempfile.TemporaryDirectory() as tmp:
    cache = evaluation.PatchCache(tmp)
    for label in ("cold (search + compile + frames)", "warm (cached patches, compiled)"):
      t0 = time.perf_counter()
      recs = list(evaluation.run_experiment("repeatability", ok, runs, opts, cache))
      wall = time.perf_counter() - t0
      peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
      _table(recs, f"{label}: {len(recs)} records, wall {wall:.1f} s, peak RSS {peak:,.0f} MB, "
                   f"max {args.max_pairs} pairs per dataset")


if __name__ == "__main__":
  main()
