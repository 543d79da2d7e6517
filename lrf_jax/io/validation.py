"""Checks shared by the readers: every bad input becomes a ValueError that names the file,
the field and what was expected versus found.

Message format (one line): ``"<file>: <field>: expected <expected>, found <found>"``; the
coordinates are checked by the package's one cloud check (`lrf_jax.checks.validate_cloud`,
``"<file>: <field>: expected <expected>, got <found>"``).
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from lrf_jax.checks import MAX_COORDINATE, validate_cloud
from lrf_jax.extras import MissingExtraError
from lrf_jax.io.atomic import loop_problem

# A pose's rotation block must satisfy |RᵀR - I| <= atol and |det R - 1| <= atol. The real
# ground-truth files are written with 6 decimals (worst case in the shipped data: 6.4e-6).
RIGID_ATOL = 1e-4


def bad_input(source: object, field: str, expected: str, found: str) -> ValueError:
  """Builds the ValueError every reader raises: file, field, expected and found.

  Args:
    source: the file (path) or a description of the in-memory input.
    field: the element / property / line that is wrong, e.g. ``"element 'vertex'"``.
    expected: what a valid file holds there.
    found: what this file holds there.

  Returns:
    A ValueError (to be raised by the caller).
  """
  return ValueError(f"{source}: {field}: expected {expected}, found {found}")


class SymlinkLoopError(OSError, ValueError):
  """A path that cannot be looked up because a symbolic link on it leads back to itself (ELOOP).

  Both an `OSError` (errno ELOOP, `filename` the path as given) and a `ValueError` (a bad input,
  as every reader raises), as `io.UnsupportedOperation` is both; `str()` is the one-line
  message, e.g. "scan.ply: file: expected a readable file, found a symbolic link loop (ELOOP:
  too many levels of symbolic links)".
  """

  def __init__(self, path: str | os.PathLike, problem: str):
    super().__init__(errno.ELOOP, os.strerror(errno.ELOOP), os.fspath(path))
    found = problem.removeprefix("is ")
    if found.startswith("goes through "):
      found = "a path that " + found
    self.message = str(bad_input(os.fspath(path), "file", "a readable file", found))

  def __str__(self) -> str:
    return self.message


# The extra that installs the optional readers (`pyproject.toml`), and what it holds.
FORMATS_EXTRA = "formats"
FORMATS_PACKAGES = "laspy[lazrs], pye57"


class MissingReaderError(MissingExtraError, ValueError):
  """A file this install cannot read: its reader's package (`FORMATS_EXTRA`) is not installed.

  Both a `lrf_jax.extras.MissingExtraError` (an ImportError naming the extra) and a `ValueError`
  (an input that cannot be read, as every reader raises, so that the command lines report it as
  one `error:` line); e.g. "scan.laz: reading .laz needs laspy[lazrs], which is not installed:
  pip install 'lrf_jax[formats]' (the 'formats' extra: laspy[lazrs], pye57)".
  """


def missing_reader(source: object, suffix: str, package: str,
                   module: str | None = None) -> MissingReaderError:
  """The error to raise (from the ImportError) when reading `source`, a `suffix` file, needs
  `package` (as pip names it) and `module` is not installed.

  Returns:
    A `MissingReaderError` naming the file, the package and the extra's install command.
  """
  return MissingReaderError(
      f"{source}: reading {suffix} needs {package}, which is not installed: pip install "
      f"'lrf_jax[{FORMATS_EXTRA}]' (the '{FORMATS_EXTRA}' extra: {FORMATS_PACKAGES})",
      name=module)


def file_problem(path: str | os.PathLike) -> str | None:
  """Why `path` cannot be read as a file, without opening it (None: a regular file): "no such
  file", "is a directory, not a file", "is not a regular file (...)", or a symbolic link loop
  (`lrf_jax.io.atomic.loop_problem`). The message does not repeat the path."""
  loop = loop_problem(path)
  if loop:
    return loop
  p = Path(path)
  if p.is_file():
    return None
  if p.is_dir():
    return "is a directory, not a file"
  if p.exists():  # a FIFO, a socket, a device: reading one may wait forever or never end
    return "is not a regular file (a FIFO, a socket or a device)"
  return "no such file"


def require_file(path: str | os.PathLike) -> Path:
  """Returns `path` as a Path, or raises FileNotFoundError naming it.

  Args:
    path: a file path.

  Returns:
    The path.

  Raises:
    FileNotFoundError: `path` does not exist or is not a regular file (the message says which).
    SymlinkLoopError: `path` is, or goes through, a symbolic link loop (ELOOP; a ValueError and
      an OSError naming `path` as given).
    ValueError: the file exists but cannot be opened for reading (e.g. no read permission).
  """
  if not os.fspath(path):  # Path("") is ".", the working directory
    raise FileNotFoundError("'': an empty path, not a file")
  p = Path(path)
  what = file_problem(p)
  if what and "symbolic link loop" in what:
    raise SymlinkLoopError(path, what)
  if what:
    raise FileNotFoundError(f"{p}: {what}")
  try:  # permissions and the like: a ValueError naming the file, as for any bad file
    with open(p, "rb"):
      pass
  except OSError as e:
    raise unreadable(p, e) from e
  return p


def unreadable(p: object, error: OSError) -> ValueError:
  """The ValueError of a file that exists but cannot be read (`error` from the OS)."""
  return bad_input(p, "file", "a readable file",
                   f"{type(error).__name__}: {error.strerror or error}")


def check_points(points: np.ndarray, source: object, field: str = "points",
                 columns: int = 3) -> np.ndarray:
  """Validates an (n, columns) coordinate array: non-empty, 2-D, finite.

  Args:
    points: array-like, expected shape (n, columns), n >= 1.
    source: the file or input the array came from (used in messages).
    field: what the array is, e.g. ``"element 'vertex' x/y/z"``.
    columns: the expected number of columns (3 for points and normals).

  Returns:
    The array as a C-contiguous (n, columns) float64 copy or view.

  Raises:
    ValueError: wrong shape, zero rows, or non-finite values (the message gives their count
      and the first offending row): `lrf_jax.checks.validate_cloud`, named by file and field.
  """
  return np.ascontiguousarray(validate_cloud(points, f"{source}: {field}", columns))


def check_rigid(transform: np.ndarray, source: object, field: str = "transform",
                atol: float = RIGID_ATOL, project: float = 0.0) -> np.ndarray:
  """Validates a (4, 4) rigid transform [R t; 0 0 0 1] with R a proper rotation.

  A rotation block off orthonormal by more than `atol` but at most `project` (|RᵀR - I|, max
  entry) is replaced by the nearest rotation (`nearest_rotation`: the orthogonal polar factor,
  in the Frobenius norm), with a `ProjectedRotation` warning that gives the figure. Published ground
  truths (3DMatch's gt.log) are printed with a few digits and reach 5e-4.

  Args:
    transform: array-like, expected shape (4, 4).
    source: the file or input the matrix came from (used in messages).
    field: what the matrix is, e.g. ``"pose of bun045.ply"``.
    atol: tolerance on |RᵀR - I| (max entry), |det R - 1| and the last row.
    project: a rotation block within this of orthonormal is projected to the nearest rotation
      (0: none is; the matrix must be within `atol`).

  Returns:
    The matrix as a (4, 4) float64 array (unchanged values, or with its rotation block
    projected).

  Raises:
    ValueError: wrong shape, non-finite entries, last row not (0, 0, 0, 1), a translation beyond
      `lrf_jax.checks.MAX_COORDINATE` in some coordinate, R not orthonormal (beyond `atol` and
      `project`; the message gives the figure), or det R != +1 (a reflection).
  """
  t = np.asarray(transform, dtype=np.float64)
  if t.shape != (4, 4):
    found = "x".join(map(str, t.shape)) if t.ndim == 2 else f"shape {t.shape}"
    raise bad_input(source, field, "a 4x4 matrix", f"a {found} matrix")
  if not np.isfinite(t).all():
    raise bad_input(source, field, "finite entries", "NaN/inf")
  if np.abs(t[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > atol:
    raise bad_input(source, field, "last row 0 0 0 1", f"last row {t[3].tolist()}")
  shift = float(np.abs(t[:3, 3]).max())
  if shift > MAX_COORDINATE:
    raise bad_input(source, field, f"a translation of magnitude at most {MAX_COORDINATE:.0e} (the "
                    "largest coordinate a cloud may hold: it would move the cloud beyond it)",
                    f"translation {t[:3, 3].tolist()} (magnitude {shift:.3e})")
  r = t[:3, :3]
  ortho = rigid_deviation(t)
  limit = max(atol, project)
  if ortho > limit:
    raise bad_input(source, field, f"an orthonormal rotation block (|RᵀR - I| <= {limit:g})",
                    f"|RᵀR - I| = {ortho:.3g} (not a rigid transform)")
  det = float(np.linalg.det(r))
  if abs(det - 1.0) > limit or det < 0:
    raise bad_input(source, field, f"det R = +1 (within {limit:g})",
                    f"det R = {det:.6g}" + (" (a reflection)" if det < 0 else ""))
  if ortho > atol:
    import warnings
    warnings.warn(ProjectedRotation(
        f"{source}: {field}: its rotation block is {ortho:.3g} off orthonormal (|RᵀR - I|); "
        "projected to the nearest rotation"), stacklevel=2)
    t = t.copy()
    t[:3, :3] = nearest_rotation(r)
    t[3] = (0.0, 0.0, 0.0, 1.0)
  return t


class ProjectedRotation(UserWarning):
  """A transform's rotation block was replaced by the nearest rotation (`check_rigid`'s
  `project`); the message gives how far off orthonormal it was."""


def rigid_deviation(transform: np.ndarray) -> float:
  """|RᵀR - I| (max entry) of a (4, 4) transform's rotation block: 0 for a rotation."""
  r = np.asarray(transform, np.float64)[:3, :3]
  return float(np.abs(r.T @ r - np.eye(3)).max())


