"""Rigid poses: `.xf` 4x4 text, Stanford `.conf` (quaternions), 3DMatch/Redwood `.log`.

Every reader checks that what it returns is rigid: finite, last row (0, 0, 0, 1), R orthonormal
and det R = +1 within `atol` (default 1e-4; the shipped ground truths are good to ~1e-5).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lrf_jax.io.validation import RIGID_ATOL, bad_input, check_rigid, require_file


def quaternion_to_matrix(q: np.ndarray, *, source: object = "quaternion",
                         atol: float = RIGID_ATOL) -> np.ndarray:
  """The rotation matrix R(q) of a unit quaternion given as (qx, qy, qz, qw) (scalar last).

  R(q) rotates a vector v as q v q*, i.e. the usual Hamilton convention (the same as
  `scipy.spatial.transform.Rotation.from_quat`).

  Args:
    q: (4,) quaternion, scalar last. Its norm must be 1 within `atol` (it is then normalised).
    source: the file or input it came from (used in messages).
    atol: tolerance on | |q| - 1 |.

  Returns:
    (3, 3) float64 rotation matrix.

  Raises:
    ValueError: not 4 finite numbers, or not of unit norm.
  """
  q = np.asarray(q, dtype=np.float64)
  if q.shape != (4,) or not np.isfinite(q).all():
    raise bad_input(source, "quaternion", "4 finite numbers qx qy qz qw", repr(q.tolist()))
  norm = float(np.linalg.norm(q))
  if abs(norm - 1.0) > atol:
    raise bad_input(source, "quaternion", f"unit norm (within {atol:g})", f"norm {norm:.6g}")
  x, y, z, w = q / norm
  return np.array([
      [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ])


def _parse_rows(lines: list[str], source: object, field: str) -> np.ndarray:
  """Whitespace rows of numbers -> (rows, cols) float64, requiring a rectangular 4x4."""
  try:
    rows = [[float(t) for t in line.split()] for line in lines]
  except ValueError as e:
    raise bad_input(source, field, "numbers", f"a non-numeric token ({e})") from e
  widths = sorted({len(r) for r in rows})
  if len(rows) != 4 or widths != [4]:
    if not rows:
      found = "no numbers"
    elif len(widths) == 1:
      found = f"a {len(rows)}x{widths[0]} matrix"
    else:
      found = f"{len(rows)} rows of {'/'.join(map(str, widths))} values"
    raise bad_input(source, field, "a 4x4 matrix", found)
  return np.array(rows)


def read_xf(path: str | os.PathLike, *, atol: float = RIGID_ATOL,
            project: float = 0.0) -> np.ndarray:
  """Reads a `.xf` file: a rigid 4x4 matrix as 4 whitespace-separated text rows.

  In the Bologna and UWA ground truths the matrix maps model points into the scene:
  ``p_scene = T[:3, :3] @ p_model + T[:3, 3]``.

  Args:
    path: the `.xf` file.
    atol: rigidity tolerance (see module docstring).
    project: a rotation block within this of orthonormal is projected to the nearest rotation
      (`lrf_jax.io.validation.check_rigid`).

  Returns:
    (4, 4) float64 matrix.

  Raises:
    FileNotFoundError: missing file.
    ValueError: not a 4x4 numeric matrix (e.g. 3x4), or not rigid.
  """
  p = require_file(path)
  lines = [line for line in p.read_text(errors="replace").splitlines() if line.strip()]
  return check_rigid(_parse_rows(lines, p, "matrix"), p, "matrix", atol, project)


def format_matrix(matrix: np.ndarray, digits: int = 9) -> str:
  """A matrix as text, a row per line, `digits` significant digits (`lrf-register --out`'s
  layout; `numpy.loadtxt` reads it back). No trailing newline.

  Args:
    matrix: (r, c) numbers, e.g. a (4, 4) transform.
    digits: significant digits of each number.
  """
  return "\n".join(" ".join(f"{v:.{digits}g}" for v in row) for row in np.asarray(matrix))


def write_xf(path: str | os.PathLike, transform: np.ndarray) -> Path:
  """Writes a rigid (4, 4) matrix as a `.xf` text file (full float64 precision).

  Args:
    path: destination file.
    transform: (4, 4) rigid transform.

  Returns:
    The path written.
  """
  t = check_rigid(transform, "write_xf", "transform")
  out = Path(path)
  out.write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in t) + "\n")
  return out


def read_stanford_conf(path: str | os.PathLike, *,
                       atol: float = RIGID_ATOL) -> dict[str, np.ndarray]:
  """Reads a Stanford scan-alignment `.conf` file (e.g. the bunny's `bun.conf`).

  Lines ``bmesh FILE tx ty tz qx qy qz qw`` (or ``mesh ...``) give the pose of each scan.
  The world point of a scan point p is ``R(q)ᵀ p + t`` -- the *conjugate* rotation. This is
  what aligns the bunny scans (>= 36 % of points within 1 mm for neighboring scans, against
  <= 2 % with ``R(q) p + t``); tests/test_datasets.py checks it on the data. ``camera`` lines and
  blank lines are skipped.

  Args:
    path: the `.conf` file.
    atol: tolerance on the quaternion's unit norm.

  Returns:
    {scan file name: (4, 4) float64 world-from-scan matrix [R(q)ᵀ t; 0 0 0 1]}, in file order.

  Raises:
    FileNotFoundError: missing file.
    ValueError: a line with the wrong number of values, a non-unit or non-finite quaternion,
      an unknown keyword, a repeated scan, or no scan at all.
  """
  p = require_file(path)
  poses: dict[str, np.ndarray] = {}
  for number, line in enumerate(p.read_text(errors="replace").splitlines(), start=1):
    tokens = line.split()
    if not tokens or tokens[0].startswith("#") or tokens[0] == "camera":
      continue
    field = f"line {number}"
    if tokens[0] not in ("bmesh", "mesh"):
      raise bad_input(p, field, "'bmesh FILE tx ty tz qx qy qz qw' or 'camera ...'",
                      repr(line.strip()))
    if len(tokens) != 9:
      raise bad_input(p, field, "9 tokens: bmesh FILE tx ty tz qx qy qz qw",
                      f"{len(tokens)} tokens")
    name = tokens[1]
    try:
      values = np.array([float(t) for t in tokens[2:]])
    except ValueError as e:
      raise bad_input(p, field, "7 numbers after the file name", repr(line.strip())) from e
    if name in poses:
      raise bad_input(p, field, "each scan once", f"{name} again")
    if not np.isfinite(values[:3]).all():
      raise bad_input(p, field, "a finite translation", repr(values[:3].tolist()))
    rotation = quaternion_to_matrix(values[3:], source=f"{p}: {field}", atol=atol).T  # conjugate
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = values[:3]
    poses[name] = pose
  if not poses:
    raise bad_input(p, "lines", "at least one 'bmesh' line", "none")
  return poses


class LogEntry(NamedTuple):
  """One 3DMatch/Redwood `.log` record.

  Attributes:
    i: first fragment id.
    j: second fragment id.
    n: the third header number (the number of fragments in the scene for gt.log).
    transform: (4, 4) float64 matrix, exactly as stored (not inverted).
  """

  i: int
  j: int
  n: int
  transform: np.ndarray


def read_3dmatch_log(path: str | os.PathLike, *, atol: float = RIGID_ATOL,
                     project: float = 0.0) -> list[LogEntry]:
  """Reads a 3DMatch / Redwood trajectory `.log` file (e.g. `gt.log`).

  The file is a sequence of 5-line records: a header ``i j n`` followed by 4 rows of a 4x4
  matrix. The matrix is returned as stored; see the benchmark's documentation for the
  direction it maps (between fragments i and j).

  Args:
    path: the `.log` file.
    atol: rigidity tolerance (see module docstring).
    project: a rotation block within this of orthonormal is projected to the nearest rotation
      (`lrf_jax.io.validation.check_rigid`).

  Returns:
    The records in file order.

  Raises:
    FileNotFoundError: missing file.
    ValueError: a record header that is not three integers, a truncated record, a matrix that
      is not 4x4 or not rigid, or no record.
  """
  p = require_file(path)
  lines = [line for line in p.read_text(errors="replace").splitlines() if line.strip()]
  if len(lines) % 5:
    raise bad_input(p, "records", "a multiple of 5 non-empty lines (header 'i j n' + 4 rows)",
                    f"{len(lines)} lines (truncated record?)")
  if not lines:
    raise bad_input(p, "records", "at least one record", "an empty file")
  entries = []
  for k in range(0, len(lines), 5):
    field = f"record {k // 5} (line {k + 1})"
    head = lines[k].split()
    try:
      i, j, n = (int(t) for t in head)
    except ValueError as e:
      raise bad_input(p, f"{field} header", "three integers 'i j n'", repr(lines[k])) from e
    matrix = _parse_rows(lines[k + 1:k + 5], p, f"{field} matrix")
    entries.append(LogEntry(i, j, n, check_rigid(matrix, p, f"{field} matrix", atol, project)))
  return entries
