"""Every console script of pyproject.toml, each run as a fresh process (nothing imported before
it: a submodule reached only through an earlier import fails here), on small clouds."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import datasets
from tests.lrf_testing import repo_env

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def _command(script: str) -> list[str]:
  """The installed console script, else its entry point run by this interpreter."""
  exe = Path(sys.executable).with_name(script)
  if exe.exists():
    return [str(exe)]
  module, _, func = SCRIPTS[script].partition(":")
  return [sys.executable, "-c", f"import sys; from {module} import {func}; sys.exit({func}())"]


@pytest.fixture(scope="module")
def clouds(tmp_path_factory) -> list[Path]:
  folder = tmp_path_factory.mktemp("console")
  out = []
  for k in range(3):
    pair = datasets.make_demo_pair(0, seed=k, noise_mr=0.05, partial=True)
    out.append(folder / f"scan{k}.npy")
    np.save(out[-1], pair.scene_points)
  return out


def _cases(clouds: list[Path], tmp: Path) -> dict[str, list[list[str]]]:
  a, b, c = map(str, clouds)
  (tmp / "pairs.tsv").write_text(f"name\tsource\ttarget\np\t{a}\t{b}\n")
  few = ["--keypoints", "300"]
  return {
      "lrf-register": [[a, b, "--out", str(tmp / "T.txt"), "--best-guess", *few],
                       [a, b, c, "--out-dir", str(tmp / "model"), "--no-figures", "--quiet",
                        *few]],
      "lrf-frames": [[a, "--out", str(tmp / "f.npz"), "--keypoints", "50"]],
      "lrf-batch": [["frames", a, "--out", str(tmp / "frames"), "--keypoints", "50",
                     "--no-progress"],
                    ["register", str(tmp / "pairs.tsv"), "--out", str(tmp / "reg"),
                     "--no-progress", *few]],
      "lrf-compile": [["--list"]],
      "lrf-view": [["--help"]],
  }


def test_every_console_script_is_tested_here(clouds, tmp_path):
  assert sorted(_cases(clouds, tmp_path)) == sorted(SCRIPTS)


@pytest.mark.slow  # a fresh process per command: JAX's import and the cached kernels' loading
@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_console_script_in_a_fresh_process(script, clouds, tmp_path):
  for args in _cases(clouds, tmp_path)[script]:
    run = subprocess.run([*_command(script), *args], capture_output=True, text=True,
                         timeout=600, cwd=tmp_path)
    assert run.returncode in (0, 3), f"{script} {args}: rc {run.returncode}\n{run.stderr}"
    assert "Traceback" not in run.stderr, run.stderr
    assert not re.search(r"\berror:", run.stderr), run.stderr


def test_ctrl_c_while_a_console_script_imports_is_one_line_and_130(tmp_path):
  """Before: a Ctrl-C while `lrf-batch` imported its modules (a second or more) was a traceback
  and the signal's own exit status."""
  code = ("from lrf_jax.cli import console\n"
          "def main():\n  raise KeyboardInterrupt\n"
          "console.run(main)\n")
  proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                        env=repo_env(), timeout=120)
  assert proc.returncode == 130 and proc.stderr.strip() == "interrupted", proc.stderr