def nearest_rotation(r: np.ndarray) -> np.ndarray:
  """The rotation nearest to a (3, 3) matrix in the Frobenius norm: U Vᵀ of its SVD U S Vᵀ,
  the last column of U negated where det(U Vᵀ) < 0 (Umeyama's correction)."""
  u, _, vt = np.linalg.svd(np.asarray(r, np.float64))
  d = np.sign(np.linalg.det(u @ vt)) or 1.0
  return u @ np.diag([1.0, 1.0, d]) @ vt


def check_normals(normals: np.ndarray, source: object, field: str = "normals",
                  n_points: int | None = None) -> np.ndarray:
  """Validates an (n, 3) normal array; a row with any NaN/inf becomes a NaN row.

  Files mark normals that could not be estimated with NaN (PCL does); such a row is a missing
  normal, not a bad point: it is kept, as a whole NaN row (the frames that need it come out
  invalid).

  Args:
    normals: array-like, expected shape (n, 3).
    source: the file or input the array came from (used in messages).
    field: what the array is, e.g. ``"element 'vertex' nx/ny/nz"``.
    n_points: the expected number of rows (the points'), if known.

  Returns:
    A C-contiguous (n, 3) float64 array: the values as stored, NaN rows where any entry was not
    finite.

  Raises:
    ValueError: wrong shape or (with `n_points`) a row count other than the points'.
  """
  arr = np.asarray(normals)
  if arr.ndim != 2 or arr.shape[1] != 3:
    raise bad_input(source, field, "an (n, 3) array", f"shape {arr.shape}")
  if n_points is not None and arr.shape[0] != n_points:
    raise bad_input(source, field, f"{n_points} rows (one per point)", f"{arr.shape[0]} rows")
  arr = np.array(arr, dtype=np.float64, order="C")  # a copy: rows are overwritten below
  arr[~np.isfinite(arr).all(axis=1)] = np.nan
  return arr
