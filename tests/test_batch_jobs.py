"""lrf_jax.batch.jobs: one job per output folder (the lock), transient failures redone,
records of another version redone, results.tsv as every record on disk, odd paths; PAIRS.tsv as
a spreadsheet saves it (a byte order mark, UTF-16, blank lines, stray quotes) and its errors named
by file and line; the job layer's refusals, interrupts and changed scans, with a stand-in for the
item's computation (`fake_frames`: the job layer is under test, not the frames)."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import records, registration
from lrf_jax.batch import items, jobs
from lrf_jax.cli import batch as batch_cli
from tests.test_batch import OPTS, make_scans, tsv_rows, write_pairs


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
  return make_scans(tmp_path_factory.mktemp("scans"), 3)


def _tsv(folder: Path, scans: list[Path], names=("p0", "p1")) -> Path:
  s, m = scans[:3], scans[3:]
  return write_pairs(folder / f"{'-'.join(names)}.tsv",
                     [(n, str(s[int(n[1])]), str(m[int(n[1])])) for n in names])


def _lock(out: Path, **holder) -> Path:
  path = out / jobs.STATE / "lock"
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text(json.dumps({"host": socket.gethostname(), "start": None,
                              "command": "lrf-batch register other.tsv --out x", **holder}))
  return path


@pytest.fixture
def sleeper():
  proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
  yield proc
  proc.kill()
  proc.wait()


def test_a_folder_in_use_is_refused_before_any_work(tmp_path, scans, sleeper, capsys):
  out = tmp_path / "out"
  _lock(out, pid=sleeper.pid)
  with pytest.raises(records.FolderInUse, match=f"pid {sleeper.pid}.*lrf-batch register other"):
    jobs.run_register(_tsv(tmp_path, scans), out, progress=False, **OPTS)
  assert not list((out / jobs.STATE / "records").glob("*"))
  assert batch_cli.main(["register", str(_tsv(tmp_path, scans)), "--out", str(out),
                         "--no-progress"]) == 2
  err = capsys.readouterr().err
  assert err.startswith("error: ") and f"pid {sleeper.pid}" in err and socket.gethostname() in err


def test_a_lock_left_by_a_dead_process_is_taken_over_with_a_note(tmp_path, scans, capsys):
  out = tmp_path / "out"
  dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                        capture_output=True, text=True, check=True)
  lock = _lock(out, pid=int(dead.stdout))
  res = jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False, **OPTS)
  assert (res.ran, res.exit_code) == (1, 0)
  assert "no longer running; taking its lock over" in capsys.readouterr().err
  assert not lock.exists()  # released when the job ended


def test_a_lock_of_another_host_is_taken_over_only_with_force(tmp_path, scans):
  out = tmp_path / "out"
  _lock(out, pid=1, host="another-host.example")
  tsv = _tsv(tmp_path, scans, ("p0",))
  with pytest.raises(records.FolderInUse, match="another-host.example.*--force"):
    jobs.run_register(tsv, out, progress=False, **OPTS)
  assert jobs.run_register(tsv, out, progress=False, force=True, **OPTS).ran == 1


def test_the_lock_is_released_when_a_job_fails(tmp_path, scans, monkeypatch):
  out = tmp_path / "out"

  def interrupted(*a, **k):
    raise KeyboardInterrupt
  monkeypatch.setattr(registration, "register", interrupted)
  with pytest.raises(KeyboardInterrupt):
    jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False, **OPTS)
  assert not (out / jobs.STATE / "lock").exists()


def test_two_processes_on_one_folder_one_is_refused(tmp_path, scans):
  """Two lrf-batch jobs at once on one --out: the second exits 2 before any work, naming the
  first's pid; the first finishes and its results.tsv is whole."""
  out = tmp_path / "out"
  cmd = [sys.executable, "-m", "lrf_jax.cli.batch", "register"]
  opts = ["--out", str(out), "--no-progress", "--keypoints", "600", "--correspondences", "200"]
  first = subprocess.Popen([*cmd, str(_tsv(tmp_path, scans, ("p0", "p1", "p2"))), *opts],
                           stderr=subprocess.PIPE, text=True)
  lock = out / jobs.STATE / "lock"
  t0 = time.monotonic()
  while not lock.exists():
    assert first.poll() is None, first.stderr.read() if first.stderr else ""
    assert time.monotonic() - t0 < 300
    time.sleep(0.05)
  second = subprocess.run([*cmd, str(_tsv(tmp_path, scans, ("p2", "p1"))), *opts],
                          capture_output=True, text=True, timeout=300)
  assert first.wait(timeout=600) == 0
  assert second.returncode == 2, second.stderr
  assert f"pid {first.pid}" in second.stderr and "error:" in second.stderr
  assert [r["name"] for r in tsv_rows(out / "results.tsv")] == ["p0", "p1", "p2"]


