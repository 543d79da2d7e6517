"""`lrf-view`: a bad command line or input is one `error:` line and exit code 2 before anything
is served; a running viewer prints its address, warns once when it serves other machines, and
ends with exit code 130 on Ctrl-C."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lrf_jax.cli.view import main
from tests.test_viz import make_batch_folder, make_model_folder

REPO = Path(__file__).resolve().parents[1]


def _refused(capsys, argv: list[str]) -> str:
  """Run lrf-view's main on `argv`; it must refuse with one error line and exit code 2."""
  assert main(argv + ["--no-browser"]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("error: "), err
  return err[0]


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
  return make_model_folder(tmp_path_factory.mktemp("view") / "model", n=500)


def test_a_folder_of_neither_kind_is_refused(tmp_path, capsys):
  (tmp_path / "notes.txt").write_text("x")
  line = _refused(capsys, [str(tmp_path)])
  assert "neither a multiway output folder" in line and "nor an lrf-batch register" in line
  assert "no such folder" in _refused(capsys, [str(tmp_path / "nothing")])


def test_a_missing_transform_or_cloud_is_refused(tmp_path, capsys):
  a, b = tmp_path / "a.npy", tmp_path / "b.npy"
  np.save(a, np.random.default_rng(0).random((50, 3)))
  np.save(b, np.random.default_rng(1).random((50, 3)))
  line = _refused(capsys, [str(a), str(b), "--transform", str(tmp_path / "T.txt")])
  assert line == f"error: --transform {tmp_path / 'T.txt'}: no such file"
  assert "TARGET" in _refused(capsys, [str(a), str(tmp_path / "c.npy")])
  bad = tmp_path / "bad.txt"
  bad.write_text("1 0 0\n0 1 0\n0 0 1\n")
  assert "--transform" in _refused(capsys, [str(a), str(b), "--transform", str(bad)])


def test_bad_ports_and_arguments_are_refused(model, capsys):
  for port in ("abc", "0", "70000", "-5"):
    assert "--port: expected a port number from 1 to 65535" in \
        _refused(capsys, [str(model), "--port", port])
  assert "--max-points" in _refused(capsys, [str(model), "--max-points", "0"])
  assert "--transform: only with two clouds" in \
      _refused(capsys, [str(model), "--transform", str(model / "alpha.txt")])
  assert "expected an output folder or two clouds" in \
      _refused(capsys, [str(model), str(model), str(model)])
  assert "--host" in _refused(capsys, [str(model), "--host", "no-such-host.invalid"])


def test_a_port_in_use_is_refused(model, capsys):
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    s.listen()
    port = s.getsockname()[1]
    line = _refused(capsys, [str(model), "--port", str(port)])
  assert f"--port: {port} is in use on 127.0.0.1" in line


def test_a_batch_frames_folder_is_refused(tmp_path, capsys):
  (tmp_path / "results.tsv").write_text("name\tscan\tstatus\n")
  assert "frames folder" in _refused(capsys, [str(tmp_path)])


def _start(args: list[str]) -> tuple[subprocess.Popen, str]:
  """lrf-view in a process of its own (python -m), and the address it printed."""
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  proc = subprocess.Popen([sys.executable, "-m", "lrf_jax.cli.view", *args, "--no-browser"],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
  line = proc.stdout.readline()
  m = re.match(r"lrf-view: (http://\S+) \(Ctrl-C to stop\)$", line.strip())
  if not m:
    proc.kill()
    raise AssertionError(f"no address line: {line!r} {proc.communicate()}")
  return proc, m.group(1)


def _interrupt(proc: subprocess.Popen) -> tuple[str, str]:
  proc.send_signal(signal.SIGINT)
  out, err = proc.communicate(timeout=30)
  assert proc.returncode == 130, (out, err)
  return out, err


def test_a_host_other_than_loopback_warns_once_and_ctrl_c_exits_130(model):
  proc, url = _start([str(model), "--host", "0.0.0.0"])
  out, err = _interrupt(proc)
  lines = err.strip().splitlines()
  assert sum(line.startswith("warning: --host 0.0.0.0") for line in lines) == 1, err
  assert "without a password" in err and lines[-1].startswith("interrupted:")
  assert url.startswith("http://localhost:") and "Traceback" not in err


def test_the_default_serves_127_0_0_1_silently_until_ctrl_c(tmp_path):
  import urllib.request
  proc, url = _start([str(make_batch_folder(tmp_path / "b"))])
  assert url.startswith("http://127.0.0.1:")
  with urllib.request.urlopen(url, timeout=10) as r:
    assert r.status == 200
  out, err = _interrupt(proc)
  assert err.strip().splitlines() == ["interrupted: the viewer stopped"]
  assert out == ""  # nothing of viser's on stdout


def test_a_missing_viser_is_one_error_line_naming_the_extra(model):
  code = ("import sys\nsys.modules['viser'] = None\nfrom lrf_jax.cli.view import main\n"
          f"sys.exit(main([{str(model)!r}, '--no-browser']))\n")
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=120)
  assert out.returncode == 2, out.stderr
  assert out.stderr.strip().splitlines() == [
      "error: lrf-view needs viser, which is not installed: pip install 'lrf_jax[viz]' (the "
      "'viz' extra: viser)"]
