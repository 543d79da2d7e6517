"""Data-set jobs: one item per scan (frames) or per pair (registration), resumable, on an engine.

A job writes into one output folder:

* `<name>.txt` (a pair's 4 x 4 source->target transform, as `lrf-register --out` writes it,
  whatever the verdict: `results.tsv` holds the verdict) or `<name>.npz` (a scan's frames, as
  `lrf-frames` writes them);
* `results.tsv`: a row per finished item of the job, in the job's order, rewritten atomically
  after each item;
* `.lrf-batch/`: the job's records, one JSON per item (the content hashes of its inputs, the
  options it ran with, its result, the node, the attempt and the lrf_jax version), and a cache
  of the inputs' hashes keyed by (size, mtime, inode), so that an unchanged file is not read
  again.

An item is done when its output exists and its record carries the hashes of its inputs and the
options it ran with: the same job again skips it (touching a file redoes nothing, changing one
byte of a scan redoes exactly the items that read it, a changed option redoes all). A rerun with
nothing to do starts no engine and rewrites nothing. An item that failed (an unreadable scan, too
few points, a pair that raised) has an `error` record naming the file and why; it is not run
again with unchanged inputs and options unless `retry_errors`. Every file is written atomically
(`lrf_jax.io.atomic`), by the driver only: workers read scans and return results.

Items are handed out largest inputs first (the long ones start early, the tail is short).
Before the engine gets the items, the driver runs the first pending one itself, which compiles
the kernels the items need into the on-disk cache; the workers then load them instead of
compiling at the same time. Each item is a pure function of its inputs and options, so the
engine, the number of workers and their order do not change a result.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import stat
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from lrf_jax.batch import engines as engines_mod
from lrf_jax import records
from lrf_jax.batch import items as items_mod
from lrf_jax.batch import scoring, tables
from lrf_jax.batch.tables import check_name, read_pairs
from lrf_jax.io import atomic
from lrf_jax.io.poses import format_matrix
from lrf_jax.multiway.outputs import scan_names

__all__ = ["JobResult", "REGISTER_COLUMNS", "FRAMES_COLUMNS", "STATE", "read_pairs",
           "run_frames", "run_register"]

STATE = ".lrf-batch"
# A record's status: "done"; "error", the item's own failure (a corrupt file), kept until
# `retry_errors`; "transient", a failure of the machine (a lost worker or node, a full disk, a
# cache error), redone by the same command.
STATUSES = ("done", "error", "transient")
REGISTER_COLUMNS = ("name", "source", "target", "init", "status", "success", "reason",
                    *scoring.SCORE_COLUMNS, "seconds", "node", "attempt", "version", "error")
FRAMES_COLUMNS = ("name", "scan", "status", "keypoints", "valid", "seconds", "node", "attempt",
                  "version", "error")
# results.tsv is rewritten after every item; a table this large at most every so many seconds
# (rewriting 10^4 rows after each of 10^4 items would write gigabytes).
_LARGE_TABLE = 1000
_LARGE_TABLE_SECONDS = 2.0


@dataclasses.dataclass(frozen=True)
class Item:
  """One unit of a job: its name (the output file's stem), its input files (absolute) and the
  key that says whether an existing record is still its result."""
  name: str
  inputs: tuple[str, ...]
  key: str


@dataclasses.dataclass
class JobResult:
  """What a job did.

  Attributes:
    rows: the results.tsv rows (dicts keyed by the columns), in the job's order.
    ran: items computed by this call; skipped: items whose record was still valid.
    failed: items whose record is an error (this call's or a kept one).
    seconds: wall time of the call.
    out: the output folder.
  """
  rows: list[dict[str, Any]]
  ran: int
  skipped: int
  failed: int
  seconds: float
  out: Path

  @property
  def counts(self) -> dict[str, int]:
    """The rows' counts (`scoring.counts`): pairs, done, claimed, scored, right and false
    claims (claimed and not right)."""
    return scoring.counts(self.rows)

  @property
  def exit_code(self) -> int:
    """0 when every item is done, 3 when some failed."""
    return 3 if self.failed else 0


# --- the output folder ---

def _check_out(path: Path, given: Any) -> None:
  """ValueError naming `given` when the output folder cannot be one: a file, a symlink loop, a
  path through a file."""
  try:
    if path.exists() and not path.is_dir():
      raise ValueError(f"out: {given} exists and is not a folder; expected a folder for the "
                       "job's outputs")
    path.resolve(strict=False)
  except (OSError, RuntimeError) as e:  # RuntimeError: Python < 3.13 on a symlink loop
    why = "a symlink loop" if "loop" in str(e).lower() or getattr(e, "errno", 0) == 40 else e
    raise ValueError(f"out: {given}: expected a folder for the job's outputs, found {why}"
                     ) from None


# --- hashes and records -----------------------------------------------------------------------

class _Hashes:
  """Content hashes (sha256) of input files, cached by (size, mtime_ns, inode) in the job's
  state folder; a missing or unreadable file, or one that is not a regular file (a folder, a
  FIFO: never opened, reading one would wait for a writer), hashes to a marker saying so."""

  def __init__(self, path: Path):
    self.path = path
    try:
      cache = json.loads(path.read_text())
    except (OSError, ValueError):
      cache = {}
    # Only well-formed entries: a damaged or hand-edited cache costs a re-hash, not the job.
    self.cache = {k: v for k, v in cache.items() if _cache_entry(v)} \
        if isinstance(cache, dict) else {}
    self.changed = False

  def __call__(self, file: str) -> str:
    try:
      st = os.stat(file)
    except OSError as e:
      return f"missing:{e.strerror}"
    if not stat.S_ISREG(st.st_mode):
      return f"not a regular file:{stat.S_IFMT(st.st_mode)}"
    stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
    hit = self.cache.get(file)
    if hit and hit[:3] == stamp:
      return hit[3]
    h = hashlib.sha256()
    try:
      with open(file, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
          h.update(block)
    except OSError as e:
      return f"unreadable:{e.strerror}"
    self.cache[file] = [*stamp, h.hexdigest()]
    self.changed = True
    return h.hexdigest()

  def save(self) -> None:
    if self.changed:
      atomic.write_text(self.path, json.dumps(self.cache))
      self.changed = False


def _cache_entry(value: Any) -> bool:
  """Whether `value` is a hash cache entry: [size, mtime_ns, inode, sha256 hex]."""
  return (isinstance(value, list) and len(value) == 4
          and all(isinstance(v, int) and not isinstance(v, bool) for v in value[:3])
          and isinstance(value[3], str))


def _size(path: str) -> int:
  try:
    return os.stat(path).st_size
  except OSError:
    return 0


def _key(kind: str, hashes: Iterable[str], options: dict[str, Any]) -> str:
  weights = records.weights_hash(options.get("weights"))
  if weights:  # a parameter file: its content, not only its path
    options = {**options, "weights_sha256": weights}
  return records.content_key(kind, *hashes, records.canonical(options))


# --- the job ----------------------------------------------------------------------------------

@dataclasses.dataclass
class _Kind:
  """What differs between the two jobs: the item function, the output suffix, the columns, how
  an item's payload and its results.tsv row are made and how its output is written."""
  name: str
  fn: Callable[[dict[str, Any]], dict[str, Any]]
  suffix: str
  columns: tuple[str, ...]
  payload: Callable[[Item, dict[str, Any]], dict[str, Any]]
  row: Callable[[Item, dict[str, Any]], dict[str, Any]]
  write: Callable[[Path, dict[str, Any]], None]
  n_inputs: tuple[int, ...]  # how many input files an item may have


def _write_transform(path: Path, value: dict[str, Any]) -> None:
  atomic.write_text(path, format_matrix(np.asarray(value["transform"])) + "\n")


def _write_npz(path: Path, value: dict[str, Any]) -> None:
  with atomic.atomic_write(path) as f:
    np.savez(f, **value["arrays"])


def _common(item: Item, rec: dict[str, Any]) -> dict[str, Any]:
  seconds = rec.get("seconds")
  return dict(name=item.name, status=rec["status"],
              seconds="" if seconds is None else f"{seconds:.3f}", node=rec.get("node", ""),
              attempt=rec.get("attempt", ""), version=rec.get("version", ""),
              error=rec.get("error") or "")


def _register_row(item: Item, rec: dict[str, Any]) -> dict[str, Any]:
  done = rec["status"] == "done"
  return dict(_common(item, rec), source=item.inputs[0], target=item.inputs[1],
              init=item.inputs[2] if len(item.inputs) > 2 else "",
              success=str(bool(rec.get("success"))) if done else "",
              reason=rec.get("reason", "") if done else "")


def _frames_row(item: Item, rec: dict[str, Any]) -> dict[str, Any]:
  return dict(_common(item, rec), scan=item.inputs[0], keypoints=rec.get("keypoints", ""),
              valid=rec.get("valid", ""))


REGISTER = _Kind("register", items_mod.register_pair, ".txt", REGISTER_COLUMNS,
                 lambda it, o: dict(source=it.inputs[0], target=it.inputs[1], options=o,
                                    init=it.inputs[2] if len(it.inputs) > 2 else None),
                 _register_row, _write_transform, (2, 3))
FRAMES = _Kind("frames", items_mod.frames_of_scan, ".npz", FRAMES_COLUMNS,
               lambda it, o: dict(scan=it.inputs[0], options=o), _frames_row, _write_npz, (1,))


class _Job:
  """The state of one job in its output folder."""

  def __init__(self, kind: _Kind, named_inputs: Sequence[tuple[str, tuple[str, ...]]],
               out: str | os.PathLike, options: dict[str, Any], *, keep_versions: bool = False,
               force: bool = False, score: scoring.Scoring | None = None):
    self.kind, self.options, self.score = kind, options, score
    self.out = Path(out).expanduser()
    _check_out(self.out, out)
    all_inputs = {p for _, ins in named_inputs for p in ins}
    for name, _ in named_inputs:
      target = self.out / (name + kind.suffix)
      if tables.absolute(target) in all_inputs:
        raise ValueError(f"out: {target} would overwrite the input of the same path; pick "
                         "another output folder")
    tables.check_unique([name for name, _ in named_inputs])
    self.state = self.out / STATE
    self._check_not_foreign([name + kind.suffix for name, _ in named_inputs])
    self.records = self.state / "records"
    try:
      self.records.mkdir(parents=True, exist_ok=True)
    except (NotADirectoryError, FileExistsError) as e:  # a file in the way: a wrong path
      raise ValueError(f"out: {self.out}: expected a folder for the job's outputs, but "
                       f"{e.filename or self.out} is in the way (not a folder)") from None
    except OSError as e:  # a read-only or full disk: one error, no work
      raise atomic.WriteError(self.records, e) from e
    self.lock = records.JobLock(self.state / "lock", force=force, folder=self.out)
    try:
      self.lock.acquire()
    except OSError as e:
      raise atomic.WriteError(self.state / "lock", e) from e
    try:
      self._read_state(named_inputs, keep_versions)
    except BaseException:
      self.lock.release()
      raise

  def _read_state(self, named_inputs: Sequence[tuple[str, tuple[str, ...]]],
                  keep_versions: bool) -> None:
    """The inputs' hashes, the items' keys and the records that still stand (this lrf_jax
    version's, or any with `keep_versions`); the other items' records in the folder (earlier
    jobs'), listed in results.tsv after this job's."""
    hashes = _Hashes(self.state / "hashes.json")
    self.input_hashes = {p: hashes(p) for _, ins in named_inputs for p in ins}
    self.items = [Item(name, ins, _key(self.kind.name, (self.input_hashes[p] for p in ins),
                                       self.options)) for name, ins in named_inputs]
    self.hashes = hashes  # saved when items run: a rerun with nothing to do writes nothing
    self.recs: dict[str, dict[str, Any]] = {}
    self._last_write = -np.inf
    for it in self.items:
      rec = records.read_record(self.records / f"{it.name}.json")
      if (rec is not None and rec.get("key") == it.key and rec.get("status") in STATUSES
          and records.is_current(rec, keep_versions)):
        self.recs[it.name] = rec
    mine = {it.name for it in self.items}
    self.others: list[tuple[Item, dict[str, Any]]] = []
    for path in sorted(self.records.glob("*.json")):
      rec = records.read_record(path)
      if (path.stem in mine or rec is None or rec.get("kind") != self.kind.name
          or rec.get("status") not in STATUSES or rec.get("name") != path.stem
          or not isinstance(rec.get("inputs"), list)
          or len(rec["inputs"]) not in self.kind.n_inputs):
        continue
      if rec["status"] == "done" and not (self.out / (path.stem + self.kind.suffix)).is_file():
        continue
      self.others.append((Item(path.stem, tuple(map(str, rec["inputs"])), str(rec.get("key"))),
                          rec))

  def is_settled(self, item: Item, retry_errors: bool) -> bool:
    """Whether `item`'s record stands: done (its output there), or an item error that is not
    retried; a transient failure never stands."""
    rec = self.recs.get(item.name)
    if rec is None or rec["status"] == "transient":
      return False
    if rec["status"] == "done":
      return (self.out / (item.name + self.kind.suffix)).is_file()
    return not retry_errors

  def _check_not_foreign(self, outputs: list[str]) -> None:
    """ValueError when the folder holds files the job would overwrite and no job state: they
    are someone else's (a previous job's folder always has its state: it is made before any
    output is written)."""
    if self.state.is_dir() or not self.out.is_dir():
      return
    clash = [n for n in (*outputs, "results.tsv")
             if (self.out / n).exists() or (self.out / n).is_symlink()]
    if clash:
      more = f" (and {len(clash) - 1} more)" if len(clash) > 1 else ""
      raise ValueError(f"out: {self.out} holds {clash[0]}{more}, which this job would "
                       f"overwrite, and is not an lrf-batch job's folder (no {STATE}/); choose "
                       "another folder or move those files away")

  def changed_inputs(self, item: Item) -> list[str]:
    """The inputs of `item` whose content is not the one its key was made from (re-hashed
    only when their size, mtime or inode changed)."""
    return [p for p in item.inputs if self.hashes(p) != self.input_hashes[p]]

  def finish(self, item: Item, outcome: engines_mod.Outcome) -> dict[str, Any]:
    """Write an item's output and record (and results.tsv); its record."""
    value = outcome.value
    rec: dict[str, Any] = dict(name=item.name, kind=self.kind.name, inputs=list(item.inputs),
                               key=item.key, options=json.loads(records.canonical(self.options)),
                               node=outcome.node, attempt=outcome.attempt,
                               version=outcome.version)
    changed = self.changed_inputs(item)
    if outcome.error is not None:  # the work around the item died, not the item
      rec.update(status="transient", error=outcome.error)
    elif changed:  # read while it changed: the result may be of neither content
      rec.update(status="error", key=f"changed:{item.key}", error=f"{changed[0]}: changed "
                 "while the job read it; the next run redoes this item")
    else:
      rec.update({k: v for k, v in value.items() if k != "arrays"})
      if rec["status"] == "done":
        self.kind.write(self.out / (item.name + self.kind.suffix), value)
    atomic.write_text(self.records / f"{item.name}.json", json.dumps(rec))
    self.recs[item.name] = rec
    self.write_results(force=False)
    return rec

  def rows(self, everything: bool = False) -> list[dict[str, Any]]:
    """This job's rows in its order; with `everything`, then the earlier jobs' records in the
    folder by name (results.tsv: every record on disk)."""
    mine = [self._row(it, self.recs[it.name]) for it in self.items if it.name in self.recs]
    return mine + [self._row(it, rec) for it, rec in self.others] if everything else mine

  def _row(self, item: Item, rec: dict[str, Any]) -> dict[str, Any]:
    row = self.kind.row(item, rec)
    return row if self.score is None else self.score.row(item.name, row, rec)

  def write_results(self, force: bool = True) -> None:
    """Rewrite results.tsv (atomically) if its content changed. With `force` False (after an
    item) a table of over `_LARGE_TABLE` rows is rewritten at most every `_LARGE_TABLE_SECONDS`
    (each item's record is on disk already; the end of the job rewrites it in any case)."""
    now = time.monotonic()
    if (not force and len(self.recs) > _LARGE_TABLE
        and now - self._last_write < _LARGE_TABLE_SECONDS):
      return
    self._last_write = now
    text = tables.tsv(self.kind.columns, self.rows(everything=True))
    path = self.out / "results.tsv"
    try:
      if path.read_text() == text:
        return
    except OSError:
      pass
    atomic.write_text(path, text)


def _run(kind: _Kind, named_inputs: Sequence[tuple[str, tuple[str, ...]]],
         out: str | os.PathLike, options: dict[str, Any], *, engine: str, address: str | None,
         progress: bool, retry_errors: bool, keep_versions: bool = False,
         force: bool = False, score: scoring.Scoring | None = None) -> JobResult:
  t0 = time.perf_counter()
  runner = engines_mod.make_engine(engine, address)  # checks the engine before any work
  try:
    job = _Job(kind, named_inputs, out, options, keep_versions=keep_versions, force=force,
               score=score)
  except BaseException:
    runner.close()
    raise
  try:
    ran = _run_pending(job, kind, options, runner, progress, retry_errors)
  finally:
    runner.close()
    job.lock.release()
  rows = job.rows()
  return JobResult(rows, ran, len(job.items) - ran, sum(r["status"] != "done" for r in rows),
                   time.perf_counter() - t0, job.out)


def _run_pending(job: _Job, kind: _Kind, options: dict[str, Any], runner: Any, progress: bool,
                 retry_errors: bool) -> int:
  """Run the job's items whose record does not stand; the number run."""
  pending = [it for it in job.items if not job.is_settled(it, retry_errors)]
  if not pending:
    job.write_results()
    return 0
  # Largest inputs first: the long items start early and the last ones to finish are short.
  pending.sort(key=lambda it: -sum(_size(p) for p in it.inputs))
  from tqdm.auto import tqdm
  bar = tqdm(total=len(pending), desc=f"lrf-batch {kind.name}", unit="item",
             disable=not progress)
  failed = 0

  def done(it: Item, outcome: engines_mod.Outcome) -> None:
    nonlocal failed
    rec = job.finish(it, outcome)
    failed += rec["status"] != "done"
    bar.update(1)
    bar.set_postfix(failed=failed, refresh=False)

  job.hashes.save()
  try:
    payloads = [kind.payload(it, options) for it in pending]
    node = runner.driver_node()  # joins the cluster (or refuses its address) before any item
    # The first item on the driver: it compiles the kernels the others load.
    first = next(iter(engines_mod.LocalEngine().run(kind.fn, payloads[:1])))
    done(pending[0], dataclasses.replace(first, node=node))
    for outcome in runner.run(kind.fn, payloads[1:]):
      done(pending[1 + outcome.index], outcome)
  except BaseException:
    bar.close()
    try:  # best effort: the error in flight (Ctrl-C, a full disk) is the one to report
      job.write_results()
    except OSError:
      pass
    raise
  bar.close()
  job.write_results()
  return len(pending)


def run_register(pairs: str | os.PathLike | Sequence[tuple[str, ...]],
                 out: str | os.PathLike, *, engine: str = "local", address: str | None = None,
                 progress: bool = True, retry_errors: bool = False,
                 keep_versions: bool = False, force: bool = False,
                 criteria: scoring.Criteria | str | None = None, **options: Any) -> JobResult:
  """Register every listed pair: `DIR/<name>.txt` (source->target) and `DIR/results.tsv`.

  Each pair is `lrf_jax.register(source, target, **options)`: this layer adds no default of its
  own, so a transform and verdict equal that call's bit for bit.

  Args:
    pairs: a PAIRS.tsv (`tables.read_pair_rows`: with optional `gt` and `init` columns) or
      [(name, source, target)], [(name, source, target, gt path or None)] or [(name, source,
      target, gt path or None, init path or None)]. A pair with an init is
      `register(source, target, init=T, **options)`, its init file one of its inputs (a
      changed init redoes the pair).
    out: the output folder (created).
    engine: "local" (this process) or "ray".
    address: the Ray cluster (`engines.resolve_address`); only with engine="ray".
    progress: a progress bar on stderr (items, rate, ETA, failures).
    retry_errors: run items again whose record is an item error (a transient failure, e.g. a
      lost worker or a full disk, is always run again).
    keep_versions: keep the records of another lrf_jax version as results (default: redo them;
      results.tsv's `version` column names the version of each row).
    force: take over the folder's lock held by a job of another host (a shared file system)
      that is gone; a lock of a dead process of this host is taken over without it.
    criteria: when a pair with a ground truth is right (`scoring.Criteria` or "DEG,DIST", DIST
      in the clouds' units): results.tsv's `right` column and `JobResult.counts`. The errors
      (`rotation_error_deg`, `translation_error`) are written for every pair with a `gt`.
    **options: keyword arguments of `register` (JSON-able values: no `params` or `init`), and
      `bin_layout` ("xyzi", "xyz"): how `.bin` inputs are read (`lrf_jax.io.read_cloud`).

  Returns:
    A `JobResult` (exit_code 0: every pair done; 3: some failed).

  Raises:
    ValueError: a bad pair list, output folder, engine or option (before any work).
    lrf_jax.records.FolderInUse: another job is writing the folder (a ValueError; before any
      work).
  """
  items_mod.check_register_options(options)
  if isinstance(criteria, str):
    criteria = scoring.parse_criteria(criteria)
  listed = tables.read_pair_rows(pairs) if isinstance(pairs, (str, os.PathLike)) else [
      tables.PairRow(check_name(p[0], "pairs: name"), *(
          None if v is None else tables.absolute(v) for v in p[1:]))
      for p in pairs]
  score = scoring.Scoring({r.name: r.gt for r in listed}, criteria)
  return _run(REGISTER, [(r.name, (r.source, r.target) + ((r.init,) if r.init else ()))
                         for r in listed], out, options,
              engine=engine, address=address, progress=progress, retry_errors=retry_errors,
              keep_versions=keep_versions, force=force, score=score)


def run_frames(scans: Sequence[str | os.PathLike], out: str | os.PathLike, *,
               engine: str = "local", address: str | None = None, progress: bool = True,
               retry_errors: bool = False, keep_versions: bool = False, force: bool = False,
               **options: Any) -> JobResult:
  """Frames (and with `descriptor=`, descriptors) of every scan: `DIR/<name>.npz` as
  `lrf-frames` writes them, named as `lrf-register --out-dir` names scans
  (`lrf_jax.multiway.outputs.scan_names`), and `DIR/results.tsv`.

  Args:
    scans: the scan files.
    out: as `run_register`.
    engine: as `run_register`.
    address: as `run_register`.
    progress: as `run_register`.
    retry_errors: as `run_register`.
    keep_versions: as `run_register`.
    force: as `run_register`.
    **options: lrf-frames' options as keywords (`items.FRAMES_OPTIONS`: keypoints, voxel_mr, voxel_size,
      method, weights, radius_mr, viewpoint, descriptor, seed, bin_layout); those not given keep
      lrf-frames' defaults.

  Returns:
    A `JobResult`.

  Raises:
    ValueError: an unknown or bad option, or a bad output folder (before any work).
  """
  items_mod.check_frames_options(options)
  paths = [tables.absolute(s) for s in scans]
  names = [check_name(n, f"scan {p}") for n, p in zip(scan_names(paths), paths)]
  return _run(FRAMES, [(n, (p,)) for n, p in zip(names, paths)], out, options, engine=engine,
              address=address, progress=progress, retry_errors=retry_errors,
              keep_versions=keep_versions, force=force)