def test_results_tsv_holds_every_record_of_the_folder(tmp_path, scans):
  """Jobs with overlapping pair lists into one folder, one after the other: results.tsv lists
  every record on disk (this job's rows first, in its order, then the others by name)."""
  out = tmp_path / "out"
  jobs.run_register(_tsv(tmp_path, scans, ("p0", "p1")), out, progress=False, **OPTS)
  res = jobs.run_register(_tsv(tmp_path, scans, ("p2", "p1")), out, progress=False, **OPTS)
  assert [r["name"] for r in res.rows] == ["p2", "p1"] and res.ran == 1
  assert [r["name"] for r in tsv_rows(out / "results.tsv")] == ["p2", "p1", "p0"]
  on_disk = sorted(p.stem for p in (out / jobs.STATE / "records").glob("*.json"))
  assert sorted(r["name"] for r in tsv_rows(out / "results.tsv")) == on_disk


def test_a_failure_of_the_machine_is_redone_by_the_same_command(tmp_path, scans, monkeypatch):
  out = tmp_path / "out"
  tsv = _tsv(tmp_path, scans, ("p0",))

  def full_disk(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "cache" / "k.nbi"))
  with monkeypatch.context() as m:
    m.setattr(registration, "register", full_disk)
    res = jobs.run_register(tsv, out, progress=False, **OPTS)
  assert res.rows[0]["status"] == "transient" and res.exit_code == 3
  again = jobs.run_register(tsv, out, progress=False, **OPTS)  # no --retry-errors
  assert (again.ran, again.rows[0]["status"], again.exit_code) == (1, "done", 0)


def test_an_items_own_error_stays_until_retried(tmp_path, scans):
  bad = tmp_path / "bad.npy"
  bad.write_bytes(b"not an array")
  tsv = write_pairs(tmp_path / "bad.tsv", [("b", str(bad), str(scans[3]))])
  out = tmp_path / "out"
  assert jobs.run_register(tsv, out, progress=False, **OPTS).rows[0]["status"] == "error"
  assert jobs.run_register(tsv, out, progress=False, **OPTS).ran == 0


@pytest.mark.parametrize("error, inputs, transient", [
    (OSError(errno.ENOSPC, "full", "/somewhere/cache.nbc"), (), True),
    (OSError(errno.EIO, "io", "/in/a.ply"), ("/in/a.ply",), True),
    (PermissionError(errno.EACCES, "denied", "/in/a.ply"), ("/in/a.ply",), False),
    (PermissionError(errno.EACCES, "denied", "/cache/x.nbi"), ("/in/a.ply",), True),
    (FileNotFoundError(errno.ENOENT, "missing", "/in/a.ply"), ("/in/a.ply",), False),
    (ValueError("/in/a.ply: expected 3 columns"), ("/in/a.ply",), False),
    (MemoryError(), (), True)])
def test_transient_or_item_error(error, inputs, transient):
  assert items.is_transient(error, inputs) is transient


