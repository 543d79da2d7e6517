"""Hostile probes, third pass, on the data-set layer (`lrf-batch`, `lrf_jax.batch`), `lrf-compile`,
the console entry points, the readers' refusals, the training workdir's lock and the checkpoint
checksum. Each test is the probe that found a problem (it fails on the code before its fix).

The data-set layer's probes replace the item's computation by a stand-in (`_fake_frames`): the
job layer is under test, not the frames."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lrf_jax.batch import items as items_mod
from lrf_jax.batch import jobs
from lrf_jax.cli import batch as batch_cli

REPO = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
  return {**os.environ, "PYTHONPATH": str(REPO)}


# --- PAIRS.tsv ------------------------------------------------------------------------------

def _tsv(tmp_path: Path, text: str | bytes, name: str = "pairs.tsv") -> Path:
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
  f = _tsv(tmp_path, "\ufeffname\tsource\ttarget\np\ta.ply\tb.ply\n")
  assert _names(jobs.read_pairs(f)) == [("p", "a.ply", "b.ply")]
  g = _tsv(tmp_path, "\ufeffsource\ttarget\r\na.ply\tb.ply\r\n", "g.tsv")
  assert _names(jobs.read_pairs(g)) == [("0001", "a.ply", "b.ply")]


def test_pairs_tsv_saved_as_spreadsheet_unicode_text(tmp_path):
  f = _tsv(tmp_path, "name\tsource\ttarget\r\np\ta.ply\tb.ply\r\n".encode("utf-16"))
  assert _names(jobs.read_pairs(f)) == [("p", "a.ply", "b.ply")]


def test_pairs_tsv_errors_name_the_real_line_after_blank_lines(tmp_path):
  f = _tsv(tmp_path, "name\tsource\ttarget\n\n\n\np\ta.ply\t\n")
  with pytest.raises(ValueError, match=r"line 5: column target"):
    jobs.read_pairs(f)


def test_pairs_tsv_stray_quote_does_not_swallow_the_next_lines(tmp_path):
  """Before: csv's quoting joined everything after a field starting with '"' into one field."""
  f = _tsv(tmp_path, 'name\tsource\ttarget\np\t"a.ply\tb.ply\nq\t"c d.ply"\td.ply\n')
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
  f = _tsv(tmp_path, text)
  with pytest.raises(ValueError, match=message) as info:
    jobs.read_pairs(f)
  assert str(f) in str(info.value)


def test_pairs_tsv_with_a_long_field_is_read(tmp_path):
  """Before: `_csv.Error: field larger than field limit` (not a ValueError: a traceback)."""
  f = _tsv(tmp_path, "source\ttarget\n" + "a" * 200_000 + "\tb\n")
  assert len(Path(jobs.read_pairs(f)[0][1]).name) == 200_000


def test_pairs_tsv_that_is_a_fifo_is_refused_as_such(tmp_path):
  fifo = tmp_path / "pairs.tsv"
  os.mkfifo(fifo)
  with pytest.raises(FileNotFoundError, match="not a regular file"):
    jobs.read_pairs(fifo)


# --- the job layer, with a stand-in for the item's computation --------------------------------

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
  fake_frames(items_mod.frames_of_scan)  # the real item: its reader refuses the FIFO
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
  """Before: NotADirectoryError / a read-only file system raised out of lrf-batch (exit 1)."""
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
  assert rc == 2 and err.startswith("error: ") and "No space left" in err, err
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


def test_ctrl_c_while_a_console_script_imports_is_one_line_and_130(tmp_path):
  """Before: a Ctrl-C while `lrf-batch` imported its modules (a second or more) was a traceback
  and the signal's own exit status."""
  code = ("from lrf_jax.cli import console\n"
          "def main():\n  raise KeyboardInterrupt\n"
          "console.run(main)\n")
  proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                        env=_env(), timeout=120)
  assert proc.returncode == 130 and proc.stderr.strip() == "interrupted", proc.stderr


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


# --- readers -----------------------------------------------------------------------------------

def test_reading_a_fifo_says_it_is_not_a_regular_file(tmp_path):
  """Before: "no such file" for a FIFO that exists."""
  from lrf_jax.io import read_cloud
  fifo = tmp_path / "scan.bin"
  os.mkfifo(fifo)
  with pytest.raises(FileNotFoundError, match="not a regular file"):
    read_cloud(fifo)


# --- lrf-compile -------------------------------------------------------------------------------

