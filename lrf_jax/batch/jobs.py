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

import csv
import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from lrf_jax.batch import engines as engines_mod
from lrf_jax.batch import items as items_mod
from lrf_jax.io import atomic
from lrf_jax.io.poses import format_matrix
from lrf_jax.registration.multiway import scan_names

__all__ = ["JobResult", "REGISTER_COLUMNS", "FRAMES_COLUMNS", "STATE", "read_pairs",
           "run_frames", "run_register"]

STATE = ".lrf-batch"
REGISTER_COLUMNS = ("name", "source", "target", "status", "success", "reason", "seconds",
                    "node", "attempt", "version", "error")
FRAMES_COLUMNS = ("name", "scan", "status", "keypoints", "valid", "seconds", "node", "attempt",
                  "version", "error")
_MAX_NAME_BYTES = 200  # leaves room for a suffix and the temporary file's decorations
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
  def exit_code(self) -> int:
    """0 when every item is done, 3 when some failed."""
    return 3 if self.failed else 0


# --- names and inputs -------------------------------------------------------------------------

def check_name(name: str, where: str) -> str:
  """`name` if it can name an output file in the job's folder, else ValueError naming `where`."""
  bad = (not name or name in (".", "..") or name.startswith(".") or "/" in name or "\\" in name
         or "\0" in name or len(name.encode("utf-8", "surrogateescape")) > _MAX_NAME_BYTES)
  if bad:
    raise ValueError(f"{where}: expected a file name without a folder, not starting with '.', "
                     f"at most {_MAX_NAME_BYTES} bytes, got {name!r}")
  return name


def read_pairs(path: str | os.PathLike) -> list[tuple[str, str, str]]:
  """The pairs of a PAIRS.tsv: a tab-separated file with a header naming the columns `source`
  and `target` (paths; relative ones are relative to the TSV's folder) and optionally `name`
  (default: the data row's number, 1-based, zero-padded to at least 4 digits).

  Returns:
    [(name, source, target)], paths absolute.

  Raises:
    FileNotFoundError: no such file.
    ValueError: a missing column, an empty field, a name that cannot name a file or a repeated
      name; the message names the file, the line and the field.
  """
  p = Path(path).expanduser()
  if not p.is_file():
    raise FileNotFoundError(f"{path}: no such file (expected a PAIRS.tsv)")
  with open(p, newline="", encoding="utf-8") as f:
    rows = list(csv.reader(f, delimiter="\t"))
  rows = [r for r in rows if any(c.strip() for c in r)]
  if not rows:
    raise ValueError(f"{p}: expected a header line naming the columns source and target, "
                     "found an empty file")
  header = [c.strip() for c in rows[0]]
  for col in ("source", "target"):
    if col not in header:
      raise ValueError(f"{p}: line 1: expected a header with the columns source and target "
                       f"(tab-separated), found {header}")
  width = max(4, len(str(len(rows) - 1)))
  out: list[tuple[str, str, str]] = []
  seen: dict[str, int] = {}
  for lineno, row in enumerate(rows[1:], start=2):
    rec = dict(zip(header, (c.strip() for c in row)))
    for col in ("source", "target"):
      if not rec.get(col):
        raise ValueError(f"{p}: line {lineno}: column {col}: expected a path, found nothing")
    name = rec.get("name") or f"{lineno - 1:0{width}d}"
    check_name(name, f"{p}: line {lineno}: column name")
    if name in seen:
      raise ValueError(f"{p}: line {lineno}: column name: {name!r} is also the name of line "
                       f"{seen[name]}; names must be unique")
    seen[name] = lineno
    src, tgt = ((p.parent / Path(rec[c]).expanduser()).resolve() for c in ("source", "target"))
    out.append((name, str(src), str(tgt)))
  return out


# --- hashes and records -----------------------------------------------------------------------

class _Hashes:
  """Content hashes (sha256) of input files, cached by (size, mtime_ns, inode) in the job's
  state folder; a missing or unreadable file hashes to a marker saying so."""

  def __init__(self, path: Path):
    self.path = path
    try:
      self.cache = json.loads(path.read_text())
    except (OSError, ValueError):
      self.cache = {}
    self.changed = False

  def __call__(self, file: str) -> str:
    try:
      st = os.stat(file)
    except OSError as e:
      return f"missing:{e.strerror}"
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


def _size(path: str) -> int:
  try:
    return os.stat(path).st_size
  except OSError:
    return 0


def _canonical(options: dict[str, Any]) -> str:
  return json.dumps(options, sort_keys=True, default=lambda v: np.asarray(v).tolist())