def test_a_record_of_another_version_is_redone_unless_kept(tmp_path, scans):
  out = tmp_path / "out"
  tsv = _tsv(tmp_path, scans, ("p0",))
  jobs.run_register(tsv, out, progress=False, **OPTS)
  path = out / jobs.STATE / "records" / "p0.json"
  rec = json.loads(path.read_text())
  path.write_text(json.dumps({**rec, "version": "0.0.1"}))
  kept = jobs.run_register(tsv, out, progress=False, keep_versions=True, **OPTS)
  assert kept.ran == 0 and tsv_rows(out / "results.tsv")[0]["version"] == "0.0.1"
  redone = jobs.run_register(tsv, out, progress=False, **OPTS)
  assert redone.ran == 1
  assert tsv_rows(out / "results.tsv")[0]["version"] == records.version()


def test_a_control_character_in_a_scan_path_keeps_each_row_one_line(tmp_path, scans):
  odd = tmp_path / "a\rb.npy"
  odd.write_bytes(scans[0].read_bytes())
  out = tmp_path / "out"
  res = jobs.run_frames([odd, scans[1]], out, progress=False, keypoints=50)
  assert res.exit_code == 0
  lines = (out / "results.tsv").read_bytes().split(b"\n")
  assert len(lines) == 4 and lines[-1] == b""  # header, two rows
  assert b"a\\rb.npy" in lines[1] + lines[2] and b"\r" not in b"".join(lines)


def test_a_symlink_loop_as_out_is_refused_naming_it(tmp_path, scans):
  loop = tmp_path / "loop"
  os.symlink(loop, loop)
  with pytest.raises(ValueError, match="out: .*loop.*symlink loop"):
    jobs.run_frames([scans[0]], loop, progress=False)


def test_lrf_batch_frames_runs_in_a_fresh_process(tmp_path, scans):
  """The console script, in a process that imported nothing before it."""
  exe = Path(sys.executable).with_name("lrf-batch")
  cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "lrf_jax.cli.batch"]
  out = tmp_path / "out"
  run = subprocess.run([*cmd, "frames", str(scans[0]), "--out", str(out), "--keypoints", "50",
                        "--no-progress"], capture_output=True, text=True, timeout=600)
  assert run.returncode == 0, run.stderr
  assert np.load(out / f"{scans[0].stem}.npz")["frames"].shape == (50, 3, 3)


# ------------------------------------------------------------------------------------ PAIRS.tsv


def _tsv_text(tmp_path: Path, text: str | bytes, name: str = "pairs.tsv") -> Path:
  path = tmp_path / name
  if isinstance(text, bytes):
    path.write_bytes(text)
  else:
    path.write_text(text, encoding="utf-8", newline="")
  return path


def _names(pairs):
  return [(n, Path(s).name, Path(t).name) for n, s, t in pairs]


def test_pairs_tsv_with_a_byte_order_mark_keeps_its_name_column(tmp_path):
  """Before: the header's first column read as '\\ufeffname', so the names were silently
  replaced by row numbers (or, with source first, the file was refused)."""
  f = _tsv_text(tmp_path, "\ufeffname\tsource\ttarget\np\ta.ply\tb.ply\n")
  assert _names(jobs.read_pairs(f)) == [("p", "a.ply", "b.ply")]
  g = _tsv_text(tmp_path, "\ufeffsource\ttarget\r\na.ply\tb.ply\r\n", "g.tsv")
  assert _names(jobs.read_pairs(g)) == [("0001", "a.ply", "b.ply")]


def test_pairs_tsv_saved_as_spreadsheet_unicode_text(tmp_path):
  f = _tsv_text(tmp_path, "name\tsource\ttarget\r\np\ta.ply\tb.ply\r\n".encode("utf-16"))
  assert _names(jobs.read_pairs(f)) == [("p", "a.ply", "b.ply")]


