"""`lrf_jax.cli.interrupt`: a Ctrl-C is never lost, neither one Python had to drop in a finalizer
nor one a library swallowed (the handler sends it again): the program stops with exit 130 and
one `interrupted:` line."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from tests.lrf_testing import repo_env


_LOST_CTRL_C = """
import gc, sys, time
from lrf_jax.cli.interrupt import interruptible

class Finalized:
  def __del__(self):
    raise KeyboardInterrupt  # Ctrl-C arriving while Python runs a finalizer or a gc callback

@interruptible("stopped")
def main():
  Finalized()  # dropped at once: its __del__ runs here, and Python must ignore what it raises
  t0 = time.monotonic()
  while time.monotonic() - t0 < 60:  # the work goes on
    time.sleep(0.01)
  return 0

sys.exit(main())
"""


def test_a_ctrl_c_python_had_to_drop_in_a_finalizer_still_stops_the_program():
  """Seen in the suite (train.py under NUMBA_CPU_NAME=generic): a SIGINT that landed in JAX's
  `_xla_gc_callback` was printed as "Exception ignored in ..." and lost; training went on (the
  test's 300 s timeout). Before: this program ran its 60 s and exited 0."""
  t0 = time.monotonic()
  proc = subprocess.run([sys.executable, "-c", _LOST_CTRL_C], capture_output=True, text=True,
                        env=repo_env(), timeout=120)
  assert proc.returncode == 130 and proc.stderr.strip() == "interrupted: stopped", proc.stderr
  assert time.monotonic() - t0 < 50


def test_a_ctrl_c_a_library_swallows_is_sent_again(monkeypatch, capsys):
  """Before: a KeyboardInterrupt caught by library code (a checkpoint manager's `except
  BaseException`, a C++ callback) was lost and the program went on (train.py trained 400 epochs
  after Ctrl-C in a fresh CI environment). The SIGINT handler sends it again unless the program
  stopped by then."""
  import signal
  from lrf_jax.cli import interrupt
  monkeypatch.setattr(interrupt, "REDELIVER_AFTER_S", 0.2)
  swallowed = []

  @interrupt.interruptible("test")
  def main() -> int:
    try:
      os.kill(os.getpid(), signal.SIGINT)
      time.sleep(2)
    except KeyboardInterrupt:
      swallowed.append(True)  # what the library did
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
      time.sleep(0.01)
    return 0

  before = signal.getsignal(signal.SIGINT)
  assert main() == interrupt.INTERRUPTED and swallowed == [True]
  assert capsys.readouterr().err.startswith("interrupted: test")
  assert signal.getsignal(signal.SIGINT) is before  # the program's handler is removed again


_CTRL_C_IN_A_CALLBACK = """
import ctypes, os, signal, sys
from lrf_jax.cli.interrupt import interruptible

@ctypes.CFUNCTYPE(None)
def compiled_hook():  # as numba's object-code hook, called by LLVM from C
  os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C lands while the callback runs
  for _ in range(10**6):
    pass
  RESULT.append("object code")  # never reached: the KeyboardInterrupt ends the callback

RESULT = []

@interruptible("stopped")
def main():
  ctypes.cast(compiled_hook, ctypes.CFUNCTYPE(None))()  # Python drops what the callback raised
  if not RESULT:
    raise RuntimeError("no compiled object yet")  # what numba then raises
  return 0

sys.exit(main())
"""


def test_an_error_after_a_ctrl_c_in_a_c_callback_is_the_ctrl_c():
  """Seen in CI (lrf-register, Ctrl-C while numba compiled `_bin`): the KeyboardInterrupt raised
  in LLVM's callback was dropped and numba failed with RuntimeError("no compiled object yet"):
  exit 1 with a traceback instead of 130. Before: this program printed that traceback."""
  proc = subprocess.run([sys.executable, "-c", _CTRL_C_IN_A_CALLBACK], capture_output=True,
                        text=True, env=repo_env(), timeout=120)
  assert proc.returncode == 130 and proc.stderr.strip() == "interrupted: stopped", proc.stderr


def test_an_error_without_a_ctrl_c_is_raised(capsys):
  """The converse: an exception with no Ctrl-C before it keeps its traceback."""
  import pytest
  from lrf_jax.cli import interrupt

  @interrupt.interruptible("test")
  def main() -> int:
    raise RuntimeError("a real failure")

  with pytest.raises(RuntimeError, match="a real failure"):
    main()
  assert "interrupted" not in capsys.readouterr().err


def test_a_ctrl_c_during_a_numba_compile_is_raised_when_the_compile_ends(capsys):
  """Seen in CI: a Ctrl-C raised inside LLVM's callbacks left numba without its object code
  (a RuntimeError, once a crash: exit -11). The handler now waits for the compile to end (the
  "numba:compile" events count it), then the KeyboardInterrupt comes."""
  import signal
  import types
  from lrf_jax import compilation_cache
  from lrf_jax.cli import interrupt
  listener = compilation_cache._numba_listener()
  event = types.SimpleNamespace(data={})
  steps = []

  @interrupt.interruptible("test")
  def main() -> int:
    listener.on_start(event)  # a compile starts
    try:
      os.kill(os.getpid(), signal.SIGINT)
      t0 = time.monotonic()
      while time.monotonic() - t0 < 0.3:  # bytecodes run: the handler ran and did not raise
        pass
      steps.append("compiled")
    finally:
      listener.on_end(event)  # the compile ends: SIGINT is sent again
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
      time.sleep(0.01)
    steps.append("went on")
    return 0

  assert main() == interrupt.INTERRUPTED
  assert steps == ["compiled"] and not compilation_cache.numba_compiling()
  assert capsys.readouterr().err.startswith("interrupted: test")
