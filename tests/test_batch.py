"""Data-set jobs on the local engine: lrf-batch register / frames, records, resume, bad items.

The Ray engine's tests are in test_batch_ray.py (one Ray instance for that module)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import batch, datasets
from lrf_jax.batch import jobs
from lrf_jax.cli import batch as batch_cli

# Small registrations: the job layer is under test, not the pipeline's accuracy.
OPTS = dict(n_keypoints=600, n_correspondences=200)
CLI_OPTS = ["--keypoints", "600", "--correspondences", "200"]


def make_scans(folder: Path, n: int = 3) -> list[Path]:
  """`n` demo scenes (pair index k) and their models, as .npy files; returns the scene paths
  then the model paths."""
  folder.mkdir(parents=True, exist_ok=True)
  scenes, models = [], []
  for k in range(n):
    pair = datasets.make_demo_pair(k, seed=0, noise_mr=0.05, partial=True)
    scenes.append(folder / f"scene{k}.npy")
    models.append(folder / f"model{k}.npy")
    np.save(scenes[-1], pair.scene_points)
    np.save(models[-1], pair.model_points)
  return scenes + models


def write_pairs(path: Path, rows: list[tuple[str, ...]], header=("name", "source", "target")):
  path.write_text("\t".join(header) + "\n" + "".join("\t".join(r) + "\n" for r in rows))
  return path


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
  return make_scans(tmp_path_factory.mktemp("scans"), 2)


def pairs_tsv(folder: Path, scans: list[Path], corrupt: Path | None = None) -> Path:
  s0, s1, m0, m1 = scans
  rows = [("p0", s0.name, m0.name), ("p1", str(s1), str(m1))]
  if corrupt is not None:
    rows.append(("bad", str(corrupt), str(m0)))
  return write_pairs(folder / "pairs.tsv", rows)


def tsv_rows(path: Path) -> list[dict[str, str]]:
  lines = path.read_text().splitlines()
  head = lines[0].split("\t")
  return [dict(zip(head, line.split("\t"))) for line in lines[1:]]


def test_read_pairs_paths_names_and_errors(tmp_path):
  f = write_pairs(tmp_path / "p.tsv", [("a.ply", "b.ply"), ("sub/c.ply", "/abs/d.ply")],
                  header=("source", "target"))
  assert jobs.read_pairs(f) == [("0001", str(tmp_path / "a.ply"), str(tmp_path / "b.ply")),
                                ("0002", str(tmp_path / "sub/c.ply"), "/abs/d.ply")]
  with pytest.raises(ValueError, match="line 1.*source and target"):
    jobs.read_pairs(write_pairs(tmp_path / "q.tsv", [("a", "b")], header=("src", "target")))
  with pytest.raises(ValueError, match="line 3: column name: 'x' is also the name of line 2"):
    jobs.read_pairs(write_pairs(tmp_path / "r.tsv", [("x", "a", "b"), ("x", "c", "d")]))
  for bad in ("../escape", ".hidden", "a/b", "x" * 300):
    with pytest.raises(ValueError, match="column name"):
      jobs.read_pairs(write_pairs(tmp_path / "s.tsv", [(bad, "a", "b")]))
  with pytest.raises(ValueError, match="line 2: column target: expected a path"):
    jobs.read_pairs(write_pairs(tmp_path / "t.tsv", [("n", "a", "")]))
  with pytest.raises(FileNotFoundError, match="no such file"):
    jobs.read_pairs(tmp_path / "none.tsv")


def test_frames_jobs_name_scans_as_multiway_does(tmp_path):
  folders = [tmp_path / d for d in "def"]
  scans = []
  for folder, name in zip(folders, ("a.npy", "a_2.npy", "a.npy")):
    scans += make_scans(folder, 1)[:1]
    scans[-1] = scans[-1].rename(folder / name)
  res = batch.run_frames(scans, tmp_path / "out", progress=False, keypoints="20")
  assert [r["name"] for r in res.rows] == ["a", "a_2", "a_3"]
  assert all((tmp_path / "out" / f"{n}.npz").is_file() for n in ("a", "a_2", "a_3"))


def test_register_job_equals_register_bit_for_bit_and_isolates_a_corrupt_scan(tmp_path, scans):
  from lrf_jax.registration import register
  corrupt = tmp_path / "corrupt.npy"
  corrupt.write_bytes(b"\x93NUMPY garbage")
  out = tmp_path / "out"
  res = batch.run_register(pairs_tsv(scans[0].parent, scans, corrupt), out, progress=False,
                           **OPTS)
  assert res.exit_code == 3 and res.ran == 3 and res.skipped == 0 and res.failed == 1
  rows = tsv_rows(out / "results.tsv")
  assert [r["name"] for r in rows] == ["p0", "p1", "bad"]
  assert list(rows[0]) == list(jobs.REGISTER_COLUMNS)
  assert rows[2]["status"] == "error" and str(corrupt) in rows[2]["error"]
  assert not (out / "bad.txt").exists()
  for row, (s, m) in zip(rows[:2], [(scans[0], scans[2]), (scans[1], scans[3])]):
    assert row["status"] == "done" and row["node"] == "local" and row["attempt"] == "1"
    reg = register(str(s), str(m), **OPTS)
    rec = json.loads((out / jobs.STATE / "records" / f"{row['name']}.json").read_text())
    assert np.array_equal(np.array(rec["transform"]), reg.transform)  # bit for bit
    assert row["success"] == str(reg.success) and row["reason"] == reg.reason
    assert np.allclose(np.loadtxt(out / f"{row['name']}.txt"), reg.transform, atol=1e-8)


def _mtimes(folder: Path) -> dict[str, int]:
  return {p.name: p.stat().st_mtime_ns for p in folder.iterdir() if p.is_file()}


def test_rerun_skips_what_is_done_and_redoes_exactly_what_changed(tmp_path):
  scans = make_scans(tmp_path / "scans", 2)
  tsv = pairs_tsv(tmp_path / "scans", scans)
  out = tmp_path / "out"
  first = batch.run_register(tsv, out, progress=False, **OPTS)
  assert first.exit_code == 0 and first.ran == 2
  before = _mtimes(out)
  os.utime(scans[0])  # touched, same bytes: nothing to redo
  again = batch.run_register(tsv, out, progress=False, **OPTS)
  assert (again.ran, again.skipped) == (0, 2)
  assert _mtimes(out) == before  # rewrote nothing, results.tsv included
  pts = np.load(scans[1])
  pts[0, 0] += 1e-3  # one scan changed: only the pair reading it
  np.save(scans[1], pts)
  changed = batch.run_register(tsv, out, progress=False, **OPTS)
  assert (changed.ran, changed.skipped) == (1, 1)
  assert _mtimes(out)["p0.txt"] == before["p0.txt"]
  other = batch.run_register(tsv, out, progress=False, seed=1, **OPTS)  # a changed option
  assert (other.ran, other.skipped) == (2, 0)
  (out / "p0.txt").unlink()  # a lost output is redone
  assert batch.run_register(tsv, out, progress=False, seed=1, **OPTS).ran == 1


def test_errors_are_kept_unless_retried(tmp_path, scans):
  tsv = write_pairs(tmp_path / "p.tsv", [("x", str(scans[0]), str(tmp_path / "late.npy"))])
  out = tmp_path / "out"
  assert batch.run_register(tsv, out, progress=False, **OPTS).failed == 1
  again = batch.run_register(tsv, out, progress=False, **OPTS)
  assert (again.ran, again.failed, again.exit_code) == (0, 1, 3)
  np.save(tmp_path / "late.npy", np.load(scans[2]))  # the missing input appears: new hashes
  fixed = batch.run_register(tsv, out, progress=False, **OPTS)
  assert (fixed.ran, fixed.failed, fixed.exit_code) == (1, 0, 0)
  (tmp_path / "late.npy").write_bytes(b"not a cloud")
  assert batch.run_register(tsv, out, progress=False, **OPTS).failed == 1
  retried = batch.run_register(tsv, out, progress=False, retry_errors=True, **OPTS)
  assert (retried.ran, retried.failed) == (1, 1)


def test_bad_jobs_are_refused_before_any_work(tmp_path, scans):
  tsv = pairs_tsv(scans[0].parent, scans)
  with pytest.raises(ValueError, match="params: not an option"):
    batch.run_register(tsv, tmp_path / "o", params={})
  with pytest.raises(ValueError, match="engine: expected one of"):
    batch.run_register(tsv, tmp_path / "o", engine="spark")
  with pytest.raises(ValueError, match="address.*engine='ray'"):
    batch.run_register(tsv, tmp_path / "o", address="127.0.0.1:1")
  (tmp_path / "file").write_text("x")
  with pytest.raises(ValueError, match="not a folder"):
    batch.run_register(tsv, tmp_path / "file")
  with pytest.raises(ValueError, match="method"):
    batch.run_frames([scans[0]], tmp_path / "f", method="bogus")
  assert not (tmp_path / "o").exists()


def test_an_output_may_not_overwrite_an_input(tmp_path):
  scans = make_scans(tmp_path, 1)
  (tmp_path / "p0.txt").write_text("an input")
  tsv = write_pairs(tmp_path / "p.tsv", [("p0", str(tmp_path / "p0.txt"), str(scans[1]))])
  with pytest.raises(ValueError, match="would overwrite the input"):
    batch.run_register(tsv, tmp_path)
  assert (tmp_path / "p0.txt").read_text() == "an input"


def test_cli_register_exit_codes_and_options(tmp_path, scans, capsys):
  tsv = pairs_tsv(scans[0].parent, scans)
  out = tmp_path / "out"
  rc = batch_cli.main(["register", str(tsv), "--out", str(out), "--no-progress", *CLI_OPTS])
  assert rc == 0
  assert "2 items: 2 done" in capsys.readouterr().err
  assert (out / "p0.txt").is_file() and (out / "p1.txt").is_file()
  rec = json.loads((out / jobs.STATE / "records" / "p0.json").read_text())
  assert rec["options"] == dict(n_keypoints=600, n_correspondences=200)  # no defaults added
  for bad in (["--png", "x.png"], ["--init", "t.txt"], ["--best-guess"], ["--keypoints", "0"],
              ["--bogus"]):
    with pytest.raises(SystemExit) as e:
      batch_cli.main(["register", str(tsv), "--out", str(out), *bad])
    assert e.value.code == 2
  assert batch_cli.main(["register", str(tmp_path / "none.tsv"), "--out", str(out)]) == 2
  assert "error: " in capsys.readouterr().err


def test_cli_frames_writes_what_lrf_frames_writes(tmp_path, scans):
  from lrf_jax.cli import frames as frames_cli
  out = tmp_path / "out"
  rc = batch_cli.main(["frames", str(scans[0]), str(scans[2]), "--out", str(out),
                       "--keypoints", "200", "--no-progress"])
  assert rc == 0
  assert frames_cli.main([str(scans[0]), "--out", str(tmp_path / "one.npz"),
                          "--keypoints", "200"]) == 0
  a, b = np.load(out / "scene0.npz"), np.load(tmp_path / "one.npz")
  assert sorted(a.files) == sorted(b.files)
  for key in a.files:
    assert np.array_equal(a[key], b[key]), key
  rows = tsv_rows(out / "results.tsv")
  assert [r["name"] for r in rows] == ["scene0", "model0"]
  assert rows[0]["keypoints"] == "200" and int(rows[0]["valid"]) > 0
  rerun = batch.run_frames([scans[0], scans[2]], out, progress=False, keypoints="200")
  assert rerun.ran == 0 and rerun.skipped == 2


def test_a_rerun_with_nothing_to_do_starts_no_engine(tmp_path, scans):
  tsv = pairs_tsv(scans[0].parent, scans)
  out = tmp_path / "out"
  assert batch.run_register(tsv, out, progress=False, **OPTS).exit_code == 0
  # Nothing listens there: joining it would fail. Nothing to do, so nothing is joined.
  again = batch.run_register(tsv, out, engine="ray", address="127.0.0.1:9", progress=False,
                             **OPTS)
  assert (again.ran, again.skipped, again.exit_code) == (0, 2, 0)


def _batch_process(tsv: Path, out: Path) -> subprocess.Popen:
  return subprocess.Popen([sys.executable, "-m", "lrf_jax.cli.batch", "register", str(tsv),
                           "--out", str(out), "--no-progress", *CLI_OPTS],
                          stderr=subprocess.PIPE, text=True)


def _records(out: Path) -> list[Path]:
  """The item records written (not an atomic write's `.NAME.XXXX.tmp.json` in flight: waiting
  for one of those and signalling raced with its rename)."""
  folder = out / jobs.STATE / "records"
  return [p for p in folder.glob("*.json") if not p.name.startswith(".")]


def _wait_for_record(out: Path, proc: subprocess.Popen, timeout: float = 300) -> None:
  t0 = time.monotonic()
  while not _records(out):
    assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
    assert time.monotonic() - t0 < timeout
    time.sleep(0.05)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGKILL, -9)])
def test_an_interrupted_or_killed_job_resumes_where_it_stopped(tmp_path, sig, code):
  scans = make_scans(tmp_path / "scans", 3)
  s, m = scans[:3], scans[3:]
  tsv = write_pairs(tmp_path / "p.tsv", [(f"p{k}", str(s[k]), str(m[k])) for k in range(3)]
                    + [(f"q{k}", str(m[k]), str(s[k])) for k in range(3)])
  out = tmp_path / "out"
  proc = _batch_process(tsv, out)
  _wait_for_record(out, proc)
  proc.send_signal(sig)
  assert proc.wait(timeout=120) == code
  if sig == signal.SIGINT:
    assert "interrupted" in proc.stderr.read()
  assert not list(out.glob(".*.tmp")) and not list(out.glob("*.tmp"))
  kept = len(_records(out))
  assert 1 <= kept < 6
  resumed = batch.run_register(tsv, out, progress=False, **OPTS)
  assert (resumed.ran, resumed.skipped, resumed.exit_code) == (6 - kept, kept, 0)
  assert len(tsv_rows(out / "results.tsv")) == 6


def test_lrf_compile_lists_and_runs_groups(capsys):
  from lrf_jax.cli import compile as compile_cli
  assert compile_cli.main(["--list"]) == 0
  listed = capsys.readouterr().out.split()
  assert {"register", "register:3point", "frames:lrf_net_plus", "descriptor:toldi",
          "multiway"} <= set(listed)
  assert compile_cli.main(["--only", "bogus"]) == 2
  assert compile_cli.main(["--jobs", "1", "--only", "frames:shot"]) == 0
  assert "compiled 1 of 1 groups with 1 worker(s)" in capsys.readouterr().err


def test_a_ray_address_where_nothing_answers_is_refused_at_once(monkeypatch):
  """Ray retries an address where nothing answers for minutes: the engine refuses it first
  (3 s at most), naming the address; "local" and "auto" need no check."""
  import time

  from lrf_jax.batch import engines
  monkeypatch.delenv("RAY_ADDRESS", raising=False)
  assert engines.address_problem("local") is None and engines.address_problem(None) is None
  assert "expected HOST:PORT" in engines.address_problem("nonsense")
  pytest.importorskip("ray")
  t = time.perf_counter()
  with pytest.raises(ValueError, match="address: no Ray cluster answers at 127.0.0.1:1"):
    engines.RayEngine("127.0.0.1:1").driver_node()  # joined on first use
  assert time.perf_counter() - t < 10
  monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
  assert engines.address_problem(None, "--address").startswith("$RAY_ADDRESS: ")


def test_lrf_frames_refuses_a_non_finite_viewpoint_before_reading_the_cloud():
  from lrf_jax.batch.scan_frames import FramesRequest
  problem = FramesRequest(cloud="/nowhere.ply", viewpoint=(float("nan"), 0.0, 0.0)).problem()
  assert problem is not None and problem.startswith("--viewpoint: expected three finite")
  assert FramesRequest(cloud="x", pair_viewpoint=(0.0, float("inf"), 0.0)).problem().startswith(
      "--pair-viewpoint:")
