"""The exit codes of every console script, and the two helpers that print an `error:` line and
return one.

The codes (`EXIT_CODES`; the table in docs/api/cli.md):

  0    done (lrf-register: the verdict is "success")
  1    an unexpected error (a bug: Python's traceback)
  2    a bad command line, or an input or output path refused before any work (a malformed or
       missing input, an output that is a folder, a device or a symbolic link loop)
  3    finished, but the result is not trusted: lrf-register's "not sure", scans left out of a
       multiway model, failed items of lrf-batch, a group lrf-compile could not compile
  74   an output could not be written (a full disk, a read-only file system, no permission, an
       I/O error), found before the work or while writing; the earlier file is untouched
       (`EX_IOERR` of sysexits.h)
  130  interrupted (Ctrl-C)

`refuse` and `write_failed` print the one `error:` line and return the code.
"""

from __future__ import annotations

import sys

__all__ = ["EXIT_BUG", "EXIT_CODES", "EXIT_INTERRUPTED", "EXIT_NOT_SURE", "EXIT_OK", "EXIT_USAGE",
           "EXIT_WRITE_FAILED", "refuse", "write_failed"]

EXIT_OK = 0
EXIT_BUG = 1
EXIT_USAGE = 2
EXIT_NOT_SURE = 3
EXIT_WRITE_FAILED = 74  # sysexits.h's EX_IOERR
EXIT_INTERRUPTED = 130  # `lrf_jax.cli.interrupt.INTERRUPTED`: 128 + SIGINT
EXIT_CODES: dict[int, str] = {
    EXIT_OK: "done",
    EXIT_BUG: "an unexpected error (a bug: Python's traceback)",
    EXIT_USAGE: "a bad command line, or an input or output path refused before any work",
    EXIT_NOT_SURE: "finished, but the result is not trusted (not sure, left out, failed items)",
    EXIT_WRITE_FAILED: "an output could not be written (full disk, read-only file system, no "
                       "permission, I/O error)",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C)",
}


def refuse(problem: str) -> int:
  """Print `error: <problem>` on stderr; the exit code of a problem found before any work:
  `EXIT_WRITE_FAILED` for an output folder the system will not let us write into (a problem
  whose `io_error` is true, `lrf_jax.io.atomic.output_problem`), else `EXIT_USAGE`."""
  print(f"error: {problem}", file=sys.stderr)
  return EXIT_WRITE_FAILED if getattr(problem, "io_error", False) else EXIT_USAGE


def write_failed(error: BaseException, note: str = "") -> int:
  """Print `error: <error><note>` on stderr for an output that could not be written (a
  `lrf_jax.io.atomic.WriteError`); returns `EXIT_WRITE_FAILED`."""
  print(f"error: {error}{note}", file=sys.stderr)
  return EXIT_WRITE_FAILED
