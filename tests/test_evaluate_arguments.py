"""Bad arguments of evaluate.py: each is one `error:` line naming the option, exit code 2, no
traceback and nothing written (driven in-process through its `main(argv)`, before any work)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tests.lrf_testing import cli_error

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import evaluate  # noqa: E402


@pytest.mark.parametrize("extra,fragment", [
    (["--methods", "nosuch"], "--methods"),
    (["--keypoints", "-5"], "--keypoints"), (["--keypoints", "0"], "--keypoints"),
    (["--radius-mr", "nan"], "--radius-mr"), (["--radius-mr", "0"], "--radius-mr"),
    (["--max-neighbors", "-1"], "--max-neighbors"), (["--max-pairs", "-1"], "--max-pairs"),
    (["--max-pairs", "0"], "--max-pairs"), (["--seed", "-2"], "--seed"),
    (["--params", "x=MISSING.msgpack"], "--params"),
    (["--params", "x=MISSING.msgpack@nosuch"], "--params"),
    (["--checkpoint", "EMPTY"], "--checkpoint"),
])
def test_evaluate_bad_argument(tmp_path, capsys, extra, fragment):
  (tmp_path / "empty").mkdir()
  extra = [a.replace("MISSING", str(tmp_path / "none")).replace("EMPTY", str(tmp_path / "empty"))
           for a in extra]
  out = tmp_path / "out"
  assert evaluate.main(["--datasets", "demo", "--out", str(out)] + extra) == 2
  assert fragment in cli_error(capsys)
  assert not out.exists()


def test_evaluate_out_is_a_file(tmp_path, capsys):
  out = tmp_path / "results"
  out.write_text("mine")
  assert evaluate.main(["--datasets", "demo", "--methods", "toldi", "--out", str(out)]) == 2
  assert "--out" in cli_error(capsys)
  assert out.read_text() == "mine"


def test_evaluate_params_file_where_an_output_goes(tmp_path, capsys):
  out = tmp_path / "out"
  out.mkdir()
  (out / "report.md").write_text("not parameters")
  assert evaluate.main(["--datasets", "demo", "--methods", "toldi", "--out", str(out),
                        "--params", f"x={out / 'report.md'}"]) == 2
  assert "--params" in cli_error(capsys)
