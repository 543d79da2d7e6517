"""Console-script entry points (`lrf-register`, `lrf-frames`, `lrf-batch`, `lrf-compile`): run a CLI's `main` and leave.

A process that has used JAX and numba spends about half a second in the interpreter's teardown
(destroying the XLA runtime, its thread pools and every module) after the answer is written;
the commands flush their output and end with `os._exit` instead. Nothing is lost: the outputs
are closed files and flushed streams, and JAX's and numba's on-disk caches are written when a
function is compiled, not at exit. Calling `main()` from Python (as the tests do) is unchanged.

The exit codes are `lrf_jax.cli.exits`'.
"""

from __future__ import annotations

import os
import sys
from typing import NoReturn
from collections.abc import Callable

def run(main: Callable[[], int]) -> NoReturn:
  """Call `main()`, flush stdout and stderr, and end the process with its return code; Ctrl-C
  before the program's own handler (while its modules are imported) is one line and 130."""
  try:
    rc = main()
  except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    rc = 130
  except SystemExit as e:  # argparse's --help and usage errors
    rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    if not isinstance(e.code, (int, type(None))):
      print(e.code, file=sys.stderr)
  sys.stdout.flush()
  sys.stderr.flush()
  os._exit(int(rc or 0))


def register() -> NoReturn:
  """`lrf-register`: `lrf_jax.cli.register.main`."""
  run(_register_main)


def _register_main() -> int:
  from lrf_jax.cli.register import main  # inside run: Ctrl-C while importing is handled
  return main()


def batch() -> NoReturn:
  """`lrf-batch`: `lrf_jax.cli.batch.main`."""
  run(_batch_main)


def _batch_main() -> int:
  from lrf_jax.cli.batch import main  # inside run: Ctrl-C while importing is handled
  return main()


def compile_all() -> NoReturn:
  """`lrf-compile`: `lrf_jax.cli.compile.main`."""
  run(_compile_all_main)


def _compile_all_main() -> int:
  from lrf_jax.cli.compile import main  # inside run: Ctrl-C while importing is handled
  return main()


def frames() -> NoReturn:
  """`lrf-frames`: `lrf_jax.cli.frames.main`."""
  run(_frames_main)


def _frames_main() -> int:
  from lrf_jax.cli.frames import main  # inside run: Ctrl-C while importing is handled
  return main()
