"""evaluate.py --engine: the pairs spread over the data-set engine give the local run's records
(exact floats, in pair order), outputs written by the driver only; a bad engine or address is
refused before any work; a pair the engine could not run is an error that names it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

import evaluate
from lrf_jax.batch import engines
from lrf_jax.evaluation import runner

# A small run for the fake engines (two methods, 100 keypoints, the demo's 4 pairs).
SMALL = ["--datasets", "demo", "--methods", "toldi", "shot", "--keypoints", "100"]


def _records(out: Path) -> list[dict]:
  """results.json's records without their timings."""
  recs = json.loads((out / "results.json").read_text())["records"]
  return [{k: v for k, v in r.items() if k != "seconds"} for r in recs]


class FakeEngine:
  """Runs every payload here, then yields the outcomes last first (`reverse`: a cluster's
  completion order at its worst) or in order; `fail` = an index whose outcome carries an engine
  error instead of a value."""

  name = "fake"

  def __init__(self, fail: int | None = None, reverse: bool = True):
    self.fail, self.reverse = fail, reverse
    self.closed = False

  def run(self, fn, payloads):
    outcomes = [engines.Outcome(i, None, "lost after 4 attempts: NodeDiedError", "?", 4, "?")
                if i == self.fail else engines.Outcome(i, fn(p), None, "n1", 1, "0")
                for i, p in enumerate(payloads)]
    yield from reversed(outcomes) if self.reverse else outcomes

  def close(self):
    self.closed = True


def test_records_are_put_back_in_pair_order_whatever_the_completion_order(tmp_path,
                                                                           monkeypatch):
  assert evaluate.main(SMALL + ["--out", str(tmp_path / "local")]) == 0
  fake = FakeEngine()
  monkeypatch.setattr(engines, "make_engine", lambda engine, address=None: fake)
  assert evaluate.main(SMALL + ["--out", str(tmp_path / "fake")]) == 0
  assert _records(tmp_path / "fake") == _records(tmp_path / "local")
  assert (tmp_path / "fake" / "report.md").read_text() == \
      (tmp_path / "local" / "report.md").read_text()
  assert fake.closed
  assert not (tmp_path / "fake" / "partial_records.jsonl").exists()


def test_an_engine_error_names_the_pair(tmp_path, monkeypatch, capsys):
  fake = FakeEngine(fail=1, reverse=False)  # the second pair fails
  monkeypatch.setattr(engines, "make_engine", lambda engine, address=None: fake)
  out = tmp_path / "out"
  assert evaluate.main(SMALL + ["--out", str(out)]) == 1
  err = capsys.readouterr().err.strip().splitlines()[-1]
  assert err.startswith("error: repeatability on demo, pair demo1/"), err
  assert "could not run it (lost after 4 attempts: NodeDiedError)" in err
  assert "noise_mr=0.3" in err  # the setting
  assert fake.closed
  assert not (out / "results.json").exists()  # no report from a partial run
  # The one pair before it (in pair order) is kept: demo0's two records.
  kept = [json.loads(line) for line in (out / "partial_records.jsonl").read_text().splitlines()]
  assert [(r["pair"], r["method"]) for r in kept] == [(kept[0]["pair"], "toldi"),
                                                     (kept[0]["pair"], "shot")]
  assert kept[0]["pair"].startswith("demo0/")
  assert "the 2 records before it are in" in err


def test_a_job_error_from_the_library_names_the_pair(tmp_path, monkeypatch):
  monkeypatch.setattr(engines, "make_engine", lambda engine, address=None: FakeEngine(0))
  runs, _ = runner.method_runs(["toldi"])
  plan = runner.EvalPlan(["demo"], ["rotation"], runs,
                         runner.EvalOptions(n_keypoints=50, max_pairs=1))
  with pytest.raises(runner.JobError, match=r"rotation on demo, pair demo0/\S+ "
                                            r"\(rotation_deg=30.0\): the fake engine"):
    runner.evaluate(plan, tmp_path, progress=False)