def test_lrf_compile_exit_code_is_3_when_a_group_failed(monkeypatch, capsys):
  """Before: 1 (the convention: 3 when some items failed, the others done)."""
  import concurrent.futures
  from lrf_jax.cli import compile as compile_cli

  class Threads(concurrent.futures.ThreadPoolExecutor):  # the groups in this process
    def __init__(self, max_workers, mp_context=None):
      super().__init__(max_workers)

  def fails():
    raise ValueError("boom")
  monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", Threads)
  monkeypatch.setattr(compile_cli, "groups", lambda: {"ok": lambda: None, "bad": fails})
  assert compile_cli.main(["--jobs", "1"]) == 3
  assert "error: bad: ValueError: boom" in capsys.readouterr().err


def test_lrf_compile_stop_ends_running_workers_at_once():
  """Before: Ctrl-C sent to lrf-compile alone (kill -INT, a supervisor) waited for the groups in
  flight to finish (245 s seen) before exiting."""
  import multiprocessing as mp
  from concurrent.futures import ProcessPoolExecutor
  from lrf_jax.cli import compile as compile_cli
  pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"))
  fut = pool.submit(time.sleep, 300)
  deadline = time.monotonic() + 60
  while not fut.running() and time.monotonic() < deadline:
    time.sleep(0.1)
  t0 = time.monotonic()
  compile_cli._stop(pool)
  assert time.monotonic() - t0 < 30


# --- the training workdir's lock ---------------------------------------------------------------

def test_a_symlinked_train_lock_never_truncates_its_target(tmp_path):
  """Before: `train.lock -> ~/precious` was opened through the link, truncated and overwritten
  with the pid."""
  from lrf_jax.learning import train_lib
  victim = tmp_path / "precious.txt"
  victim.write_text("precious data\n")
  work = tmp_path / "work"
  work.mkdir()
  (work / train_lib.LOCK_FILE).symlink_to(victim)
  with pytest.raises(ValueError, match="not a regular file"):
    with train_lib.workdir_lock(work):
      pass
  assert victim.read_text() == "precious data\n"
  assert (work / train_lib.LOCK_FILE).is_symlink()  # left as it was


def test_a_fifo_train_lock_is_refused_and_left_alone(tmp_path):
  from lrf_jax.learning import train_lib
  os.mkfifo(tmp_path / train_lib.LOCK_FILE)
  with pytest.raises(ValueError, match="not a regular file"):
    with train_lib.workdir_lock(tmp_path):
      pass
  assert (tmp_path / train_lib.LOCK_FILE).exists()


# --- the checkpoint checksum -------------------------------------------------------------------

@pytest.fixture(scope="module")
def checkpointed(tmp_path_factory):
  from lrf_jax.learning import config as config_lib
  from lrf_jax.learning import train_lib
  cfg = config_lib.replace(config_lib.load_config("smoke"), epochs=2)
  work = tmp_path_factory.mktemp("ck")
  train_lib.train_and_evaluate(cfg, work, progress=False, stop_after_steps=12)
  assert (work / "checkpoints" / "12" / "checksum").is_dir()
  return work


def _damaged(checkpointed: Path, tmp_path: Path, damage) -> Path:
  work = tmp_path / "work"
  shutil.copytree(checkpointed, work)
  damage(work / "checkpoints" / "12")
  return work


def _replace_checksum_by_a_file(step: Path) -> None:
  shutil.rmtree(step / "checksum")
  (step / "checksum").write_text("x")


def _empty_checksum_files(step: Path) -> None:
  for f in (step / "checksum").iterdir():
    if f.is_file():
      f.write_bytes(b"")


@pytest.mark.parametrize("damage, message", [
    (lambda step: shutil.rmtree(step / "checksum"), "checksum saved with it is missing"),
    (_replace_checksum_by_a_file, "checksum saved with it is missing"),
    (_empty_checksum_files, "checksum saved with it is unreadable"),
])
def test_a_checkpoint_whose_checksum_is_gone_is_not_trusted(checkpointed, tmp_path, damage,
                                                           message):
  """Before: a checkpoint without its checksum folder (a partial copy) was restored unverified,
  and an unreadable checksum raised a bare JSONDecodeError."""
  from lrf_jax.learning import checkpoints
  work = _damaged(checkpointed, tmp_path, damage)
  with pytest.raises(checkpoints.ChecksumError, match=rf"checkpoints/12: .*{message}"):
    checkpoints.restore_params(work, "latest")


