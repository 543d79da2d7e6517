"""evaluate.py --scans: each folder of scans is a data set of its own, named by the folder, in
the same report, results and figures as the built-in data sets; a bad folder is one `error:`
line and exit code 2 before any work."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from lrf_jax.evaluation import experiments
from tests.lrf_testing import cli_error
from tests.test_datasets_scan_sets import write_scan_folder

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import evaluate  # noqa: E402


@pytest.fixture(scope="module")
def ring(tmp_path_factory) -> Path:
  folder = tmp_path_factory.mktemp("scans") / "ring"
  write_scan_folder(folder)
  return folder


def test_evaluate_scans_reports_the_folder_as_a_data_set(ring, tmp_path, capsys, monkeypatch):
  monkeypatch.setenv("LRF_CACHE", str(tmp_path / "cache"))
  out = tmp_path / "out"
  rc = evaluate.main(["--scans", str(ring), "--datasets", "demo", "--methods", "toldi",
                      "--keypoints", "40", "--max-pairs", "1", "--experiments",
                      "repeatability", "decimation", "--out", str(out)])
  assert rc == 0, capsys.readouterr().err
  report = (out / "report.md").read_text()
  assert "| ring | - | 1 |" in report and "| demo | noise_mr=0.3 | 1 |" in report
  assert "| ring | decimation=0.5 | 1 |" in report
  assert "ring: scan set" in report and "5 of 10 candidate pairs" in report
  records = json.loads((out / "results.json").read_text())["records"]
  ours = [r for r in records if r["dataset"] == "ring"]
  assert {r["experiment"] for r in ours} == {"repeatability", "decimation"}
  assert ours[0]["pair"] == "scan0->scan1" and ours[0]["n_keypoints"] == 40
  assert 0.3 < ours[0]["meancos"] <= 1.0
  assert (out / "repeatability.png").is_file() and (out / "decimation.png").is_file()
  assert "ring" in capsys.readouterr().out


def test_evaluate_scans_alone_runs_only_the_scan_sets(ring, tmp_path, monkeypatch):
  monkeypatch.setenv("LRF_CACHE", str(tmp_path / "cache"))
  out = tmp_path / "out"
  assert evaluate.main(["--scans", str(ring), "--methods", "toldi", "--keypoints", "30",
                        "--max-pairs", "1", "--out", str(out)]) == 0
  records = json.loads((out / "results.json").read_text())["records"]
  assert {r["dataset"] for r in records} == {"ring"}


def test_evaluate_weights_columns_and_min_overlap(ring, tmp_path, monkeypatch, capsys):
  """--weights adds an lrf_net_plus column per weights (named by the kind or the file's stem,
  read with the options of its card); --min-overlap keeps the pairs the rule would drop."""
  import shutil
  from lrf_jax.frames.weights import WEIGHTS_DIR
  monkeypatch.setenv("LRF_CACHE", str(tmp_path / "cache"))
  w = tmp_path / "mine.msgpack"
  shutil.copy(WEIGHTS_DIR / "lrf_net.msgpack", w)
  w.with_suffix(".json").write_text('{"options": {"vote": false}}')
  out = tmp_path / "out"
  assert evaluate.main(["--scans", str(ring), "--methods", "toldi", "--keypoints", "30",
                        "--max-pairs", "1", "--weights", "objects", str(w),
                        "--out", str(out)]) == 0, capsys.readouterr().err
  report = (out / "report.md").read_text()
  assert "lrf_net_plus[objects]" in report and "lrf_net_plus[mine]" in report
  assert "lrf_net_plus[mine]: mine.msgpack, read with {'vote': False}" in report
  low = tmp_path / "low"
  assert evaluate.main(["--scans", str(ring), "--methods", "toldi", "--keypoints", "30",
                        "--min-overlap", "0.01", "--out", str(low)]) == 0
  assert "of 10 candidate pairs overlap >= 1%" in (low / "report.md").read_text()
  assert evaluate.main(["--scans", str(ring), "--min-overlap", "0", "--out", str(low)]) == 2
  assert "--min-overlap: expected a fraction in (0, 1]" in capsys.readouterr().err


@pytest.mark.parametrize("case", ["not_a_folder", "no_pose_file", "built_in_name", "same_name"])
def test_evaluate_bad_scan_folder_is_one_error(tmp_path, capsys, case, ring):
  if case == "not_a_folder":
    args, fragment = [str(tmp_path / "nowhere")], "is not a folder"
  elif case == "no_pose_file":
    (tmp_path / "bare").mkdir()
    args, fragment = [str(tmp_path / "bare")], "pose file"
  elif case == "built_in_name":
    (tmp_path / "bunny").symlink_to(ring)
    args, fragment = [str(tmp_path / "bunny")], "built-in"
  else:
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "ring").symlink_to(ring)
    args, fragment = [str(ring), str(tmp_path / "a" / "ring")], "both named"
  out = tmp_path / "out"
  assert evaluate.main(["--scans", *args, "--methods", "toldi", "--out", str(out)]) == 2
  assert fragment in cli_error(capsys) and not out.exists()


def test_scan_sets_join_the_sweeps_as_their_own_clean_sets(ring):
  opts = experiments.EvalOptions(scans=(str(ring),), max_pairs=2)
  assert experiments.clean_datasets(["BR@0.3", "ring", "bunny"], opts) == ["BR", "bunny", "ring"]
  jobs = list(experiments.experiment_jobs("noise", ["ring"], [], opts))
  assert len(jobs) == 2 * len(experiments.NOISE_LEVELS)
  assert {j.dataset for j in jobs} == {"ring"} and jobs[0].nuisance == ("noise", 0.1)
