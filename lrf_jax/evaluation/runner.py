"""The whole evaluation job behind `evaluate.py`: which runs, the jobs, the outputs.

`evaluate(plan, out)` cuts every experiment of an `EvalPlan` into jobs (one pair at one
setting, `experiments.PairJob`), runs them on the plan's engine (`lrf_jax.batch.engines`: in
this process, or Ray tasks; `pair_records` is the pure function the engine maps over them) and
puts their records back in job order, so every engine gives the same records. One progress bar
(its total is the number of records, so it shows an ETA, timed from the end of the first
record: a first run spends that one compiling); what is done, in order, is kept in
`partial_records.jsonl` every 50 records; results.json, report.md and the figures are written
by this process only, each atomically (`lrf_jax.io.atomic`: a failed write leaves the previous
file); `evaluate.py` only parses arguments into a plan.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator

from tqdm.auto import tqdm

from lrf_jax.batch import engines
from lrf_jax.evaluation import description, pose, report
from lrf_jax.evaluation.experiments import (ABLATION_X, ABLATION_Z, AS_NAMED, DECIMATIONS,
                                            NOISE_LEVELS, RADII_MR, ROTATIONS_DEG, EvalOptions,
                                            PairJob, clean_datasets, clean_pairs, dataset_pairs,
                                            experiment_jobs, iter_pairs, job_records,
                                            plus_ablation_runs, points_only_runs)
from lrf_jax.evaluation.repeatability import (EXACT_NETWORK, MethodRun, PatchCache,
                                              paper_options)
from lrf_jax.frames import METHODS
from lrf_jax.io import atomic
from lrf_jax.defaults import DEFAULT_METHOD
from lrf_jax.frames.weights import (WEIGHTS_KINDS, load_params, weights_file, weights_options,
                                    weights_params)
from lrf_jax.progress import restart_clock

# Experiments that sweep one nuisance: the number of settings per clean pair.
SWEEPS = {"noise": len(NOISE_LEVELS), "decimation": len(DECIMATIONS), "radius": len(RADII_MR),
          "rotation": len(ROTATIONS_DEG)}
PARTIAL_EVERY = 50  # records between two writes of partial_records.jsonl


def default_methods() -> list[str]:
  """Every registered method, lrf_net_plus (the most repeatable) first; lrf_net_variant left
  out (it needs its own parameters, see the ablation experiment)."""
  return ["lrf_net_plus"] + [m for m in METHODS if m not in ("lrf_net_variant", "lrf_net_plus")]


def method_runs(methods: list[str] | None = None, *, checkpoint: str | None = None,
                params: tuple[str, ...] = (), weights: tuple[str, ...] = ()
                ) -> tuple[list[MethodRun], list[str]]:
  """The columns of the evaluation and the notes that say where learned parameters came from.

  Args:
    methods: method names (None: `default_methods()`); each runs with `paper_options`.
    checkpoint: a train.py workdir: its best checkpoint replaces lrf_net's shipped weights and
      its latest parameters add a column "lrf_net[final]".
    params: "LABEL=PATH[@METHOD]" items: extra learned columns from parameter files (METHOD
      defaults to lrf_net).
    weights: weights `compute_frames(weights=)` names ("objects", "rooms", "streets" or a
      parameter file's path): a column "lrf_net_plus[KIND]" each (a file's: its stem), with the
      options the weights were trained under (`frames.weights.weights_options`).

  Returns:
    (runs, notes).

  Raises:
    ValueError: an unknown method (in `methods` or after a `params` item's @), a `params` item
      not of the form LABEL=PATH[@METHOD] or whose file does not exist, a `checkpoint` that is
      not a train.py workdir with a checkpoint. Each message names the option.
  """
  unknown = [m for m in (methods or []) if m not in METHODS]
  if unknown:
    raise ValueError(f"--methods: unknown method(s) {unknown}; expected any of {sorted(METHODS)}")
  parsed = []
  for item in params:
    label, sep, path = item.partition("=")
    path, _, method = path.partition("@")
    method = method or "lrf_net"
    if not sep or not label or not path:
      raise ValueError(f"--params: expected LABEL=PATH[@METHOD], got {item!r}")
    if method not in METHODS:
      raise ValueError(f"--params {item!r}: unknown method {method!r}; expected one of "
                       f"{sorted(METHODS)}")
    if not Path(path).expanduser().is_file():
      raise ValueError(f"--params {item!r}: no such parameter file {path}")
    parsed.append((label, path, method))
  runs = [MethodRun(m, m, options=paper_options(m)) for m in (methods or default_methods())]
  notes = []
  if checkpoint:
    from lrf_jax.learning.checkpoints import restore_params
    try:
      best, cfg = restore_params(checkpoint, "best")
      final, _ = restore_params(checkpoint, "latest")
    except (FileNotFoundError, ValueError) as e:
      raise ValueError(f"--checkpoint: {e}") from None
    runs = [MethodRun(r.label, r.method, params=best, options=r.options)
            if r.method == "lrf_net" else r for r in runs]
    runs.append(MethodRun("lrf_net[final]", "lrf_net", params=final, options=EXACT_NETWORK))
    notes.append(f"lrf_net: best checkpoint of {checkpoint} (config {cfg.name}); "
                 "lrf_net[final]: its latest")
  for label, path, method in parsed:
    try:
      loaded = load_params(path)
    except (FileNotFoundError, ValueError) as e:
      raise ValueError(f"--params {label}={path}: {e}") from None
    runs.append(MethodRun(label, method, params=loaded, options=paper_options(method)))
  for w in weights:
    spec = METHODS[DEFAULT_METHOD]
    try:
      path = weights_file(spec.weights, w)
      loaded = weights_params(spec.weights, w)
      options = weights_options(path)
    except (FileNotFoundError, ValueError) as e:
      raise ValueError(f"--{e}") from None
    label = f"{DEFAULT_METHOD}[{w if w in WEIGHTS_KINDS else path.stem}]"
    runs.append(MethodRun(label, DEFAULT_METHOD, params=loaded, options=tuple(options.items())))
    notes.append(f"{label}: {path.name}" + (f", read with {options}" if options else ""))
  return runs, notes


@dataclasses.dataclass
class EvalPlan:
  """What one evaluation runs.

  Attributes:
    datasets: names of `DATASETS` whose data was found, and of the scan sets of
      `options.scans` (`experiments.scan_set_names`).
    experiments: names of `EXPERIMENTS`, "description" or "pose".
    runs: the method columns (`method_runs`).
    options: the knobs shared by every experiment.
    notes: lines for the report (skipped data, where parameters came from).
    cache_dir: keep neighborhoods on disk here (None: in memory only).
    meta: extra fields for results.json's "meta".
    methods_named: the runs were named by the caller (--methods); else the points_only
      experiment runs its own default hand-crafted methods (`POINTS_ONLY_HANDCRAFTED`).
    engine: where the jobs run: "local" (this process, one job after another) or "ray"
      (`lrf_jax.batch.engines`); the records are the same on either.
    address: the Ray cluster of the "ray" engine ("local": a new instance of this machine on
      127.0.0.1; None: $RAY_ADDRESS, else "local"); None for the local engine.
  """

  datasets: list[str]
  experiments: list[str]
  runs: list[MethodRun]
  options: EvalOptions
  notes: list[str] = dataclasses.field(default_factory=list)
  cache_dir: str | None = None
  meta: dict[str, Any] = dataclasses.field(default_factory=dict)
  methods_named: bool = True
  engine: str = "local"
  address: str | None = None


def _experiment_runs(experiment: str, plan: EvalPlan) -> list[MethodRun]:
  """The method columns `experiment` runs under `plan`."""
  if experiment == "points_only":
    return points_only_runs(plan.runs if plan.methods_named else ())
  return plan.runs if experiment == "repeatability" else plus_ablation_runs()


def count_records(experiment: str, plan: EvalPlan) -> int:
  """How many records `experiment` yields under `plan` (reads the pair lists, runs nothing)."""
  opts = plan.options
  if experiment in ("description", "pose"):
    per_pair = (len(description.default_runs(None)) if experiment == "description"
                else len(pose.ESTIMATORS))
    return per_pair * sum(1 for _ in iter_pairs(plan.datasets, opts))
  if experiment in AS_NAMED:
    return (len(_experiment_runs(experiment, plan))
            * sum(1 for _ in iter_pairs(plan.datasets, opts)))
  pairs = sum(len(clean_pairs(ds, opts)) for ds in clean_datasets(plan.datasets, opts))
  per_pair = (len(ABLATION_Z) * len(ABLATION_X) if experiment == "ablation"
              else SWEEPS[experiment] * len(plan.runs))
  return pairs * per_pair


def _jobs(experiment: str, plan: EvalPlan) -> Iterator[PairJob]:
  """The jobs of `experiment` under `plan`, in the order of its records."""
  if experiment in ("description", "pose"):
    params = next((r.params for r in plan.runs if r.method == "lrf_net"), None)
    for ds, setting, pair in iter_pairs(plan.datasets, plan.options):
      yield PairJob(experiment, ds, pair, setting, (), plan.options, params=params)
    return
  runs = [] if experiment == "points_only" and not plan.methods_named else plan.runs
  yield from experiment_jobs(experiment, plan.datasets, runs, plan.options)


def pair_records(job: PairJob, cache: PatchCache | None = None) -> list[dict[str, Any]]:
  """The records of one job: the pure, picklable function an engine maps over the jobs (the
  same records in any process: `job_records`, `description.evaluate_description_pair` or
  `pose.evaluate_pose_pair`, "dataset" set to the job's).

  Args:
    job: the payload (`PairJob`; "description" and "pose" jobs carry LRF-Net's parameters).
    cache: a patch cache shared with the other jobs of this process (None: one for this job).
  """
  cache = PatchCache() if cache is None else cache
  opts = job.options
  if job.experiment == "description":
    recs = description.evaluate_description_pair(
        job.pair, description.default_runs(job.params), n_keypoints=opts.n_keypoints,
        seed=opts.seed, radius_mr=opts.radius_mr, cache=cache, setting=job.setting)
  elif job.experiment == "pose":
    recs = pose.evaluate_pose_pair(job.pair, n_keypoints=opts.n_keypoints, seed=opts.seed,
                                   radius_mr=opts.radius_mr, params=job.params, cache=cache,
                                   setting=job.setting)
  else:
    return job_records(job, cache)
  for rec in recs:
    rec["dataset"] = job.dataset
  return recs


def _records(experiment: str, plan: EvalPlan, cache: PatchCache) -> Iterator[dict[str, Any]]:
  """The records of `experiment` in this process, one job after another."""
  for job in _jobs(experiment, plan):
    yield from pair_records(job, cache)


class JobError(RuntimeError):
  """A job that its engine could not run: its worker or node lost beyond Ray's retries, its
  function raised on a worker, or a worker of another lrf_jax version refused it."""


def _clean(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
  return [{k: v for k, v in r.items() if not k.startswith("_")} for r in records]


def evaluate(plan: EvalPlan, out: Path, *, progress: bool = True) -> str:
  """Run `plan`, write its outputs to `out` and return the markdown report.

  The jobs (one pair at one setting, `PairJob`) run on `plan.engine`; their records are put
  back in job order, so the outputs do not depend on the engine nor on the order the jobs
  finish in. Only this process writes files. Writes results.json (the repeatability records
  and `meta`), report.md, the figures of `report.plot_figures`, LRF-Net's weight figures when a
  learned method ran, and for the description / pose experiments
  results_description_pose.json and their sections of report.md (with the RPC figure).
  `partial_records.jsonl` holds the records done so far (in job order) while it runs and is
  removed once every output is written.

  Raises:
    JobError: a job the engine could not run (the message names its experiment, dataset,
      pair and setting); the records of the jobs before it are in partial_records.jsonl.
    ValueError: an unknown engine, or an address given to the local engine.
  """
  out = Path(out)
  cache = PatchCache(plan.cache_dir)
  engine = engines.make_engine(plan.engine, plan.address)
  # The local engine runs the jobs here: they share this run's patch cache (and its counts).
  fn = functools.partial(pair_records, cache=cache) if engine.name == "local" else pair_records
  total = sum(count_records(exp, plan) for exp in plan.experiments)
  t0 = time.perf_counter()
  jobs = [job for exp in plan.experiments for job in _jobs(exp, plan)]
  try:
    desc = "evaluate" if engine.name == "local" else f"evaluate ({engine.name})"
    with tqdm(total=total, desc=desc, unit="record", dynamic_ncols=True,
              disable=not progress) as bar:
      records, other = _run_jobs(jobs, engine, fn, bar, out)
  finally:
    engine.close()
  meta = dict(plan.meta, seconds=time.perf_counter() - t0,  # the workers' caches: not counted
              patch_cache={"hits": cache.hits, "misses": cache.misses}
              if engine.name == "local" else None)
  report.write_results(records, out, notes=plan.notes, meta=meta)
  if set(plan.experiments) - {"points_only"}:  # points_only runs its own columns only
    _learned_figures(plan, out)
  text = report.markdown_report(records, notes=plan.notes)
  extra_md = _description_pose_outputs(other, out)
  if extra_md:
    atomic.write_text(out / "report.md", text + "\n" + "\n".join(extra_md))
  (out / "partial_records.jsonl").unlink(missing_ok=True)  # complete: results.json has them
  return "\n".join([text] + extra_md)


def _run_jobs(jobs: list[PairJob], engine: engines.Engine,
              fn: Callable[[PairJob], list[dict[str, Any]]], bar: Any, out: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
  """Run `jobs` on `engine`; (repeatability-like records, description and pose records), each
  in job order. The bar counts records as their jobs finish (its rate and ETA timed from the
  first record); partial_records.jsonl is rewritten every `PARTIAL_EVERY` records in order.

  Raises:
    JobError: an outcome with an error (the records before its job are kept on disk first).
  """
  records: list[dict[str, Any]] = []
  other: list[dict[str, Any]] = []
  done: dict[int, list[dict[str, Any]]] = {}
  nxt = 0
  for outcome in engine.run(fn, jobs):
    job = jobs[outcome.index]
    if outcome.error is not None:
      if records:
        _write_partial(records, out)
      kept = f"; the {len(records)} records before it are in {out / 'partial_records.jsonl'}"
      raise JobError(f"{job.describe()}: the {engine.name} engine could not run it "
                     f"({outcome.error}){kept if records else ''}")
    done[outcome.index] = outcome.value
    for rec in outcome.value:
      bar.set_postfix(exp=job.experiment, ds=rec["dataset"], pair=str(rec.get("pair", ""))[:18])
      bar.update(1)
      if bar.n == 1:
        restart_clock(bar)
    while nxt in done:
      aside = jobs[nxt].experiment in ("description", "pose")
      for rec in done.pop(nxt):
        (other if aside else records).append(rec)
        if not aside and len(records) % PARTIAL_EVERY == 0:
          _write_partial(records, out)
      nxt += 1
  return records, other


def _write_partial(records: list[dict[str, Any]], out: Path) -> None:
  """partial_records.jsonl: the records done so far, one JSON object a line (kept if the run
  is stopped)."""
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_text(out / "partial_records.jsonl", "\n".join(json.dumps(r) for r in _clean(records)))


def _learned_figures(plan: EvalPlan, out: Path) -> None:
  """The paper's weight visualisation on the first dataset's first pair, and the weight maps."""
  lrf = next((r for r in plan.runs if r.method == "lrf_net"), None)
  if lrf is not None:
    first = dataset_pairs(plan.datasets[0], plan.options)[0][0]
    report.weights_figure(first, lrf.params, out, radius_mr=plan.options.radius_mr)
  if any(r.method in ("lrf_net", "lrf_net_plus") for r in plan.runs):
    report.weight_maps_figure(out)


def _description_pose_outputs(other: list[dict[str, Any]], out: Path) -> list[str]:
  """Report sections and files of the description and pose records (none: [])."""
  extra_md = []
  desc = [r for r in other if r["experiment"] == "description"]
  if desc:
    extra_md.append(description.description_report(desc))
    description.plot_rpc(desc, out)
  poses = [r for r in other if r["experiment"] == "pose"]
  if poses:
    extra_md.append(pose.pose_report(poses))
  if other:
    atomic.write_text(out / "results_description_pose.json",
                      json.dumps(_clean(other), indent=1, default=float))
  return extra_md