def test_pairs_tsv_errors_name_the_real_line_after_blank_lines(tmp_path):
  f = _tsv_text(tmp_path, "name\tsource\ttarget\n\n\n\np\ta.ply\t\n")
  with pytest.raises(ValueError, match=r"line 5: column target"):
    jobs.read_pairs(f)


def test_pairs_tsv_stray_quote_does_not_swallow_the_next_lines(tmp_path):
  """Before: csv's quoting joined everything after a field starting with '"' into one field."""
  f = _tsv_text(tmp_path, 'name\tsource\ttarget\np\t"a.ply\tb.ply\nq\t"c d.ply"\td.ply\n')
  assert _names(jobs.read_pairs(f)) == [("p", '"a.ply', "b.ply"), ("q", "c d.ply", "d.ply")]


@pytest.mark.parametrize("text, message", [
    ("source\tsource\ttarget\na\tb\tc\n", r"line 1: column 'source' appears twice"),
    ("source\ttarget\na\tb\tc\n", r"line 2: 3 tab-separated fields, but the header names 2"),
    (b"source\ttarget\n\xe9.ply\tb.ply\n", r"line 2: expected UTF-8 text, found the byte 0xe9"),
    ("source\ttarget\na\0.ply\tb.ply\n", r"line 2: expected text, found a NUL byte"),
    ("name\tsource\ttarget\na\x1bb\ta\tb\n", r"line 2: column name: .*control characters"),
    ("name\tsource\ttarget\nA\ta\tb\na\tc\td\n", r"line 3: column name: 'a' is also the name "
                                                 r"of line 2 \(ignoring case\)"),
])
def test_pairs_tsv_bad_files_are_one_message_naming_file_and_line(tmp_path, text, message):
  """Before: a repeated column or extra fields were silently ignored, a non-UTF-8 byte or a NUL
  gave a message without the file, control characters and names equal but for case passed."""
  f = _tsv_text(tmp_path, text)
  with pytest.raises(ValueError, match=message) as info:
    jobs.read_pairs(f)
  assert str(f) in str(info.value)


def test_pairs_tsv_with_a_long_field_is_read(tmp_path):
  """Before: `_csv.Error: field larger than field limit` (not a ValueError: a traceback)."""
  f = _tsv_text(tmp_path, "source\ttarget\n" + "a" * 200_000 + "\tb\n")
  assert len(Path(jobs.read_pairs(f)[0][1]).name) == 200_000


def test_pairs_tsv_that_is_a_fifo_is_refused_as_such(tmp_path):
  fifo = tmp_path / "pairs.tsv"
  os.mkfifo(fifo)
  with pytest.raises(FileNotFoundError, match="not a regular file"):
    jobs.read_pairs(fifo)


# ------------------------------------ the job layer, with a stand-in for the item's computation


def _fake_frames(payload):
  data = Path(payload["scan"]).read_bytes()
  return dict(status="done", arrays={"n": np.array([len(data)])}, keypoints=1, valid=1,
              seconds=0.0)


@pytest.fixture()
def fake_frames(monkeypatch):
  """Frames jobs whose item reads the scan's bytes (replace `fn` for other behaviour)."""
  def use(fn=_fake_frames, write=None):
    kind = dataclasses.replace(jobs.FRAMES, fn=fn, write=write or jobs.FRAMES.write)
    monkeypatch.setattr(jobs, "FRAMES", kind)
  use()
  return use


def _scans(tmp_path: Path, n: int = 2) -> list[Path]:
  out = []
  for k in range(n):
    p = tmp_path / f"s{k}.npy"
    np.save(p, np.full((4, 3), float(k)))
    out.append(p)
  return out


