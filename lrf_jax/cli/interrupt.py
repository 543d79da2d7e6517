"""Ctrl-C in the command-line programs: one line and exit code 130, never a traceback.

`interruptible` decorates a program's `main(argv)` (lrf-register, lrf-frames, multiway,
train.py, evaluate.py). A module of its own: the programs import it, and `cli.console` imports
the programs.
"""

from __future__ import annotations

import functools
import os
import signal
import sys
import threading
from typing import Any, TypeVar
from collections.abc import Callable

from lrf_jax import compilation_cache
from lrf_jax.io.atomic import CTRL_C_RECEIVED, caused_by_interrupt

# The exit code of a program stopped by Ctrl-C (SIGINT): 128 + 2, as a shell reports it.
INTERRUPTED = 130

_Main = TypeVar("_Main", bound=Callable[..., int])


class _Program:
  """Whether an `interruptible` program runs in this process (a nested one, a program calling
  another's `main`, counts as the outer one). Its Ctrl-C handlers set `CTRL_C_RECEIVED`."""
  running = False


def interruptible(note: str) -> Callable[[_Main], _Main]:
  """Decorate a CLI's `main(argv)`: Ctrl-C (KeyboardInterrupt) anywhere in it prints one line,
  `interrupted: <note>`, on stderr and returns `INTERRUPTED` (130) instead of a traceback. An
  exception raised after a Ctrl-C counts as the Ctrl-C's consequence, whether or not it names
  the KeyboardInterrupt (`caused_by_interrupt`). Every output is written atomically
  (`lrf_jax.io.atomic`), so an interrupted program leaves no partial file."""
  def wrap(main: _Main) -> _Main:
    @functools.wraps(main)
    def run(*args: Any, **kwargs: Any) -> int:
      outer = _Program.running
      if not outer:
        CTRL_C_RECEIVED.clear()
      _Program.running = True
      redeliver_lost_interrupts()
      finished = threading.Event()
      previous = _watch_interrupts(finished)
      try:
        return main(*args, **kwargs)
      except Exception as e:  # noqa: BLE001 -- re-raised unless Ctrl-C caused it
        if not caused_by_interrupt(e):
          raise
      except KeyboardInterrupt:
        pass
      finally:
        finished.set()
        _Program.running = outer
        if not outer:
          CTRL_C_RECEIVED.clear()  # a later error in this process is not this Ctrl-C's
        if previous is not None:
          signal.signal(signal.SIGINT, previous)
      print(f"interrupted: {note}", file=sys.stderr, flush=True)
      return INTERRUPTED
    return run  # type: ignore[return-value]
  return wrap


# Seconds after a Ctrl-C that the program must have stopped by; else the Ctrl-C was swallowed
# (a library's `except BaseException`, a C++ callback) and SIGINT is sent again.
REDELIVER_AFTER_S = 10.0


def _watch_interrupts(finished: threading.Event) -> Any:
  """On the main thread, a SIGINT handler that raises KeyboardInterrupt as Python's does (but
  while numba compiles, when the compile ends: `compilation_cache.defer_interrupt`) and
  sends SIGINT again `REDELIVER_AFTER_S` seconds later unless `finished` is set by then (the
  program returned): a Ctrl-C is never lost, whatever swallowed the first KeyboardInterrupt.
  Returns the previous handler (None off the main thread, where nothing is installed)."""
  if threading.current_thread() is not threading.main_thread():
    return None

  def resend() -> None:
    if not finished.is_set():
      os.kill(os.getpid(), signal.SIGINT)

  def handler(signum: int, frame: Any) -> None:
    CTRL_C_RECEIVED.set()
    if compilation_cache.numba_compiling():  # never inside LLVM's callbacks: after the compile
      compilation_cache.defer_interrupt()
      return
    timer = threading.Timer(REDELIVER_AFTER_S, resend)
    timer.daemon = True
    timer.start()
    raise KeyboardInterrupt

  return signal.signal(signal.SIGINT, handler)


def redeliver_lost_interrupts() -> None:
  """Make a Ctrl-C that Python had to drop count (idempotent).

  A KeyboardInterrupt raised while Python runs a finalizer or a garbage-collection callback
  (JAX's `_xla_gc_callback`, a `__del__`) cannot propagate: Python prints "Exception ignored
  in ..." and goes on, and the Ctrl-C is lost (train.py went on training, seen in the suite).
  The hook installed here sends SIGINT again from a helper thread a moment later, when the main
  thread is back in ordinary code, if an `interruptible` program is still running then; other
  unraisable exceptions keep Python's own report."""
  if getattr(sys.unraisablehook, "_lrf_jax_redeliver", False):
    return
  previous = sys.unraisablehook

  def resend() -> None:
    if _Program.running:  # else the program has stopped: nothing is left to interrupt
      os.kill(os.getpid(), signal.SIGINT)

  def hook(unraisable: Any) -> None:
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and \
        threading.current_thread() is threading.main_thread():
      CTRL_C_RECEIVED.set()
      timer = threading.Timer(0.05, resend)
      timer.daemon = True
      timer.start()
      return
    previous(unraisable)

  hook._lrf_jax_redeliver = True  # type: ignore[attr-defined]
  sys.unraisablehook = hook


def exit_with(rc: int) -> None:
  """End a script (`python train.py`) with `rc`. After Ctrl-C the interpreter's teardown would
  run beside JAX's, XLA's and orbax's threads stopped mid-work (a segmentation fault, seen
  after the `interrupted:` line): the streams are flushed and the process ends at once
  (`os._exit`); otherwise `sys.exit(rc)`."""
  if rc == INTERRUPTED:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)
  sys.exit(rc)