def _key(kind: str, hashes: Iterable[str], options: dict[str, Any]) -> str:
  return hashlib.sha256(f"{kind}|{'|'.join(hashes)}|{_canonical(options)}".encode()).hexdigest()


def _read_record(path: Path) -> dict[str, Any] | None:
  try:
    rec = json.loads(path.read_text())
  except (OSError, ValueError):
    return None
  return rec if isinstance(rec, dict) else None


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
              success=str(bool(rec.get("success"))) if done else "",
              reason=rec.get("reason", "") if done else "")


def _frames_row(item: Item, rec: dict[str, Any]) -> dict[str, Any]:
  return dict(_common(item, rec), scan=item.inputs[0], keypoints=rec.get("keypoints", ""),
              valid=rec.get("valid", ""))


REGISTER = _Kind("register", items_mod.register_pair, ".txt", REGISTER_COLUMNS,
                 lambda it, o: dict(source=it.inputs[0], target=it.inputs[1], options=o),
                 _register_row, _write_transform)
FRAMES = _Kind("frames", items_mod.frames_of_scan, ".npz", FRAMES_COLUMNS,
               lambda it, o: dict(scan=it.inputs[0], options=o), _frames_row, _write_npz)


def _tsv(columns: Sequence[str], rows: Iterable[dict[str, Any]]) -> str:
  def cell(v: Any) -> str:
    return str(v).replace("\t", " ").replace("\n", " ")
  lines = ["\t".join(columns)]
  lines += ["\t".join(cell(r.get(c, "")) for c in columns) for r in rows]
  return "\n".join(lines) + "\n"


class _Job:
  """The state of one job in its output folder."""

  def __init__(self, kind: _Kind, named_inputs: Sequence[tuple[str, tuple[str, ...]]],
               out: str | os.PathLike, options: dict[str, Any]):
    self.kind, self.options = kind, options
    self.out = Path(out).expanduser()
    if self.out.exists() and not self.out.is_dir():
      raise ValueError(f"out: {out} exists and is not a folder; expected a folder for the job's "
                       "outputs")
    all_inputs = {p for _, ins in named_inputs for p in ins}
    for name, _ in named_inputs:
      target = self.out / (name + kind.suffix)
      if str(target.resolve()) in all_inputs:
        raise ValueError(f"out: {target} would overwrite the input of the same path; pick "
                         "another output folder")
    self.state = self.out / STATE
    self.records = self.state / "records"
    self.records.mkdir(parents=True, exist_ok=True)
    hashes = _Hashes(self.state / "hashes.json")
    self.items = [Item(name, ins, _key(kind.name, map(hashes, ins), options))
                  for name, ins in named_inputs]
    self.hashes = hashes  # saved when items run: a rerun with nothing to do writes nothing
    self.recs: dict[str, dict[str, Any]] = {}
    self._last_write = -np.inf
    for it in self.items:
      rec = _read_record(self.records / f"{it.name}.json")
      if rec is not None and rec.get("key") == it.key:
        self.recs[it.name] = rec

  def is_settled(self, item: Item, retry_errors: bool) -> bool:
    rec = self.recs.get(item.name)
    if rec is None:
      return False
    if rec["status"] == "done":
      return (self.out / (item.name + self.kind.suffix)).is_file()
    return not retry_errors

  def finish(self, item: Item, outcome: engines_mod.Outcome) -> dict[str, Any]:
    """Write an item's output and record (and results.tsv); its record."""
    value = outcome.value
    rec: dict[str, Any] = dict(name=item.name, kind=self.kind.name, inputs=list(item.inputs),
                               key=item.key, options=json.loads(_canonical(self.options)),
                               node=outcome.node, attempt=outcome.attempt,
                               version=outcome.version)
    if outcome.error is not None:
      rec.update(status="error", error=outcome.error)
    else:
      rec.update({k: v for k, v in value.items() if k != "arrays"})
      if rec["status"] == "done":
        self.kind.write(self.out / (item.name + self.kind.suffix), value)
    atomic.write_text(self.records / f"{item.name}.json", json.dumps(rec))
    self.recs[item.name] = rec
    self.write_results(force=False)
    return rec

  def rows(self) -> list[dict[str, Any]]:
    return [self.kind.row(it, self.recs[it.name]) for it in self.items if it.name in self.recs]

  def write_results(self, force: bool = True) -> None:
    """Rewrite results.tsv (atomically) if its content changed. With `force` False (after an
    item) a table of over `_LARGE_TABLE` rows is rewritten at most every `_LARGE_TABLE_SECONDS`
    (each item's record is on disk already; the end of the job rewrites it in any case)."""
    now = time.monotonic()
    if (not force and len(self.recs) > _LARGE_TABLE
        and now - self._last_write < _LARGE_TABLE_SECONDS):
      return
    self._last_write = now
    text = _tsv(self.kind.columns, self.rows())
    path = self.out / "results.tsv"
    try:
      if path.read_text() == text:
        return
    except OSError:
      pass
    atomic.write_text(path, text)


