"""Data-set jobs on a real Ray instance (started by this module, bound to 127.0.0.1): the same
results as the local engine, a worker killed mid-job at a deterministic point, a refused worker
version, a corrupt scan isolated."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from lrf_jax import batch  # noqa: E402
from lrf_jax.batch import engines, jobs  # noqa: E402
from tests.lrf_testing import own_ray_instance  # noqa: E402
from tests.test_batch import OPTS, make_scans, pairs_tsv, tsv_rows  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def ray_instance():
  """A Ray instance of this module: new (address "local": never a cluster found on the machine
  or in RAY_ADDRESS), on 127.0.0.1, with a token of its own (nothing read from or written to
  ~/.ray); the engines of the tests use it."""
  with own_ray_instance():
    yield


def test_ray_engine_gives_the_local_engines_results(tmp_path):
  scans = make_scans(tmp_path / "scans", 2)
  corrupt = tmp_path / "scans" / "corrupt.ply"
  corrupt.write_text("ply\nformat ascii 1.0\nelement vertex 5\nend_header\n1 2\n")
  tsv = pairs_tsv(tmp_path / "scans", scans, corrupt)
  local = batch.run_register(tsv, tmp_path / "local", progress=False, **OPTS)
  remote = batch.run_register(tsv, tmp_path / "ray", engine="ray", progress=False, **OPTS)
  assert local.exit_code == remote.exit_code == 3
  node = ray.get_runtime_context().get_node_id()
  for a, b in zip(tsv_rows(tmp_path / "local" / "results.tsv"),
                  tsv_rows(tmp_path / "ray" / "results.tsv")):
    for col in ("name", "status", "success", "reason", "error"):
      assert a[col] == b[col], col
    assert b["node"] == node and a["node"] == "local"
    if a["status"] == "done":
      ra, rb = (json.loads((tmp_path / d / jobs.STATE / "records" / f"{a['name']}.json")
                           .read_text()) for d in ("local", "ray"))
      assert ra["transform"] == rb["transform"]  # exact floats
      assert (tmp_path / "local" / f"{a['name']}.txt").read_bytes() == \
          (tmp_path / "ray" / f"{a['name']}.txt").read_bytes()
  assert "corrupt.ply" in tsv_rows(tmp_path / "ray" / "results.tsv")[2]["error"]
  again = batch.run_register(tsv, tmp_path / "ray", engine="ray", progress=False, **OPTS)
  assert (again.ran, again.skipped) == (0, 3)


def test_a_worker_killed_mid_item_costs_a_retry_not_the_job(tmp_path):
  pid_file, go = tmp_path / "pid", tmp_path / "go"

  def gated(x):  # item 2 waits on a file the test controls; its first worker is killed
    if x == 2 and not go.exists():
      pid_file.write_text(str(os.getpid()))
      while not go.exists():
        time.sleep(0.05)
    return x * x

  def killer():
    while not pid_file.exists():
      time.sleep(0.05)
    os.kill(int(pid_file.read_text()), signal.SIGKILL)
    go.touch()

  t = threading.Thread(target=killer, daemon=True)
  t.start()
  outcomes = sorted(engines.RayEngine().run(gated, list(range(5))), key=lambda o: o.index)
  t.join(timeout=60)
  assert [o.value for o in outcomes] == [0, 1, 4, 9, 16]
  assert all(o.error is None for o in outcomes)
  assert outcomes[2].attempt == 2 and {o.attempt for i, o in enumerate(outcomes) if i != 2} == {1}


def test_a_worker_of_another_version_is_refused(monkeypatch):
  monkeypatch.setattr(engines, "_version", lambda: "0.0.0-driver")
  (o,) = engines.RayEngine().run(abs, [-3])
  assert o.value is None and "the driver 0.0.0-driver: refused" in o.error


def test_lost_work_beyond_the_retries_is_an_error_row(tmp_path):
  def dies(x):
    os.kill(os.getpid(), signal.SIGKILL)

  (o,) = engines.RayEngine(max_retries=0).run(dies, [1])
  assert o.value is None and o.error.startswith("lost after 1 attempts")


def test_every_item_records_the_node_and_version(tmp_path):
  import lrf_jax
  scans = make_scans(tmp_path / "s", 1)
  res = batch.run_frames(scans, tmp_path / "out", engine="ray", progress=False, keypoints="50")
  assert res.exit_code == 0
  for row in res.rows:
    assert row["version"] == lrf_jax.__version__ and len(row["node"]) > 20
  a = np.load(tmp_path / "out" / "scene0.npz")
  local = batch.run_frames(scans, tmp_path / "loc", progress=False, keypoints="50")
  b = np.load(Path(local.out) / "scene0.npz")
  for key in a.files:
    assert np.array_equal(a[key], b[key]), key


def test_each_worker_uses_the_cpus_its_task_was_given():
  def threads(_):
    from lrf_jax.search import grid
    return os.environ.get("LRF_JAX_NUM_THREADS"), grid.num_threads()

  outcomes = list(engines.RayEngine(cpus_per_task=1).run(threads, [0, 1]))
  assert {o.value for o in outcomes} == {("1", 1)}


def test_multiway_on_ray_gives_the_in_process_result(tmp_path):
  """`register_all(engine=RayEngine())`: each scan described once as a task, its features put
  once in the object store, every pair a task; poses and edges equal the in-process run's, and
  a rerun from the state folder registers nothing."""
  from lrf_jax import multiway
  from tests.test_multiway import _views
  clouds, _, mr = _views(3, step_deg=35.0)
  kw = dict(mr=mr, refine=False, n_keypoints=300)
  local = multiway.register_all(clouds, **kw)
  remote = multiway.register_all(clouds, engine=engines.RayEngine(), state_dir=tmp_path, **kw)
  assert remote.work == dict(scans_described=3, pairs_registered=3, pairs_resumed=0)
  assert np.array_equal(local.poses, remote.poses, equal_nan=True)
  for a, b in zip(local.edges, remote.edges):
    assert (a.verdict, a.reason, a.accepted) == (b.verdict, b.reason, b.accepted)
    assert np.array_equal(a.transform, b.transform, equal_nan=True)
  again = multiway.register_all(clouds, engine=engines.RayEngine(), state_dir=tmp_path, **kw)
  assert again.work["pairs_registered"] == 0