def test_resume_sets_aside_a_checkpoint_whose_checksum_is_gone(checkpointed, tmp_path, smoke):
  from lrf_jax.learning import checkpoints, train_step
  work = _damaged(checkpointed, tmp_path, lambda step: shutil.rmtree(step / "checksum"))
  cfg = _smoke2(smoke)
  with pytest.warns(UserWarning, match=r"checkpoints/12 \(ChecksumError\).*resumed from "
                                       r"checkpoints/8"):
    mngr, state = checkpoints.resume(work, train_step.create_state(cfg), cfg)
  mngr.close()
  assert int(state.step) == 8 and (work / "checkpoints" / "12.unreadable").is_dir()


@pytest.fixture(scope="module")
def smoke():
  from lrf_jax.learning import config as config_lib
  return config_lib.load_config("smoke")


def _smoke2(smoke):
  from lrf_jax.learning import config as config_lib
  return config_lib.replace(smoke, epochs=2)


# --- numba's CPU target and the kernel cache ---------------------------------------------------

_MATCH = """
import numpy as np
from lrf_jax.descriptors import select_correspondences
rng = np.random.default_rng(0)
q = np.where(rng.random((40, 30)) < 0.5, 100.0, rng.random((40, 30))).astype(np.float32)
select_correspondences(q, q[::-1], n=10)
"""


def _compiles(cache: Path, cpu: str | None) -> bool:
  env = {k: v for k, v in _env().items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES")}
  env["NUMBA_CACHE_DIR"] = str(cache)
  if cpu is not None:
    env["NUMBA_CPU_NAME"] = cpu
  out = subprocess.run([sys.executable, "-c", _MATCH], env=env, capture_output=True, text=True,
                       timeout=600)
  assert out.returncode == 0, out.stderr
  return "compiling kernels" in out.stderr


def test_kernels_compiled_for_one_cpu_target_are_never_loaded_for_another(tmp_path):
  """A user's NUMBA_CPU_NAME (here "generic", as for a cache shipped to other machines) is
  respected: lrf_jax's locator keys a kernel by its sources, and numba's index keys each entry
  by the target (triple, CPU name, features), so one cache holds both builds side by side and
  each run loads only its own."""
  cache = tmp_path / "cache"
  assert _compiles(cache, "generic")
  assert _compiles(cache, None)  # native: not the generic build
  assert not _compiles(cache, "generic")
  assert not _compiles(cache, None)


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


def test_a_nuscenes_pcd_bin_is_refused_not_misread_as_kitti(tmp_path):
  """Before: 8 points of 5 float32 (160 bytes, a multiple of 16) read as 10 KITTI points of
  shuffled columns, silently."""
  from lrf_jax.io import read_cloud
  sweep = np.arange(40, dtype="<f4").reshape(8, 5)
  sweep.tofile(tmp_path / "n008__LIDAR_TOP__1.pcd.bin")
  with pytest.raises(ValueError, match=r"nuScenes-style \.pcd\.bin"):
    read_cloud(tmp_path / "n008__LIDAR_TOP__1.pcd.bin")
  sweep[:, :4].tofile(tmp_path / "kitti.bin")  # a KITTI layout still reads
  assert read_cloud(tmp_path / "kitti.bin").points.shape == (8, 3)


def test_lrf_compile_into_a_cache_it_cannot_write_is_one_error_before_the_work(tmp_path,
                                                                                monkeypatch,
                                                                                capsys):
  """Before: with a read-only NUMBA_CACHE_DIR, lrf-compile compiled for 40 s, said "compiled 1
  of 1 groups ... into <that folder>" and exited 0, keeping nothing."""
  from lrf_jax.cli import compile as compile_cli
  blocker = tmp_path / "file"
  blocker.write_text("x")  # a folder under a file cannot be created, even by root
  monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "numba"))
  monkeypatch.setattr(compile_cli, "groups",
                      lambda: {"g": lambda: pytest.fail("the work started")})
  monkeypatch.setattr(compile_cli, "_run_group", lambda name: pytest.fail("the work started"))
  rc = compile_cli.main(["--jobs", "1"])
  err = capsys.readouterr().err
  assert rc == 2 and err.startswith("error: the cache of numba's kernels"), err
  assert str(blocker / "numba") in err and "not writable" in err


def test_a_step_set_aside_twice_keeps_both_copies(checkpointed, tmp_path, smoke):
  """Before: a step replayed over a set-aside checkpoint and corrupted again could not be set
  aside (`OSError: Directory not empty: checkpoints/12 -> checkpoints/12.unreadable`): the run
  could not resume at all."""
  from lrf_jax.learning import checkpoints, train_step

  def again(step: Path) -> None:
    shutil.copytree(step, step.parent / "12.unreadable")  # the first time it was set aside
    shutil.rmtree(step / "checksum")
  work = _damaged(checkpointed, tmp_path, again)
  cfg = _smoke2(smoke)
  with pytest.warns(UserWarning, match=r"kept as 12\.unreadable-2; resumed from checkpoints/8"):
    mngr, state = checkpoints.resume(work, train_step.create_state(cfg), cfg)
  mngr.close()
  assert int(state.step) == 8
  assert {"12.unreadable", "12.unreadable-2"} <= {p.name for p in (work / "checkpoints").iterdir()}


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


