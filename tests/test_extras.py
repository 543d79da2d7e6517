"""The install's extras: the core computes frames and registers without flax, optax, orbax,
matplotlib or fast-simplification, and a call that needs one of them names the extra."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
OPTIONAL = ("flax", "optax", "orbax", "matplotlib", "fast_simplification")


def _run_without(code: str, blocked=OPTIONAL, args: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
  """Run `code` in a fresh interpreter where the `blocked` packages cannot be imported."""
  prelude = "import sys\n" + "".join(f"sys.modules[{m!r}] = None\n" for m in blocked)
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  return subprocess.run([sys.executable, "-c", prelude + code, *args], capture_output=True,
                        text=True, env=env, cwd=REPO, timeout=600)


def test_pyproject_core_leaves_the_extras_out():
  meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
  core = " ".join(meta["dependencies"])
  for name in ("flax", "optax", "orbax", "matplotlib", "fast-simplification"):
    assert name not in core
  extras = meta["optional-dependencies"]
  assert {"train", "eval", "plot", "test"} <= set(extras)
  assert any(d.startswith("optax") for d in extras["train"])
  assert any(d.startswith("fast-simplification") for d in extras["eval"])
  assert "lrf_jax[train,eval,ray]" in extras["test"]  # the suite runs the Ray engine too
  assert (REPO / "lrf_jax" / "py.typed").exists()


@pytest.mark.slow
def test_core_computes_frames_and_registers_without_the_extras():
  code = """
import numpy as np, lrf_jax
rng = np.random.default_rng(0)
uv = rng.uniform(-1, 1, (3000, 2))
pts = np.column_stack([uv, 0.3 * np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])])
frames, valid = lrf_jax.compute_frames(pts, np.arange(50), radius_mr=15)
assert valid.sum() > 40
reg = lrf_jax.register(pts, pts + [0.1, 0.0, 0.0], n_keypoints=300, n_correspondences=200)
assert abs(reg.transform[0, 3] - 0.1) < 1e-3, reg.transform
blocked = [m for m in ("flax", "optax", "orbax", "matplotlib", "fast_simplification")
           if sys.modules.get(m) is not None]
assert not blocked, blocked
print("ok")
"""
  out = _run_without(code)
  assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-3000:]


def test_train_py_names_the_train_extra(tmp_path):
  code = "import runpy; runpy.run_path('train.py', run_name='__main__')"
  out = _run_without(code, ("optax",), ("--config", "smoke", "--workdir", str(tmp_path / "w")))
  assert out.returncode == 2, out.stderr[-3000:]
  assert "error:" in out.stderr and "lrf_jax[train]" in out.stderr and "optax" in out.stderr
  assert "Traceback" not in out.stderr
  assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("code, blocked, extra", [
    ("import lrf_jax.learning.networks", ("flax",), "train"),
    ("import lrf_jax.learning.checkpoints", ("orbax",), "train"),
    ("import numpy as np\nfrom lrf_jax.datasets import decimate\n"
     "decimate(np.random.default_rng(0).random((10, 3)), np.array([[0, 1, 2], [1, 2, 3]]), 0.5)",
     ("fast_simplification",), "eval"),
    ("from lrf_jax.extras import pyplot\npyplot()", ("matplotlib",), "plot"),
])
def test_a_missing_extra_is_named(code, blocked, extra):
  out = _run_without(code, blocked)
  assert out.returncode != 0
  last = out.stderr.strip().splitlines()[-1]
  assert "MissingExtraError" in last and f"lrf_jax[{extra}]" in last, last


def test_evaluate_py_names_the_eval_extra_before_any_work(tmp_path):
  code = "import runpy; runpy.run_path('evaluate.py', run_name='__main__')"
  out = _run_without(code, ("matplotlib",), ("--out", str(tmp_path / "o"), "--max-pairs", "1"))
  assert out.returncode == 2, out.stderr[-3000:]
  assert "error:" in out.stderr and "lrf_jax[eval]" in out.stderr and "matplotlib" in out.stderr
  assert not (tmp_path / "o").exists()


def test_require_sees_installed_and_blocked_packages():
  out = _run_without("from lrf_jax import extras\nextras.require('train', 'x')\nprint('ok')",
                     blocked=())
  assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-2000:]
  out = _run_without("from lrf_jax import extras\nextras.require('train', 'x')", ("optax",))
  assert out.returncode != 0 and "lrf_jax[train]" in out.stderr.strip().splitlines()[-1]
