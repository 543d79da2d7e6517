"""The pairwise stage of `register_all` as tasks on an engine, resumable.

Each scan of a candidate pair is described once (`describe_task`: `scan_features.describe_scan`
at the set's resolution), then every pair is registered from the two scans' features
(`pair_task`: `scan_features.register_scans`, and the edge's overlap points). Both are pure
functions of picklable payloads: an engine (`lrf_jax.batch.engines`: this process or a Ray
cluster) runs them anywhere, in any order, and the results are the same.

With a state folder every finished pair leaves a record (`PairRecords`: one JSON file per pair,
named by the hash of what its result depends on: both scans' points, faces and viewpoints, the
options, the resolution, the seed and the weights; never the scans' positions in the run),
written atomically by the driver as it arrives (`lrf_jax.records`); a job run again, with the
same scans in any order, repeated or among new ones, reads the records and redoes only the
pairs without one, and describes only the scans those pairs need. A record of another lrf_jax
version is redone. A pair whose task was lost (a node that died beyond the engine's
retries) leaves no record: the next run redoes it.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from lrf_jax import records
from lrf_jax.registration.options import RegisterOptions
from lrf_jax.search import engine as search_engine
from lrf_jax.progress import restart_clock

__all__ = ["PairRecords", "describe_task", "edge_record", "error_record", "pair_task", "run_pairs",
           "scan_hash"]

# Points per edge in the pose graph's residual.
EDGE_POINTS = 32
# Source points a pair's overlap is looked for among.
OVERLAP_SAMPLES = 4000
# The state folder's file format.
RECORD_VERSION = 1


def _farthest(points: np.ndarray, k: int) -> np.ndarray:
  """k points of `points` by farthest-point sampling from the first (repeated when fewer)."""
  if len(points) <= k:
    return np.resize(points, (k, 3))
  chosen = [0]
  d = np.linalg.norm(points - points[0], axis=1)
  for _ in range(k - 1):
    chosen.append(int(np.argmax(d)))
    d = np.minimum(d, np.linalg.norm(points - points[chosen[-1]], axis=1))
  return points[chosen]


def overlap_points(src: np.ndarray, target: np.ndarray, transform: np.ndarray, distance: float,
                   seed: Sequence[int]) -> np.ndarray:
  """`EDGE_POINTS` points of `src` within `distance` of `target` under `transform`, spread by
  farthest-point sampling among up to `OVERLAP_SAMPLES` seeded ones; (0, 3) when none is."""
  rng = np.random.default_rng(list(seed))
  sub = src if len(src) <= OVERLAP_SAMPLES else src[np.sort(
      rng.choice(len(src), OVERLAP_SAMPLES, replace=False))]
  grid = search_engine.knn_grid(target)
  moved = sub @ transform[:3, :3].T + transform[:3, 3]
  d, _ = search_engine.knn(grid, moved, 1, distance)
  near = sub[np.isfinite(d[:, 0])]
  return _farthest(near, EDGE_POINTS) if len(near) else near


def error_record(i: int, j: int, reason: str, code: str = "error") -> dict[str, Any]:
  """The record of a pair that gave no edge (`reason`; `code` its reason_code)."""
  return dict(i=i, j=j, transform=None, verdict="error", n_inliers=0, overlap=0.0, rmse=None,
              reason_code=code, points=[], reason=reason)


def edge_record(i: int, j: int, reg: Any, error: str | None, src: np.ndarray, target: np.ndarray,
                distance: float, seed: Sequence[int]) -> dict[str, Any]:
  """A pair's result as plain data (what `MultiwayEdge` holds, and its overlap points): from a
  registration `reg` (an object with `transform`, `success`, `reason`, `n_inliers`, `overlap`,
  `rmse`, optionally `estimated` and `reason_code`) or an `error` (no edge)."""
  if error is not None:
    return error_record(i, j, error)
  if not getattr(reg, "estimated", True):
    return error_record(i, j, str(getattr(reg, "reason", "")),
                        str(getattr(reg, "reason_code", "no_hypothesis")))
  t = np.asarray(reg.transform, np.float64)
  pts = overlap_points(src, target, t, distance, seed)
  return dict(i=i, j=j, transform=t.tolist(), verdict="success" if reg.success else "not sure",
              reason=str(getattr(reg, "reason", "")), n_inliers=int(reg.n_inliers),
              overlap=float(reg.overlap), rmse=float(reg.rmse),
              reason_code=str(getattr(reg, "reason_code", "")), points=pts.tolist())


def _error_text(e: BaseException) -> str:
  """A task's error as a message; Ctrl-C that surfaced as another exception (numba turns one
  inside a kernel into a SystemError) is raised again as a KeyboardInterrupt."""
  from lrf_jax.io.atomic import caused_by_interrupt
  if caused_by_interrupt(e):
    raise KeyboardInterrupt from e
  return str(e) if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"


def describe_task(payload: dict[str, Any]) -> dict[str, Any]:
  """One scan's features: {"features": `ScanFeatures`} or {"error": message}.

  Args:
    payload: {"cloud": `CheckedCloud`, "name": str, "options": `RegisterOptions`, "mr": float,
      "viewpoint": (3,) or None, "params": learned parameters or None}.
  """
  from lrf_jax.registration.scan_features import describe_scan
  try:
    features = describe_scan(payload["cloud"], payload["options"], mr=payload["mr"],
                             viewpoint=payload["viewpoint"], params=payload["params"],
                             name=f"scan {payload['name']}")
  except Exception as e:  # noqa: BLE001 -- a scan that cannot be described gives no edges
    text = _error_text(e)
    where = f"scan {payload['name']}"
    return {"error": text if where in text else f"{where}: {text}"}
  return {"features": features}


def pair_task(payload: dict[str, Any]) -> dict[str, Any]:
  """One pair's edge record (`edge_record`) from the two scans' features.

  Args:
    payload: {"i", "j": scan indices, "source", "target": `ScanFeatures`, "options":
      `RegisterOptions`, "distance": the overlap distance (cloud units), "seed": the overlap
      points' seed (`overlap_seed`)}.
  """
  from lrf_jax.registration.scan_features import register_scans
  a, b = payload["source"], payload["target"]
  reg, error = None, None
  try:
    reg = register_scans(a, b, payload["options"])
  except Exception as e:  # noqa: BLE001 -- a pair that cannot be registered is an error edge
    error = _error_text(e)
  return edge_record(payload["i"], payload["j"], reg, error, a.runs[0].side.points,
                     b.runs[0].side.points, payload["distance"], payload["seed"])


def scan_hash(cloud: Any, viewpoint: Any) -> str:
  """sha256 of a scan's points, faces and viewpoint (what its features depend on)."""
  return records.array_hash(cloud.points, cloud.faces, viewpoint)


def overlap_seed(seed: int, source_hash: str, target_hash: str) -> tuple[int, int, int]:
  """The seed of a pair's overlap points: the run's seed and the two scans' content (never
  their positions in a run, so that a pair's record is the same in any run that has it)."""
  return (int(seed), int(source_hash[:16], 16), int(target_hash[:16], 16))


class PairRecords:
  """The finished pairs of a job in `folder` (None: nothing kept), found by what they are: the
  two scans' content (`scan_hash`, source then target), the options, the resolution, the
  overlap distance and the parameters, never the scans' positions in the run. `get(i, j)` the
  record of this run's pair (i, j) (with i and j set to this run's positions), `put(i, j,
  record)` writes it (atomically). A record of another lrf_jax version is redone."""

  def __init__(self, folder: str | os.PathLike | None, scan_hashes: Sequence[str],
               options: RegisterOptions, mr: float, distance: float, params: Any):
    self.folder = None if folder is None else Path(folder) / "pairs"
    self.common = records.canonical(dict(format=RECORD_VERSION, options=options.as_dict(),
                                         mr=float(mr).hex(), distance=float(distance).hex(),
                                         params=records.params_hash(params),
                                         weights=records.weights_hash(
                                             options.description.weights)))
    self.hashes = list(scan_hashes)

  def _path(self, i: int, j: int) -> Path:
    assert self.folder is not None
    key = records.content_key(self.hashes[i], self.hashes[j], self.common)
    return self.folder / f"{key[:40]}.json"

  def get(self, i: int, j: int) -> dict[str, Any] | None:
    """The record of pair (i, j), or None (none kept, one of another lrf_jax version, or one
    this job cannot read)."""
    if self.folder is None:
      return None
    rec = records.read_record(self._path(i, j))
    if rec is None or "verdict" not in rec or not records.is_current(rec):
      return None
    return {**rec, "i": i, "j": j}

  def put(self, i: int, j: int, record: dict[str, Any]) -> None:
    if self.folder is not None:
      self.folder.mkdir(parents=True, exist_ok=True)
      stored = {k: v for k, v in record.items() if k not in ("i", "j")}
      records.write_record(self._path(i, j), dict(stored, source=self.hashes[i],
                                                  target=self.hashes[j]))


def _bar(total: int, progress: bool, desc: str) -> Any:
  """A progress bar of one stage (its own total: a scan is described faster than a pair is
  registered, and one rate for both would mislead); none for a stage with nothing to do."""
  from tqdm.auto import tqdm
  unit = "scan" if desc.startswith("describing") else "pair"
  return tqdm(total=total, desc=desc, unit=unit, disable=not progress or total == 0)


def tick(bar: Any, first: bool) -> None:
  """One item of `bar` done; after the `first` that ran a task, its clock restarts
  (`restart_clock`)."""
  bar.update(1)
  if first:
    restart_clock(bar)


def run_pairs(clouds: Sequence[Any], names: Sequence[str], pairs: Sequence[tuple[int, int]], *,
              options: RegisterOptions, mr: float, viewpoints: Sequence[Any], distance: float,
              params: Any, engine: Any, records: PairRecords, progress: bool
              ) -> tuple[list[dict[str, Any]], dict[str, int]]:
  """Every pair's edge record, in the order of `pairs`, and the work done:
  {"scans_described", "pairs_registered", "pairs_resumed"}.

  The scans of the pairs without a record are described (once each) on `engine`, their
  features shared with the pair tasks (`engine.put`), then those pairs registered on `engine`
  and recorded as they finish."""
  out: dict[int, dict[str, Any]] = {}
  for k, (i, j) in enumerate(pairs):
    rec = records.get(i, j)
    if rec is not None:
      out[k] = rec
  todo = [k for k in range(len(pairs)) if k not in out]
  scans = sorted({s for k in todo for s in pairs[k]})
  bar = _bar(len(scans), progress, "describing scans")
  try:
    features = _describe_all(clouds, names, scans, options, mr, viewpoints, params, engine, bar)
    bar.close()
    bar = _bar(len(todo), progress, "registering pairs")
    payloads = []
    for k in todo:
      i, j = pairs[k]
      payloads.append(dict(i=i, j=j, source=features[i], target=features[j], options=options,
                           distance=distance,
                           seed=overlap_seed(options.inputs.seed, records.hashes[i], records.hashes[j])))
    ran = 0
    for k, rec, task in _registered(engine, todo, payloads, features, pairs):
      out[k] = rec
      if rec.pop("lost", False) is False:
        records.put(*pairs[k], rec)
      ran += task
      tick(bar, task and ran == 1)  # an error edge without a task is no pair's time
  except BaseException:
    bar.close()
    if progress:  # what is printed next starts a line of its own
      print(file=sys.stderr, flush=True)
    raise
  bar.close()
  work = dict(scans_described=len(scans), pairs_registered=len(todo),
              pairs_resumed=len(pairs) - len(todo))
  return [out[k] for k in range(len(pairs))], work


def _describe_all(clouds, names, scans, options, mr, viewpoints, params, engine, bar
                  ) -> dict[int, Any]:
  """scan -> a handle of its features (`engine.put`) or {"error": message}."""
  payloads = [dict(cloud=clouds[s], name=names[s], options=options, mr=mr,
                   viewpoint=viewpoints[s], params=params) for s in scans]
  features: dict[int, Any] = {}
  for outcome in _run(engine, describe_task, payloads):
    s = scans[outcome.index]
    value = outcome.value if outcome.error is None else {"error": outcome.error}
    if "features" in value and engine is not None:  # stored once, read by all its pairs
      value = {"features": engine.put(value["features"])}
    features[s] = value["features"] if "features" in value else value
    tick(bar, len(features) == 1)
  return features


def _registered(engine, todo, payloads, features, pairs) -> Iterator[tuple[int, dict, bool]]:
  """(pair position, record, whether a task ran for it) as the pairs finish; a pair with a scan
  that could not be described is an error edge without a task (those come first)."""
  ready, runnable = [], []
  for k, payload in zip(todo, payloads):
    bad = next((features[s] for s in pairs[k] if isinstance(features[s], dict)), None)
    if bad is not None:
      i, j = pairs[k]
      ready.append((k, error_record(i, j, bad["error"]), False))
    else:
      runnable.append((k, payload))
  yield from ready
  for outcome in _run(engine, pair_task, [p for _, p in runnable]):
    k = runnable[outcome.index][0]
    if outcome.error is not None:  # lost with its node: no record, the next run redoes it
      i, j = pairs[k]
      yield k, {**error_record(i, j, f"the engine lost this pair: {outcome.error}"),
                "lost": True}, True
    else:
      yield k, outcome.value, True


@dataclasses.dataclass(frozen=True)
class _Done:
  index: int
  value: Any
  error: str | None = None


def _run(engine: Any, fn: Callable[[Any], Any], payloads: list[Any]) -> Iterator[Any]:
  """`engine.run(fn, payloads)`, or in this process when `engine` is None."""
  if not payloads:
    return iter(())
  if engine is None:
    return (_Done(k, fn(p)) for k, p in enumerate(payloads))
  return engine.run(fn, payloads)
