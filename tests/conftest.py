"""Shared test setup: NaN debugging on, float64 available, the real data root resolved once."""

import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_debug_nans", True)  # any NaN produced inside a jitted function fails a test
# no compile workers beside the suite's commands (tests/test_parallel_compile.py turns them on)
os.environ.setdefault("LRF_JAX_PARALLEL_COMPILE", "0")

REPO = Path(__file__).resolve().parents[1]


def _data_root() -> Path | None:
  for cand in (os.environ.get("LRF_DATA"), REPO / "data", REPO.parent / "shared" / "data"):
    if cand and (Path(cand) / "bologna_retrieval").is_dir():
      return Path(cand)
  return None


@pytest.fixture(scope="session")
def data_root() -> Path:
  root = _data_root()
  if root is None:
    pytest.skip("real data not found: set LRF_DATA to the folder holding bologna_retrieval/ "
                "(see data/README.md)")
  return root


@pytest.fixture(scope="session")
def br_bunny(data_root):
  """The BR bunny model (points float64, faces), its mr (mean edge length) and Scene0's .xf."""
  from tests.lrf_testing import load_br_model
  return load_br_model(data_root, "bunny", scene=0)


@pytest.fixture(scope="module")
def cloud_npy(tmp_path_factory) -> Path:
  """A small demo cloud as an .npy (points only), for the command-line programs' tests."""
  import numpy as np
  from lrf_jax import datasets
  path = tmp_path_factory.mktemp("cloud") / "scan.npy"
  np.save(path, datasets.make_demo_pair(0).model_points[::16])
  return path


def pytest_collection_modifyitems(config, items):
  """Every test that reaches the real data through the `data_root` fixture (directly or through
  a fixture built on it) is marked `data`, so `-m "not data"` means what it says."""
  for item in items:
    if "data_root" in getattr(item, "fixturenames", ()):
      item.add_marker(pytest.mark.data)
