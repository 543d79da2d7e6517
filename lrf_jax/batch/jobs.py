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
import re
import stat
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
  """`name` if it can name an output file in the job's folder, else ValueError naming `where`:
  empty, "." or "..", starting with ".", a path separator, a control character (a tab or a
  newline would also break results.tsv) or over `_MAX_NAME_BYTES` bytes."""
  bad = (not name or name in (".", "..") or name.startswith(".") or "/" in name or "\\" in name
         or any(ord(ch) < 32 or ord(ch) == 127 for ch in name)
         or len(name.encode("utf-8", "surrogateescape")) > _MAX_NAME_BYTES)
  if bad:
    raise ValueError(f"{where}: expected a file name without a folder or control characters, "
                     f"not starting with '.', at most {_MAX_NAME_BYTES} bytes, got {name!r}")
  return name


def _tsv_text(p: Path) -> str:
  """The text of a PAIRS.tsv: UTF-8 (a byte-order mark dropped), or UTF-16 with its mark (a
  spreadsheet's "Unicode text"); ValueError naming the file and the line of a bad byte."""
  try:
    data = p.read_bytes()
  except OSError as e:
    raise ValueError(f"{p}: could not read it ({e.strerror or e})") from None
  encoding = "utf-16" if data[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"
  try:
    text = data.decode(encoding)
  except UnicodeDecodeError as e:
    line = data[:e.start].count(b"\n") + 1
    raise ValueError(f"{p}: line {line}: expected UTF-8 text, found the byte "
                     f"0x{data[e.start]:02x}") from None
  if "\0" in text:
    line = text[:text.index("\0")].count("\n") + 1
    raise ValueError(f"{p}: line {line}: expected text, found a NUL byte")
  return text


def _tsv_lines(p: Path) -> list[tuple[int, list[str]]]:
  """(line number, fields) of each non-blank line of a PAIRS.tsv. Fields are split at tabs
  only and stripped; a field wholly in double quotes (as spreadsheets quote) is unquoted, ""
  standing for one quote; any other quote is part of the field (no field spans lines)."""
  out = []
  for lineno, line in enumerate(re.split(r"\r\n|\r|\n", _tsv_text(p)), start=1):
    fields = []
    for field in line.split("\t"):
      field = field.strip()
      if len(field) >= 2 and field[0] == field[-1] == '"':
        field = field[1:-1].replace('""', '"')
      fields.append(field)
    if any(fields):
      out.append((lineno, fields))
  return out


def _tsv_header(p: Path, lines: list[tuple[int, list[str]]]) -> list[str]:
  if not lines:
    raise ValueError(f"{p}: expected a header line naming the columns source and target, "
                     "found an empty file")
  lineno, header = lines[0]
  for col in ("source", "target"):
    if col not in header:
      raise ValueError(f"{p}: line {lineno}: expected a header with the columns source and "
                       f"target (tab-separated), found {header}")
  named = [c for c in header if c]
  twice = sorted({c for c in named if named.count(c) > 1})
  if twice:
    raise ValueError(f"{p}: line {lineno}: column {twice[0]!r} appears twice in the header")
  return header


def read_pairs(path: str | os.PathLike) -> list[tuple[str, str, str]]:
  """The pairs of a PAIRS.tsv: a tab-separated file (UTF-8; blank lines skipped) with a header
  naming the columns `source` and `target` (paths; relative ones are relative to the TSV's
  folder) and optionally `name` (default: the data row's number, 1-based, zero-padded to 4
  digits: 0001, ..., 9999, 10000; a name that does not change when pairs are appended). Other
  columns are ignored.

  Returns:
    [(name, source, target)], paths absolute.

  Raises:
    FileNotFoundError: no such file.
    ValueError: not text, a missing or repeated column, a row with more fields than the
      header, an empty field, a name that cannot name a file or a repeated name (also ignoring
      case: one file on a case-insensitive file system); the message names the file, the line
      and the field.
  """
  p = Path(path).expanduser()
  if not p.is_file():
    what = "not a regular file" if p.exists() else "no such file"
    raise FileNotFoundError(f"{path}: {what} (expected a PAIRS.tsv)")
  lines = _tsv_lines(p)
  header = _tsv_header(p, lines)
  out: list[tuple[str, str, str]] = []
  seen: dict[str, int] = {}
  for row, (lineno, fields) in enumerate(lines[1:], start=1):
    where = f"{p}: line {lineno}"
    if any(fields[len(header):]):
      raise ValueError(f"{where}: {len(fields)} tab-separated fields, but the header names "
                       f"{len(header)} columns")
    rec = dict(zip(header, fields))
    for col in ("source", "target"):
      if not rec.get(col):
        raise ValueError(f"{where}: column {col}: expected a path, found nothing")
    # Zero-padded to 4 digits whatever the number of rows: appending the 10000th pair must not
    # rename (and so redo) the 9999 before it.
    name = check_name(rec.get("name") or f"{row:04d}", f"{where}: column name")
    if name.casefold() in seen:
      raise ValueError(f"{where}: column name: {name!r} is also the name of line "
                       f"{seen[name.casefold()]} (ignoring case); names must be unique")
    seen[name.casefold()] = lineno
    src, tgt = ((p.parent / Path(rec[c]).expanduser()).resolve() for c in ("source", "target"))
    out.append((name, str(src), str(tgt)))
  return out


def _check_unique(names: Sequence[str]) -> None:
  """ValueError when two items share a name, also ignoring case (their outputs would be one
  file on a case-insensitive file system)."""
  seen: dict[str, str] = {}
  for name in names:
    if name.casefold() in seen:
      raise ValueError(f"names: {seen[name.casefold()]!r} and {name!r} would name the same "
                       "output file; names must be unique (also ignoring case)")
    seen[name.casefold()] = name


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
    _check_unique([name for name, _ in named_inputs])
    self.state = self.out / STATE
    self._check_not_foreign([name + kind.suffix for name, _ in named_inputs])
    self.records = self.state / "records"
    try:
      self.records.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a read-only or full disk, a file in the way: one error, no work
      raise atomic.WriteError(self.records, e) from e
    hashes = _Hashes(self.state / "hashes.json")
    self.input_hashes = {p: hashes(p) for _, ins in named_inputs for p in ins}
    self.items = [Item(name, ins, _key(kind.name, (self.input_hashes[p] for p in ins), options))
                  for name, ins in named_inputs]
    self.hashes = hashes  # saved when items run: a rerun with nothing to do writes nothing
    self.recs: dict[str, dict[str, Any]] = {}
    self._last_write = -np.inf
    for it in self.items:
      rec = _read_record(self.records / f"{it.name}.json")
      if rec is not None and rec.get("key") == it.key and rec.get("status") in ("done", "error"):
        self.recs[it.name] = rec

  def is_settled(self, item: Item, retry_errors: bool) -> bool:
    rec = self.recs.get(item.name)
    if rec is None:
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
                               key=item.key, options=json.loads(_canonical(self.options)),
                               node=outcome.node, attempt=outcome.attempt,
                               version=outcome.version)
    changed = self.changed_inputs(item)
    if outcome.error is not None:
      rec.update(status="error", error=outcome.error)
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
    except BaseException:
      bar.close()
      runner.close()
      try:  # best effort: the error in flight (Ctrl-C, a full disk) is the one to report
        job.write_results()
      except OSError:
        pass
      raise
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
    **options: lrf-frames' options as keywords (`items.FRAMES_OPTIONS`: keypoints, voxel_mr, voxel_size,
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
