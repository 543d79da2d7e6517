"""Whitespace text clouds: one point per line, ``x y z [more columns ...]``, optionally .gz."""

from __future__ import annotations

import os
import warnings
import zlib

import numpy as np

from lrf_jax.io.cloud import Cloud
from lrf_jax.io.validation import bad_input, check_points, require_file


def read_xyz(path: str | os.PathLike) -> Cloud:
  """Reads a whitespace-separated text cloud (`.xyz`, `.txt`, ..., or the same gzip'ed).

  Each non-comment line holds at least three numbers; the first three are x y z, further
  columns are ignored. Lines starting with ``#`` are comments. A `.gz` suffix is decompressed
  transparently (the UWA 3D modelling views are stored this way).

  Args:
    path: the text file.

  Returns:
    A Cloud with (n, 3) float64 points (no faces, no normals).

  Raises:
    FileNotFoundError: missing file.
    ValueError: a non-numeric token, fewer than 3 columns, rows of different lengths, no
      points, or NaN/inf coordinates (the message names the file and the line).
  """
  p = require_file(path)
  try:
    with warnings.catch_warnings():
      warnings.simplefilter("ignore", UserWarning)  # "input contained no data": checked below
      arr = np.loadtxt(p, dtype=np.float64, comments="#", ndmin=2)
  except ValueError as e:
    # numpy's message names the line ("... at row 7" / "could not convert ... at row 3").
    raise bad_input(p, "rows", "numeric 'x y z [...]' rows with the same number of columns",
                    str(e)) from e
  except (OSError, EOFError, zlib.error) as e:  # e.g. a truncated or corrupt .gz
    raise bad_input(p, "file", "readable text (gzip if .gz)", f"{type(e).__name__}: {e}") from e
  if arr.shape[0] == 0:
    raise bad_input(p, "points", "at least one 'x y z' row", "an empty cloud (0 points)")
  if arr.shape[1] < 3:
    raise bad_input(p, "columns", "at least 3 columns (x y z)", f"{arr.shape[1]} columns")
  return Cloud(check_points(arr[:, :3], p, "x/y/z columns"), None, None, p)