@pytest.mark.timeout(120)
def test_a_fifo_among_the_scans_is_one_failed_item_not_a_hang(tmp_path, fake_frames):
  """Before: hashing the inputs opened the FIFO and waited for a writer forever."""
  fake_frames(items.frames_of_scan)  # the real item: its reader refuses the FIFO
  fifo = tmp_path / "live.ply"
  os.mkfifo(fifo)
  res = jobs.run_frames([fifo], tmp_path / "out", progress=False)
  assert res.exit_code == 3
  assert "not a regular file" in res.rows[0]["error"], res.rows


def test_names_equal_but_for_case_are_refused_before_any_work(tmp_path, fake_frames):
  """Before: the Python API's pairs [(a, ...), (A, ...)] ran both (one file on a
  case-insensitive file system), and [(x, ...), (x, ...)] wrote x.txt twice."""
  s0, s1 = _scans(tmp_path)
  for names in (("x", "x"), ("a", "A")):
    with pytest.raises(ValueError, match="would name the same output file"):
      jobs.run_register([(names[0], s0, s1), (names[1], s1, s0)], tmp_path / "out",
                        progress=False)
    assert not (tmp_path / "out").exists()


def test_out_under_a_file_is_one_error_line_and_exit_2(tmp_path, fake_frames, capsys):
  """Before: NotADirectoryError / a read-only file system raised out of lrf-batch (exit 1). A file
  in the way is a wrong path (exit 2); a read-only or full disk is exit 74."""
  (s0, _) = _scans(tmp_path)
  (tmp_path / "file").write_text("x")
  rc = batch_cli.main(["frames", str(s0), "--out", str(tmp_path / "file" / "sub"),
                       "--no-progress"])
  err = capsys.readouterr().err
  assert rc == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, err


def test_full_disk_mid_job_is_one_error_line_exit_2_no_partial_file(tmp_path, fake_frames,
                                                                     capsys):
  from lrf_jax.io import atomic

  def full(path, value):
    with atomic.atomic_write(path) as f:
      f.write(b"partial")
      raise OSError(28, "No space left on device")
  fake_frames(write=full)
  s0, s1 = _scans(tmp_path)
  out = tmp_path / "out"
  rc = batch_cli.main(["frames", str(s0), str(s1), "--out", str(out), "--no-progress"])
  err = capsys.readouterr().err
  assert rc == 74 and err.startswith("error: ") and "No space left" in err, err
  assert len(err.strip().splitlines()) == 1, err
  assert sorted(p.name for p in out.iterdir()) == [".lrf-batch", "results.tsv"]


def test_ctrl_c_inside_a_kernel_is_not_recorded_as_a_failed_item(tmp_path, monkeypatch,
                                                                 capsys):
  """numba turns a KeyboardInterrupt inside a kernel into a SystemError. Before: the item's
  `except Exception` recorded it as failed (kept as failed on every later run) and the job went
  on to the next item."""
  from lrf_jax.batch import scan_frames

  def interrupted(request):
    try:
      raise KeyboardInterrupt
    except KeyboardInterrupt as e:
      raise SystemError("<numba kernel> returned a result with an exception set") from e
  monkeypatch.setattr(scan_frames, "frames_of_scan", interrupted)
  s0, s1 = _scans(tmp_path)
  out = tmp_path / "out"
  rc = batch_cli.main(["frames", str(s0), str(s1), "--out", str(out), "--no-progress"])
  err = capsys.readouterr().err
  assert rc == 130 and err.startswith("interrupted: "), err
  assert not list((out / ".lrf-batch" / "records").iterdir())  # nothing recorded as failed