_LOST_CTRL_C = """
import gc, sys, time
from lrf_jax.cli.interrupt import interruptible

class Finalized:
  def __del__(self):
    raise KeyboardInterrupt  # Ctrl-C arriving while Python runs a finalizer or a gc callback

@interruptible("stopped")
def main():
  Finalized()  # dropped at once: its __del__ runs here, and Python must ignore what it raises
  t0 = time.monotonic()
  while time.monotonic() - t0 < 60:  # the work goes on
    time.sleep(0.01)
  return 0

sys.exit(main())
"""


def test_a_ctrl_c_python_had_to_drop_in_a_finalizer_still_stops_the_program():
  """Seen in the suite (train.py under NUMBA_CPU_NAME=generic): a SIGINT that landed in JAX's
  `_xla_gc_callback` was printed as "Exception ignored in ..." and lost; training went on (the
  test's 300 s timeout). Before: this program ran its 60 s and exited 0."""
  t0 = time.monotonic()
  proc = subprocess.run([sys.executable, "-c", _LOST_CTRL_C], capture_output=True, text=True,
                        env=_env(), timeout=120)
  assert proc.returncode == 130 and proc.stderr.strip() == "interrupted: stopped", proc.stderr
  assert time.monotonic() - t0 < 50


def test_a_hidden_files_scan_name_has_no_leading_dot():
  """Before: `.hidden.npy` was named `.hidden`: lrf-batch refused the whole job (a name may not
  start with a dot) and lrf-register --out-dir wrote a hidden `.hidden.txt`."""
  from lrf_jax.registration.multiway import scan_names
  assert scan_names(["/d/.hidden.npy", "/d/a.npy", "/d/...npy"]) == ["hidden", "a", "scan2"]


def test_lrf_frames_refuses_a_non_finite_viewpoint_before_reading_the_cloud():
  from lrf_jax.batch.scan_frames import FramesRequest
  problem = FramesRequest(cloud="/nowhere.ply", viewpoint=(float("nan"), 0.0, 0.0)).problem()
  assert problem is not None and problem.startswith("--viewpoint: expected three finite")
  assert FramesRequest(cloud="x", pair_viewpoint=(0.0, float("inf"), 0.0)).problem().startswith(
      "--pair-viewpoint:")


def test_a_voxel_size_that_leaves_no_cloud_is_named():
  """Before: voxel_size=1e300 thinned each cloud to one point and register said "only 0
  descriptor matches ... too sparse for r = 15.0 mr"; 1e-20 was voxel_downsample's error."""
  from lrf_jax import datasets
  from lrf_jax.registration import register
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.05, partial=True)
  with pytest.raises(ValueError, match=r"^voxel_size: voxels of 1e\+300 leave 1 points"):
    register(pair.model_points, pair.scene_points, voxel_size=1e300)
  with pytest.raises(ValueError, match=r"^voxel_size: size 1e-20 is too small"):
    register(pair.model_points, pair.scene_points, voxel_size=1e-20)


def test_a_ctrl_c_a_library_swallows_is_sent_again(monkeypatch, capsys):
  """Before: a KeyboardInterrupt caught by library code (a checkpoint manager's `except
  BaseException`, a C++ callback) was lost and the program went on (train.py trained 400 epochs
  after Ctrl-C in a fresh CI environment). The SIGINT handler sends it again unless the program
  stopped by then."""
  import signal
  from lrf_jax.cli import interrupt
  monkeypatch.setattr(interrupt, "REDELIVER_AFTER_S", 0.2)
  swallowed = []

  @interrupt.interruptible("test")
  def main() -> int:
    try:
      os.kill(os.getpid(), signal.SIGINT)
      time.sleep(2)
    except KeyboardInterrupt:
      swallowed.append(True)  # what the library did
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
      time.sleep(0.01)
    return 0

  before = signal.getsignal(signal.SIGINT)
  assert main() == interrupt.INTERRUPTED and swallowed == [True]
  assert capsys.readouterr().err.startswith("interrupted: test")
  assert signal.getsignal(signal.SIGINT) is before  # the program's handler is removed again
