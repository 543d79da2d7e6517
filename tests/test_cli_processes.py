"""The command-line programs (`lrf_jax.cli`) as separate processes: Ctrl-C (a real SIGINT) and a
base install without matplotlib (simulated by `sys.modules["matplotlib"] = None`, which makes
every import of it fail as if it were not installed)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import datasets
from tests.lrf_testing import repo_env

REPO = Path(__file__).resolve().parents[1]

# Run lrf-register's main with matplotlib missing; print whether it got imported.
_NO_MATPLOTLIB = """
import sys
sys.modules["matplotlib"] = None
from lrf_jax.cli.register import main
rc = main(sys.argv[1:])
imported = [m for m in sys.modules if m.startswith("matplotlib") and sys.modules[m] is not None]
print("matplotlib imported:", imported, file=sys.stderr)
sys.exit(rc)
"""


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> list[str]:
  """Three small overlapping views of the demo model (.npy)."""
  folder = tmp_path_factory.mktemp("scans")
  pair = datasets.make_demo_pair(0)
  paths = []
  for k, pts in enumerate((pair.model_points, pair.scene_points, pair.model_points + 0.01)):
    path = folder / f"s{k}.npy"
    np.save(path, np.asarray(pts)[::2])
    paths.append(str(path))
  return paths


def _run_without_matplotlib(args: list[str]) -> subprocess.CompletedProcess:
  return subprocess.run([sys.executable, "-c", _NO_MATPLOTLIB, *args], capture_output=True,
                        text=True, cwd=REPO, env=repo_env(), timeout=600)


def test_png_without_matplotlib_fails_before_the_work(scans, tmp_path):
  t0 = time.perf_counter()
  r = _run_without_matplotlib([scans[0], scans[1], "--png", str(tmp_path / "x.png")])
  assert r.returncode == 2, r.stderr
  lines = [line for line in r.stderr.splitlines() if not line.startswith("matplotlib imported")]
  assert len(lines) == 1 and lines[0].startswith("error: --png needs matplotlib"), r.stderr
  assert "lrf_jax[plot]" in r.stderr and "Traceback" not in r.stderr
  assert r.stdout == "" and not (tmp_path / "x.png").exists()  # no transform: no work done
  assert time.perf_counter() - t0 < 60


def test_multiway_without_matplotlib_writes_the_model(scans, tmp_path):
  """A base install: with --no-figures matplotlib is never imported (merged.ply's colours were
  matplotlib's colormaps: ModuleNotFoundError, no merged.ply); without it everything but the
  figures is written and one line says they were skipped."""
  common = ["--quiet", "--keypoints", "300", "--no-refine"]
  out = tmp_path / "plain"
  r = _run_without_matplotlib([*scans, "--out-dir", str(out), "--no-figures", *common])
  assert r.returncode in (0, 3), r.stderr
  assert "Traceback" not in r.stderr and "matplotlib imported: []" in r.stderr, r.stderr
  assert (out / "merged.ply").stat().st_size > 0 and (out / "edges.tsv").exists()
  out = tmp_path / "figures"
  r = _run_without_matplotlib([*scans, "--out-dir", str(out), *common])
  assert r.returncode in (0, 3), r.stderr
  assert "Traceback" not in r.stderr and "matplotlib imported: []" in r.stderr, r.stderr
  skipped = [line for line in r.stderr.splitlines() if "figures skipped" in line]
  assert len(skipped) == 1 and "lrf_jax[plot]" in skipped[0], r.stderr
  assert (out / "merged.ply").exists() and not (out / "merged.png").exists()
  assert "merged.png" not in (out / "manifest.json").read_text()


def test_sigint_during_multiway_is_exit_130_without_traceback(scans, tmp_path):
  """A real Ctrl-C (SIGINT) while the pairs are registered: exit 130, one line, no traceback,
  nothing written."""
  out = tmp_path / "model"
  proc = subprocess.Popen([sys.executable, "-m", "lrf_jax.cli.register", *scans, "--out-dir",
                           str(out), "--no-figures", "--keypoints", "3000"],
                          stderr=subprocess.PIPE, cwd=REPO, env=repo_env())
  seen = b""
  while b"pairwise registration" not in seen:  # tqdm's bar: the imports are done
    chunk = os.read(proc.stderr.fileno(), 256)
    if not chunk:
      break
    seen += chunk
  time.sleep(1)  # registering the first pair
  proc.send_signal(signal.SIGINT)
  _, rest = proc.communicate(timeout=300)
  err = (seen + rest).decode(errors="replace")
  if proc.returncode == 0:
    pytest.skip("finished before the signal")
  assert proc.returncode == 130, err
  lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip()]
  assert "Traceback" not in err and lines[-1].startswith("interrupted: "), err
  assert sum(line.startswith(("interrupted", "error")) for line in lines) == 1, err
  assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("when", ["starting", "checkpointed"])
def test_sigint_during_training_is_exit_130_and_the_run_resumes(tmp_path, when):
  """A real Ctrl-C in train.py, while it starts (its checkpoint manager made, nothing saved) or
  once checkpoints exist: exit 130 and one line (the interpreter's teardown beside JAX's and
  orbax's threads crashed with a segmentation fault, -11, when interrupted while starting), no
  partial checkpoint and no lock left; what was saved restores."""
  work = tmp_path / "run"
  cmd = [sys.executable, "train.py", "--config", "smoke", "--workdir", str(work),
         "--no-progress", "epochs=400"]
  proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          cwd=REPO, env=repo_env())
  deadline = time.monotonic() + 300
  while ((work / "checkpoints").is_dir() if when == "starting" else
         len([p for p in (work / "checkpoints").glob("*") if p.name.isdigit()]) >= 2) is False:
    assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
    time.sleep(0.05)
  if when == "starting":
    time.sleep(1)
  proc.send_signal(signal.SIGINT)
  _, err = proc.communicate(timeout=300)
  assert proc.returncode == 130, err
  lines = [line for line in err.splitlines() if line.startswith(("interrupted", "error"))]
  assert lines == [lines[0]] and lines[0].startswith("interrupted: "), err
  assert "Traceback" not in err, err
  assert not list((work / "checkpoints").glob("*tmp*")) and not (work / "train.lock").exists()
  from lrf_jax.learning import checkpoints
  if any(p.name.isdigit() for p in (work / "checkpoints").iterdir()):
    params, _ = checkpoints.restore_params(work, "latest")  # intact, checksum verified
    assert not checkpoints.nonfinite_leaves(params)
  else:
    assert when == "starting"
