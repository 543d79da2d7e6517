"""Console-script entry points (`lrf-register`, `lrf-frames`, `lrf-batch`): run a CLI's `main` and leave.

A process that has used JAX and numba spends about half a second in the interpreter's teardown
(destroying the XLA runtime, its thread pools and every module) after the answer is written;
the commands flush their output and end with `os._exit` instead. Nothing is lost: the outputs
are closed files and flushed streams, and JAX's and numba's on-disk caches are written when a
function is compiled, not at exit. Calling `main()` from Python (as the tests do) is unchanged.
"""

from __future__ import annotations

import functools
import os
import sys
from typing import Any, NoReturn, TypeVar
from collections.abc import Callable

# The exit code of a program stopped by Ctrl-C (SIGINT): 128 + 2, as a shell reports it.
INTERRUPTED = 130

_Main = TypeVar("_Main", bound=Callable[..., int])


def interruptible(note: str) -> Callable[[_Main], _Main]:
  """Decorate a CLI's `main(argv)`: Ctrl-C (KeyboardInterrupt) anywhere in it prints one line,
  `interrupted: <note>`, on stderr and returns `INTERRUPTED` (130) instead of a traceback. Every
  output is written atomically (`lrf_jax.io.atomic`), so an interrupted program leaves no
  partial file."""
  def wrap(main: _Main) -> _Main:
    @functools.wraps(main)
    def run(*args: Any, **kwargs: Any) -> int:
      try:
        return main(*args, **kwargs)
      except Exception as e:  # noqa: BLE001 -- re-raised unless Ctrl-C caused it
        if not caused_by_interrupt(e):
          raise
      except KeyboardInterrupt:
        pass
      print(f"interrupted: {note}", file=sys.stderr, flush=True)
      return INTERRUPTED
    return run  # type: ignore[return-value]
  return wrap


def caused_by_interrupt(error: BaseException) -> bool:
  """Whether a KeyboardInterrupt is in `error`'s chain of causes: Ctrl-C inside a numba
  dispatcher surfaces as a `SystemError` ("returned a result with an exception set") raised from
  the KeyboardInterrupt."""
  seen: set[int] = set()
  e: BaseException | None = error
  while e is not None and id(e) not in seen:
    if isinstance(e, KeyboardInterrupt):
      return True
    seen.add(id(e))
    e = e.__cause__ or e.__context__
  return False


def run(main: Callable[[], int]) -> NoReturn:
  """Call `main()`, flush stdout and stderr, and end the process with its return code."""
  try:
    rc = main()
  except SystemExit as e:  # argparse's --help and usage errors
    rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    if not isinstance(e.code, (int, type(None))):
      print(e.code, file=sys.stderr)
  sys.stdout.flush()
  sys.stderr.flush()
  os._exit(int(rc or 0))


def register() -> NoReturn:
  """`lrf-register`: `lrf_jax.cli.register.main`."""
  from lrf_jax.cli.register import main
  run(main)


def batch() -> NoReturn:
  """`lrf-batch`: `lrf_jax.cli.batch.main`."""
  from lrf_jax.cli.batch import main
  run(main)


def frames() -> NoReturn:
  """`lrf-frames`: `lrf_jax.cli.frames.main`."""
  from lrf_jax.cli.frames import main
  run(main)