def test_a_scan_changed_while_the_job_read_it_is_redone_next_run(tmp_path, fake_frames):
  """Before: the result of a scan rewritten while its item ran (a copy still arriving) was
  recorded as done under the hash of the content before; had the file been changed back, the
  next run would have kept that result."""
  s0, s1 = _scans(tmp_path)
  original = s1.read_bytes()

  def changing(payload):
    value = _fake_frames(payload)
    if payload["scan"] == str(s1):
      s1.write_bytes(original + b"more")
    return value
  fake_frames(changing)
  out = tmp_path / "out"
  res = jobs.run_frames([s0, s1], out, progress=False)
  row = {r["name"]: r for r in res.rows}["s1"]
  assert row["status"] == "error" and "changed while the job read it" in row["error"], row
  assert not (out / "s1.npz").exists()
  s1.write_bytes(original)  # changed back: still redone, and done
  fake_frames()
  again = jobs.run_frames([s0, s1], out, progress=False)
  assert again.ran == 1 and again.exit_code == 0


def test_a_record_without_a_status_is_redone_not_a_keyerror(tmp_path, fake_frames):
  s0, _ = _scans(tmp_path)
  out = tmp_path / "out"
  jobs.run_frames([s0], out, progress=False)
  rec_path = out / ".lrf-batch" / "records" / "s0.json"
  rec = json.loads(rec_path.read_text())
  del rec["status"]
  rec_path.write_text(json.dumps(rec))
  again = jobs.run_frames([s0], out, progress=False)
  assert again.ran == 1 and again.exit_code == 0


@pytest.mark.parametrize("cache", ["[]", "null", '{"X": 5}', '{"X": [1, 2, 3, 4]}',
                                   '{"X": [true, 2, 3, "h"]}'])
def test_a_damaged_hash_cache_costs_a_rehash_not_the_job(tmp_path, fake_frames, cache):
  """Before: a hashes.json holding a list, null or a malformed entry raised AttributeError or
  TypeError out of every later run of the job."""
  s0, _ = _scans(tmp_path)
  out = tmp_path / "out"
  jobs.run_frames([s0], out, progress=False)
  (out / jobs.STATE / "hashes.json").write_text(cache.replace("X", str(s0)))
  again = jobs.run_frames([s0], out, progress=False)
  assert (again.ran, again.skipped, again.exit_code) == (0, 1, 0)


@pytest.mark.parametrize("viewpoint", [["nan", "0", "0"], ["0", "inf", "0"]])
def test_a_non_finite_viewpoint_is_refused_before_the_work(tmp_path, viewpoint, capsys):
  """Before: every scan of the job ran and failed on it (exit 3, one error row per scan)."""
  s0, s1 = _scans(tmp_path)
  out = tmp_path / "out"
  rc = batch_cli.main(["frames", str(s0), str(s1), "--out", str(out), "--no-progress",
                       "--viewpoint", *viewpoint])
  err = capsys.readouterr().err
  assert rc == 2 and err.startswith("error: viewpoint: expected three finite"), err
  assert not out.exists()


def test_files_of_someone_else_in_the_out_folder_are_not_overwritten(tmp_path, fake_frames,
                                                                     capsys):
  """Before: `--out` onto a folder holding a user's s0.npz (or results.tsv) replaced it
  silently. A previous job's folder (it has .lrf-batch/) is still resumed and updated."""
  s0, s1 = _scans(tmp_path)
  out = tmp_path / "mine"
  out.mkdir()
  (out / "s0.npz").write_bytes(b"my own file")
  rc = batch_cli.main(["frames", str(s0), str(s1), "--out", str(out), "--no-progress"])
  err = capsys.readouterr().err
  assert rc == 2 and "holds s0.npz" in err and "not an lrf-batch job's folder" in err, err
  assert (out / "s0.npz").read_bytes() == b"my own file"
  assert sorted(p.name for p in out.iterdir()) == ["s0.npz"]
  (tmp_path / "scans_here").mkdir()  # a folder with other files but no clash is fine
  (tmp_path / "scans_here" / "notes.txt").write_text("x")
  assert jobs.run_frames([s0], tmp_path / "scans_here", progress=False).exit_code == 0
  s0.write_bytes(s0.read_bytes())  # a job's own folder: resumed (and redone where changed)
  assert jobs.run_frames([s0, s1], tmp_path / "scans_here", progress=False).exit_code == 0


