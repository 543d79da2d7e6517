"""Chunked, sharded and single-call frame computations give the same frames."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

import lrf_jax

REPO = Path(__file__).resolve().parents[1]
SCRIPT = """
import numpy as np, lrf_jax, jax
from lrf_jax import datasets
pair = datasets.make_demo_pair(0, seed=0, partial=False)
kp = np.arange(0, len(pair.model_points), 37)[:250]
f, v = lrf_jax.compute_frames(pair.model_points, kp, 15 * pair.mr, chunk_size=64)
np.savez(OUT, frames=np.asarray(f), valid=np.asarray(v), devices=jax.local_device_count())
"""


def _run(tmp_path: Path, devices: int) -> dict:
  out = tmp_path / f"f{devices}.npz"
  env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
             JAX_PLATFORMS="cpu")
  subprocess.run([sys.executable, "-c", SCRIPT.replace("OUT", repr(str(out)))], check=True,
                 env=env, cwd=REPO, capture_output=True)
  return dict(np.load(out))


def test_sharded_chunked_and_single_call_agree(tmp_path):
  from lrf_jax import datasets
  pair = datasets.make_demo_pair(0, seed=0, partial=False)
  kp = np.arange(0, len(pair.model_points), 37)[:250]
  single, vs = lrf_jax.compute_frames(pair.model_points, kp, 15 * pair.mr, chunk_size=10_000)
  four = _run(tmp_path, 4)
  assert int(four["devices"]) == 4
  np.testing.assert_array_equal(four["valid"], np.asarray(vs))
  np.testing.assert_allclose(four["frames"], np.asarray(single), atol=1e-5)
