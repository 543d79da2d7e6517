"""Compare runs of `bench_scenes.py`: their counts side by side, the cases whose outcome moved,
and what the best of the runs would reach case by case.

    python benchmarks/compare_scenes.py BASE.json OTHER.json [MORE.json ...]
        [--labels base,other,...] [--method lrf] [--changes]

Each argument is a `bench_scenes.py --json` file of the same cases (the same seed); the first is
the base. Printed, as Markdown:

* per run and split ("tune", "test"): right (true successes), claimed, false claims (claimed
  and not right), claimed of right, and the same for the 10-30 % overlap bin;
* "any run": per split, the cases right under at least one of the runs and the cases claimed
  and right under at least one of them. It bounds what choosing among these runs case by case
  could reach, an oracle no rule has: a target above it needs a case none of the runs gets;
* with `--changes`, every case whose (right, claimed) differs from the base's, or whose rotation
  error moved by more than 1 deg, with both reasons.

`--method` picks the records' method ("lrf", the default; "open3d" and "kiss" where the runs
have them: their claims are empty where the method has no verdict).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

LOW = "10-30%"
SPLITS = ("tune", "test")


def load(path: str | Path, method: str = "lrf") -> dict[str, dict[str, Any]]:
  """{case: {"split", "bin", "right", "claimed", "re", "reason"}} of one `--json` file.

  Raises:
    ValueError: the file is not a `bench_scenes.py --json` output with `method`'s records (the
      message names the file and the field).
  """
  data = json.loads(Path(path).read_text())
  if not isinstance(data, dict) or not isinstance(data.get("records"), list):
    raise ValueError(f"{path}: expected a bench_scenes.py --json file (a 'records' list)")
  out = {}
  for k, rec in enumerate(data["records"]):
    res = rec.get(method)
    if not isinstance(res, dict) or "true" not in res:
      raise ValueError(f"{path}: records[{k}].{method}: expected a result with 'true' (is "
                       f"'{method}' a method of this run?)")
    out[rec["case"]] = {"split": rec["split"], "bin": rec["bin"], "right": bool(res["true"]),
                        "claimed": bool(res.get("claimed")), "re": res.get("re"),
                        "reason": res.get("reason") or res.get("error") or ""}
  return out


def case_seed(path: str | Path) -> Any:
  """The `--seed` a `bench_scenes.py --json` file's cases were built with (None if unrecorded):
  runs of different seeds have the same case names and different cases."""
  return (json.loads(Path(path).read_text()).get("args") or {}).get("seed")


def counts(run: dict[str, dict[str, Any]], split: str, low: bool = False) -> dict[str, int]:
  """Right, claimed and false claims (claimed, not right) of `run`'s cases of `split` (only
  the 10-30 % bin with `low`), and their number."""
  cases = [c for c in run.values() if c["split"] == split and (not low or c["bin"] == LOW)]
  return {"cases": len(cases), "right": sum(c["right"] for c in cases),
          "claimed": sum(c["claimed"] for c in cases),
          "false": sum(c["claimed"] and not c["right"] for c in cases)}


def any_run(runs: list[dict[str, dict[str, Any]]], split: str, low: bool = False
            ) -> dict[str, int]:
  """Cases of `split` (only the 10-30 % bin with `low`) right under at least one run, and
  claimed and right under at least one run (the best of the runs, case by case)."""
  names = [n for n, c in runs[0].items() if c["split"] == split and (not low or c["bin"] == LOW)]
  return {"cases": len(names),
          "right": sum(any(r[n]["right"] for r in runs) for n in names),
          "claimed_right": sum(any(r[n]["right"] and r[n]["claimed"] for r in runs)
                               for n in names)}


def _share(part: int, whole: int) -> str:
  return f"{100 * part / whole:.0f} %" if whole else "-"


def counts_table(runs: list[dict[str, dict[str, Any]]], labels: list[str]) -> str:
  """The Markdown table of `counts` per run and split, then the "any run" rows."""
  lines = ["| run | split | cases | right | claimed | false | claimed of right "
           "| 10-30 %: cases | right | claimed | false |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  for label, run in zip(labels, runs):
    for split in SPLITS:
      a, lo = counts(run, split), counts(run, split, low=True)
      lines.append(f"| {label} | {split} | {a['cases']} | {a['right']} | {a['claimed']} | "
                   f"{a['false']} | {_share(a['claimed'] - a['false'], a['right'])} | "
                   f"{lo['cases']} | {lo['right']} | {lo['claimed']} | {lo['false']} |")
  for split in SPLITS:
    a, lo = any_run(runs, split), any_run(runs, split, low=True)
    lines.append(f"| any run | {split} | {a['cases']} | {a['right']} | "
                 f"{a['claimed_right']} (right) | - | - | {lo['cases']} | {lo['right']} | "
                 f"{lo['claimed_right']} (right) | - |")
  return "\n".join(lines)


def changes(base: dict[str, dict[str, Any]], other: dict[str, dict[str, Any]],
            degrees: float = 1.0) -> list[str]:
  """The cases whose (right, claimed) differs between `base` and `other`, or whose rotation
  error moved by more than `degrees`: one line each, then both reasons."""
  out = []
  for name, a in base.items():
    b = other[name]
    moved = (a["re"] is not None and b["re"] is not None and abs(a["re"] - b["re"]) > degrees)
    if (a["right"], a["claimed"]) != (b["right"], b["claimed"]) or moved:
      def state(c: dict[str, Any]) -> str:
        re = "-" if c["re"] is None else f"{c['re']:.2f} deg"
        return f"{re}, right {c['right']}, claimed {c['claimed']}"
      out.append(f"- {a['split']} {name}: {state(a)} -> {state(b)}\n"
                 f"    - before: {a['reason'][:200]}\n    - after: {b['reason'][:200]}")
  return out


def main(argv: list[str] | None = None) -> None:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("runs", nargs="+", help="bench_scenes.py --json files; the first is the base")
  ap.add_argument("--labels", help="comma-separated names of the runs (default: file stems)")
  ap.add_argument("--method", default="lrf", help="the records' method (default lrf)")
  ap.add_argument("--changes", action="store_true",
                  help="list the cases whose outcome differs from the base's")
  args = ap.parse_args(argv)
  labels = args.labels.split(",") if args.labels else [Path(p).stem for p in args.runs]
  if len(labels) != len(args.runs):
    ap.error(f"--labels: expected {len(args.runs)} names, got {len(labels)}")
  try:
    runs = [load(p, args.method) for p in args.runs]
  except (OSError, ValueError, KeyError) as e:
    sys.exit(f"error: {e}")
  seeds = [case_seed(p) for p in args.runs]
  if len(set(map(str, seeds))) > 1:
    sys.exit(f"error: the runs' cases were built with different seeds ({seeds}); compare runs "
             "of the same seed")
  for path, run in zip(args.runs[1:], runs[1:]):
    if set(run) != set(runs[0]):
      sys.exit(f"error: {path}: its cases are not those of {args.runs[0]} "
               f"({len(set(run) ^ set(runs[0]))} differ); compare runs of the same seed")
  print(counts_table(runs, labels))
  if args.changes:
    for label, run in zip(labels[1:], runs[1:]):
      lines = changes(runs[0], run)
      print(f"\n{label} against {labels[0]}: {len(lines)} cases moved")
      if lines:
        print("\n".join(lines))


if __name__ == "__main__":
  main()