def test_a_symlink_loop_as_a_scan_is_an_error_row_naming_it(tmp_path, scans):
  loop = tmp_path / "loop.npy"
  os.symlink(loop, loop)
  tsv = write_pairs(tmp_path / "loop.tsv", [("l", str(loop), str(scans[3]))])
  res = jobs.run_register(tsv, tmp_path / "reg", progress=False, **OPTS)
  assert res.rows[0]["status"] == "error"
  assert str(loop) in res.rows[0]["error"] and "loop" in res.rows[0]["error"]
  frames = jobs.run_frames([loop], tmp_path / "frames", progress=False, keypoints=50)
  assert frames.rows[0]["status"] == "error" and "symbolic link loop" in frames.rows[0]["error"]


def test_a_lock_whose_pid_was_reused_is_taken_over(tmp_path, scans, sleeper, capsys):
  """The holder's pid is alive but started at another time than the lock says: a new process
  that reuses a dead job's pid (Linux: /proc's start time)."""
  if records._process_start(sleeper.pid) is None:
    pytest.skip("no /proc start times on this system")
  out = tmp_path / "out"
  _lock(out, pid=sleeper.pid).write_text(json.dumps(
      {"host": socket.gethostname(), "pid": sleeper.pid, "start": "1", "command": "old"}))
  assert jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False,
                           **OPTS).ran == 1
  assert "taking its lock over" in capsys.readouterr().err


@pytest.mark.parametrize("content", ["", "{not json", "[1, 2]"])
def test_a_damaged_lock_is_taken_over_with_a_note(tmp_path, scans, capsys, content):
  """Nobody holds a lock file that names no holder (POSIX: nobody holds its file lock); an empty
  one is taken silently, one with other content with a note."""
  out = tmp_path / "out"
  _lock(out, pid=1).write_text(content)
  assert jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False,
                           **OPTS).exit_code == 0
  assert ("not a readable lock" in capsys.readouterr().err) is bool(content)


def test_a_lock_held_by_a_live_process_is_refused_whatever_its_content(tmp_path, scans):
  """POSIX: the holder's file lock decides, also when the file names nobody (a job that has
  not written its name yet)."""
  fcntl = pytest.importorskip("fcntl")
  out = tmp_path / "out"
  path = _lock(out, pid=1)
  path.write_text("")
  code = (f"import fcntl, os, time; fd = os.open({str(path)!r}, os.O_RDWR); "
          "fcntl.lockf(fd, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)")
  holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
  try:
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(records.FolderInUse, match="in use by another job"):
      jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False, **OPTS)
  finally:
    holder.kill()
    holder.wait()
  assert fcntl is not None


def test_something_else_at_the_locks_path_is_refused(tmp_path, scans):
  out = tmp_path / "out"
  (out / jobs.STATE / "lock").mkdir(parents=True)
  with pytest.raises(records.FolderInUse, match="lock file"):
    jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False, **OPTS)


def test_a_lock_of_a_zombie_is_taken_over(tmp_path, scans, capsys):
  """A killed job its parent has not collected yet (a zombie) holds nothing."""
  proc = subprocess.Popen([sys.executable, "-c", "pass"])
  t0 = time.monotonic()
  while records._proc_stat(proc.pid) is not None and records._proc_stat(proc.pid)[0] != "Z":
    assert time.monotonic() - t0 < 30
    time.sleep(0.05)
  if records._proc_stat(proc.pid) is None:
    proc.wait()
    pytest.skip("no /proc on this system")
  try:
    out = tmp_path / "out"
    _lock(out, pid=proc.pid, start=records._process_start(proc.pid))
    assert jobs.run_register(_tsv(tmp_path, scans, ("p0",)), out, progress=False,
                             **OPTS).ran == 1
    assert "taking its lock over" in capsys.readouterr().err
  finally:
    proc.wait()
