"""Multi-process training: 2 processes (one CPU device each, joined by jax.distributed over
gloo) train the smoke config to the same parameters as 1 process with 2 devices."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from lrf_jax.learning import checkpoints
from lrf_jax.frames.weights import load_params

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 300
# One epoch (16 steps) with validation, so that checkpoints with metrics and best_params.msgpack
# are written too; 50 validation keypoints keep each run at about 20 s.
OVERRIDES = ["epochs=1", "val_keypoints=50"]


def _free_port() -> int:
  """A TCP port on 127.0.0.1 that nothing listens on now."""
  with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _train_cmd(workdir: Path, *extra: str) -> list[str]:
  return [sys.executable, str(REPO / "train.py"), "--config", "smoke", "--workdir", str(workdir),
          "--no-progress", *extra, *OVERRIDES]


def _env(devices: int) -> dict[str, str]:
  return dict(os.environ, JAX_PLATFORMS="cpu",
              XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")


def _run_all(cmds: list[list[str]], env: dict[str, str]) -> list[tuple[int, str]]:
  """Run `cmds` at the same time; (exit code, output) of each. Kills all of them when one is
  still running after TIMEOUT_S, so a process waiting for a dead peer cannot hang the test."""
  procs = [subprocess.Popen(c, env=env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True) for c in cmds]
  results = []
  try:
    for p in procs:
      out, _ = p.communicate(timeout=TIMEOUT_S)
      results.append((p.returncode, out))
  except subprocess.TimeoutExpired:
    for p in procs:
      p.kill()
    outs = [p.communicate()[0] for p in procs]
    pytest.fail(f"training did not finish within {TIMEOUT_S} s; output:\n" + "\n---\n".join(outs))
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
  return results


def _assert_close(a, b) -> tuple[float, float]:
  """assert_allclose over two parameter trees; returns (max abs, max rel) difference."""
  la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
  assert jax.tree.structure(a) == jax.tree.structure(b) and len(la) > 0
  abs_d = rel_d = 0.0
  for x, y in zip(la, lb):
    x, y = np.asarray(x), np.asarray(y)
    np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-7)
    d = np.abs(x - y)
    abs_d = max(abs_d, float(d.max()))
    rel_d = max(rel_d, float((d / np.maximum(np.abs(y), 1e-30)).max()))
  return abs_d, rel_d


@pytest.mark.slow
def test_two_processes_train_like_one_process_with_two_devices(tmp_path):
  port = _free_port()
  multi = tmp_path / "two_processes"
  cmds = [_train_cmd(multi, "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
                     "--process-id", str(i)) for i in range(2)]
  results = _run_all(cmds, _env(1))
  for i, (rc, out) in enumerate(results):
    assert rc == 0, f"process {i} exited {rc}:\n{out}"
  # Only process 0 prints the final metrics.
  assert "step 16 of 16" in results[0][1] and "step 16 of" not in results[1][1], results
  assert "wrote " in results[0][1] and "wrote " not in results[1][1], results

  single = tmp_path / "one_process"
  ((rc, out),) = _run_all([_train_cmd(single)], _env(2))
  assert rc == 0, out

  for name in ("final_params.msgpack", "best_params.msgpack"):
    diff = _assert_close(load_params(multi / name), load_params(single / name))
    print(f"{name}: max abs / rel difference {diff[0]:.3g} / {diff[1]:.3g}")
  # The checkpoint both processes wrote together is complete and holds the final parameters.
  params, _ = checkpoints.restore_params(multi, "latest")
  _assert_close(params, load_params(multi / "final_params.msgpack"))
  # metrics.jsonl is written once (by process 0), with the same numbers as the 1-process run.
  rows = [json.loads(l) for l in (multi / "metrics.jsonl").read_text().splitlines()]
  ref = [json.loads(l) for l in (single / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == [r["step"] for r in ref] == [4, 8, 12, 16]
  for key in ("loss", "grad_norm", "val_meancos"):
    np.testing.assert_allclose([r.get(key, 0.0) for r in rows], [r.get(key, 0.0) for r in ref],
                               rtol=1e-5)
  assert (multi / "curves.png").exists() and (multi / "config.json").exists()