def _run(kind: _Kind, named_inputs: Sequence[tuple[str, tuple[str, ...]]],
         out: str | os.PathLike, options: dict[str, Any], *, engine: str, address: str | None,
         progress: bool, retry_errors: bool) -> JobResult:
  t0 = time.perf_counter()
  runner = engines_mod.make_engine(engine, address)  # checks the engine before any work
  job = _Job(kind, named_inputs, out, options)
  pending = [it for it in job.items if not job.is_settled(it, retry_errors)]
  skipped = len(job.items) - len(pending)
  # Largest inputs first: the long items start early and the last ones to finish are short.
  pending.sort(key=lambda it: -sum(_size(p) for p in it.inputs))
  if pending:
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
      # The first item on the driver: it compiles the kernels the others load.
      first = next(iter(engines_mod.LocalEngine().run(kind.fn, payloads[:1])))
      done(pending[0], dataclasses.replace(first, node=runner.driver_node()))
      for outcome in runner.run(kind.fn, payloads[1:]):
        done(pending[1 + outcome.index], outcome)
    finally:
      bar.close()
      runner.close()
      job.write_results()
  else:
    job.write_results()
  rows = job.rows()
  return JobResult(rows, len(pending), skipped, sum(r["status"] != "done" for r in rows),
                   time.perf_counter() - t0, job.out)


def run_register(pairs: str | os.PathLike | Sequence[tuple[str, str, str]],
                 out: str | os.PathLike, *, engine: str = "local", address: str | None = None,
                 progress: bool = True, retry_errors: bool = False,
                 **options: Any) -> JobResult:
  """Register every listed pair: `DIR/<name>.txt` (source->target) and `DIR/results.tsv`.

  Each pair is `lrf_jax.register(source, target, **options)`: this layer adds no default of its
  own, so a transform and verdict equal that call's bit for bit.

  Args:
    pairs: a PAIRS.tsv (`read_pairs`) or [(name, source, target)].
    out: the output folder (created).
    engine: "local" (this process) or "ray".
    address: the Ray cluster (`engines.resolve_address`); only with engine="ray".
    progress: a progress bar on stderr (items, rate, ETA, failures).
    retry_errors: run items again whose record is an error.
    **options: keyword arguments of `register` (JSON-able values: no `params` or `init`).

  Returns:
    A `JobResult` (exit_code 0: every pair done; 3: some failed).

  Raises:
    ValueError: a bad pair list, output folder, engine or option (before any work).
  """
  items_mod.check_register_options(options)
  listed = read_pairs(pairs) if isinstance(pairs, (str, os.PathLike)) else [
      (check_name(n, "pairs: name"), str(Path(s).expanduser().resolve()),
       str(Path(t).expanduser().resolve())) for n, s, t in pairs]
  return _run(REGISTER, [(n, (s, t)) for n, s, t in listed], out, options, engine=engine,
              address=address, progress=progress, retry_errors=retry_errors)


def run_frames(scans: Sequence[str | os.PathLike], out: str | os.PathLike, *,
               engine: str = "local", address: str | None = None, progress: bool = True,
               retry_errors: bool = False, **options: Any) -> JobResult:
  """Frames (and with `descriptor=`, descriptors) of every scan: `DIR/<name>.npz` as
  `lrf-frames` writes them, named as `lrf-register --out-dir` names scans
  (`registration.multiway.scan_names`), and `DIR/results.tsv`.

  Args:
    scans: the scan files.
    out, engine, address, progress, retry_errors: as `run_register`.
    **options: lrf-frames' options as keywords (`items.FRAMES_OPTIONS`: keypoints, voxel_mr,
      method, radius_mr, viewpoint, descriptor, seed); those not given keep lrf-frames'
      defaults.

  Returns:
    A `JobResult`.

  Raises:
    ValueError: an unknown or bad option, or a bad output folder (before any work).
  """
  items_mod.check_frames_options(options)
  paths = [str(Path(s).expanduser().resolve()) for s in scans]
  names = [check_name(n, f"scan {p}") for n, p in zip(scan_names(paths), paths)]
  return _run(FRAMES, [(n, (p,)) for n, p in zip(names, paths)], out, options, engine=engine,
              address=address, progress=progress, retry_errors=retry_errors)