@pytest.mark.parametrize("argv, flag", [
    (["--address", "127.0.0.1:6379"], "--address"),
    (["--engine", "local", "--address", "local"], "--address"),
    (["--engine", "ray", "--cache-dir", "cache"], "--cache-dir"),
    (["--engine", "ray", "--address", "127.0.0.1:1"], "--address"),  # nothing listens there
    (["--engine", "ray", "--address", "no-port"], "--address"),
])
def test_a_bad_engine_option_is_refused_before_any_work(tmp_path, monkeypatch, capsys, argv,
                                                        flag):
  monkeypatch.setattr(runner, "evaluate", lambda *a, **k: pytest.fail("work started"))
  out = tmp_path / "out"
  assert evaluate.main(["--datasets", "demo", "--out", str(out)] + argv) == 2
  err = capsys.readouterr().err.strip()
  assert err.startswith(f"error: {flag}: ") and len(err.splitlines()) == 1, err
  assert not out.exists()


def test_the_ray_engine_without_ray_names_the_extra_before_any_work(tmp_path, monkeypatch,
                                                                   capsys):
  monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
  monkeypatch.setattr(runner, "evaluate", lambda *a, **k: pytest.fail("work started"))
  out = tmp_path / "out"
  assert evaluate.main(["--datasets", "demo", "--engine", "ray", "--out", str(out)]) == 2
  err = capsys.readouterr().err.strip()
  assert err.startswith("error: ") and "lrf_jax[ray]" in err and "--engine ray" in err, err
  assert not out.exists()


def test_an_unknown_engine_is_an_argparse_error(tmp_path, capsys):
  with pytest.raises(SystemExit) as e:
    evaluate.main(["--engine", "spark", "--out", str(tmp_path / "out")])
  assert e.value.code == 2
  err = capsys.readouterr().err
  assert "--engine: invalid choice: 'spark'" in err and "'local', 'ray'" in err
  assert not (tmp_path / "out").exists()


def test_help_names_the_engines(capsys):
  with pytest.raises(SystemExit):
    evaluate.main(["--help"])
  text = capsys.readouterr().out
  assert "--engine {local,ray}" in text and "--address ADDRESS" in text


@pytest.fixture
def ray_instance():
  ray = pytest.importorskip("ray")
  from tests.lrf_testing import own_ray_instance
  with own_ray_instance():  # never joins another cluster of the machine
    yield ray


@pytest.mark.slow  # about 60 s on 2 cores: Ray's start, two workers compiling, the run twice
def test_the_default_run_on_ray_gives_the_local_records(tmp_path, monkeypatch, ray_instance):
  """`python evaluate.py` with no data (the demo: repeatability, every method, 1000 keypoints,
  4 pairs) on a Ray instance of 127.0.0.1 with 2 CPUs: the same records, report and figures as
  the local run; every pair ran on the Ray node."""
  nowhere = ["--data", str(tmp_path / "no-data")]  # no real data: the demo, as with none found
  assert evaluate.main(nowhere + ["--out", str(tmp_path / "local")]) == 0
  nodes = []
  real = engines.make_engine

  def spy(engine, address=None):
    eng = real(engine, address)
    run = eng.run

    def run_spy(fn, payloads):
      for outcome in run(fn, payloads):
        nodes.append(outcome.node)
        yield outcome
    eng.run = run_spy  # type: ignore[method-assign]
    return eng

  monkeypatch.setattr(engines, "make_engine", spy)
  assert evaluate.main(nowhere + ["--engine", "ray", "--out", str(tmp_path / "ray")]) == 0
  assert nodes == [ray_instance.get_runtime_context().get_node_id()] * 4  # one job a pair
  local, remote = tmp_path / "local", tmp_path / "ray"
  assert _records(remote) == _records(local)  # exact floats, same order
  assert (remote / "report.md").read_text() == (local / "report.md").read_text()
  assert sorted(p.name for p in remote.iterdir()) == sorted(p.name for p in local.iterdir())
  for png in local.glob("*.png"):
    assert (remote / png.name).read_bytes() == png.read_bytes(), png.name
  meta = json.loads((remote / "results.json").read_text())["meta"]
  assert meta["args"]["engine"] == "ray" and meta["patch_cache"] is None
