"""Every check of an argument the package is given, in one message style.

A bad argument raises a `ValueError` whose message reads ``"<name>: expected <what is accepted>,
got <what was given>"`` (a few say more: the first bad row, the supported range), `<name>` being
the argument's name as the caller wrote it (or, for a reader, the file and the field). The
checks return the value in the form the package computes with (float64 points, int64 indices),
so that a caller checks each argument once and hands the result inward.

The clouds themselves are checked once, by `lrf_jax.geometry.cloud.CheckedCloud`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# The support radii the frames' arithmetic supports (cloud units), and how far from the origin,
# in support radii, a cloud may reach (float64 offsets q - p keep ~4 significant digits more
# than the float32 frames need up to there).
MIN_SCALE = 1e-30
MAX_SCALE = 1e30
MAX_RADII_FROM_ORIGIN = 1e12
# The largest coordinate magnitude a cloud may hold: no supported scale reaches further (a support
# radius of at most MAX_SCALE, within MAX_RADII_FROM_ORIGIN radii of the origin). Squares of such
# coordinates, and their sums over any cloud, stay far inside float64's range (1.8e308), which
# squared differences leave (overflow to inf) from about FLOAT64_SQUARE_LIMIT on; the float32
# arithmetic of the frames only ever sees offsets scaled by the support radius.
MAX_COORDINATE = MAX_SCALE * MAX_RADII_FROM_ORIGIN
FLOAT64_SQUARE_LIMIT = float(np.sqrt(np.finfo(np.float64).max))


def validate_cloud(points: np.ndarray, name: str = "points", columns: int = 3) -> np.ndarray:
  """Check that `points` is a non-empty (n, 3) array of finite floats no larger in magnitude
  than `MAX_COORDINATE` and return it as float64 (`columns`: another row length, for a reader's
  other coordinate arrays).

  Raises:
    ValueError: naming what was wrong and what was expected (for coordinates too large, the
      largest magnitude found and the limit: `coordinate_problem`).
  """
  try:
    arr = np.asarray(points)
  except (TypeError, ValueError):  # e.g. rows of different lengths
    raise ValueError(f"{name}: expected a numeric (n, {columns}) array of floats, got "
                     f"{type(points).__name__} {points!r:.80} (not an array)") from None
  if arr.dtype.kind not in "fiu":
    raise ValueError(f"{name}: expected a numeric (n, {columns}) array of floats, got dtype "
                     f"{arr.dtype}")
  if arr.ndim != 2 or arr.shape[1] != columns:
    raise ValueError(f"{name}: expected shape (n, {columns}), got {arr.shape}")
  if arr.shape[0] == 0:
    raise ValueError(f"{name}: expected at least one point, got an empty cloud (shape {arr.shape})")
  arr = arr.astype(np.float64, copy=False)
  # two flat passes (the per-row reductions below are several times slower); NaN fails both tests
  if -MAX_COORDINATE <= arr.min() and arr.max() <= MAX_COORDINATE:
    return arr
  bad = ~np.isfinite(arr).all(axis=1)
  if bad.any():
    first = int(np.flatnonzero(bad)[0])
    raise ValueError(
        f"{name}: expected finite coordinates, got {int(bad.sum())} non-finite point(s) (NaN or "
        f"inf; first at row {first}: {arr[first].tolist()})")
  problem = coordinate_problem(arr, name)
  if problem:
    raise ValueError(problem)
  return arr


def coordinate_problem(points: np.ndarray, name: str = "points") -> str | None:
  """The message for finite coordinates beyond `MAX_COORDINATE` in magnitude (None: none): the
  count, the largest magnitude found, the first such row, the limit and why, computed without
  squaring anything (the magnitudes themselves never overflow).

  Args:
    points: an (n, k) array of finite floats.
    name: the array as the caller names it (for a reader, the file and the field).
  """
  arr = np.asarray(points, np.float64)
  peak = np.abs(arr).max(axis=1) if arr.size else np.zeros(0)
  bad = peak > MAX_COORDINATE
  if not bad.any():
    return None
  first = int(np.flatnonzero(bad)[0])
  largest = float(peak.max())
  return (f"{name}: expected coordinates of magnitude at most {MAX_COORDINATE:.0e}, got "
          f"{int(bad.sum())} point(s) beyond it (largest magnitude {largest:.3e}; first at row "
          f"{first}: {arr[first].tolist()}): too large to compute with, since no supported scale "
          f"(a support radius of at most {MAX_SCALE:.0e}, within {MAX_RADII_FROM_ORIGIN:.0e} "
          "radii of the origin) reaches that far and squared distances overflow float64 to inf "
          f"from about {FLOAT64_SQUARE_LIMIT:.1e} on; rescale the cloud (e.g. to metres or "
          "millimetres)")


def validate_keypoints(keypoints: np.ndarray, n_points: int, name: str = "keypoints") -> np.ndarray:
  """Check that `keypoints` is a 1-D array of integer indices into a cloud of `n_points`."""
  try:
    kp = np.asarray(keypoints)
  except (TypeError, ValueError):  # e.g. nested lists of different lengths
    raise ValueError(f"{name}: expected a 1-D array of point indices, got "
                     f"{type(keypoints).__name__} {keypoints!r:.80} (not an array)") from None
  if kp.ndim != 1:
    raise ValueError(f"{name}: expected a 1-D array of point indices, got shape {kp.shape}")
  if kp.size and kp.dtype.kind not in "iu":
    raise ValueError(f"{name}: expected integer point indices, got dtype {kp.dtype}")
  # the range is checked in the input's own dtype: a uint64 above 2**63 must not wrap negative
  if kp.size and (kp.min() < 0 or kp.max() >= n_points):
    bad = kp[(kp < 0) | (kp >= n_points)][0]
    raise ValueError(
        f"{name}: index {int(bad)} is out of range; expected indices in [0, {n_points}) "
        f"for a cloud of {n_points} points")
  return kp.astype(np.int64)


def validate_radius(radius: float, name: str = "radius") -> float:
  """Check that the support radius is a positive finite number (not a string or bool)."""
  if isinstance(radius, (str, bytes, bool, np.bool_)):
    raise ValueError(f"{name}: expected a positive number, got {radius!r}")
  try:
    r = float(radius)
  except (TypeError, ValueError):
    raise ValueError(f"{name}: expected a positive number, got {radius!r}") from None
  if not np.isfinite(r) or r <= 0:
    raise ValueError(f"{name}: expected a positive finite number (cloud units), got {radius!r}")
  if not MIN_SCALE <= r <= MAX_SCALE:
    raise ValueError(f"{name}: {r:.6g} is outside the supported scale {MIN_SCALE:g} .. "
                     f"{MAX_SCALE:g}; rescale the cloud (frames do not depend on its unit)")
  return r


def validate_scale(max_abs: float, radius: float, name: str = "points") -> None:
  """Check that a cloud whose largest absolute coordinate is `max_abs` can be searched at
  `radius`: the radius within `MIN_SCALE` .. `MAX_SCALE` and the cloud within
  `MAX_RADII_FROM_ORIGIN` radii of the origin (beyond, offsets lose their precision and grid
  cell indices overflow).

  Raises:
    ValueError: naming `name` and the scale.
  """
  validate_radius(radius)
  if not max_abs <= MAX_RADII_FROM_ORIGIN * radius:
    raise ValueError(f"{name}: coordinates reach {max_abs:.6g}, more than "
                     f"{MAX_RADII_FROM_ORIGIN:g} support radii ({radius:.6g}) from the origin: "
                     "outside the supported scale; centre the cloud or use a larger radius")


def validate_faces(faces: object, n_points: int, name: str = "faces") -> np.ndarray:
  """Check that `faces` is an (f, 3) integer array of indices into `n_points` vertices.

  Returns:
    The faces as int64.
  """
  try:
    f = np.asarray(faces)
  except (TypeError, ValueError):  # e.g. rows of different lengths
    raise ValueError(f"{name}: expected an (f, 3) integer array of triangle vertex indices, got "
                     f"{type(faces).__name__} {faces!r:.80} (not an array)") from None
  if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
    raise ValueError(f"{name}: expected an (f, 3) integer array of triangle vertex indices, got "
                     f"shape {f.shape} and dtype {f.dtype}")
  f = f.astype(np.int64)
  if f.size and (f.min() < 0 or f.max() >= n_points):
    raise ValueError(f"{name}: indices must lie in [0, {n_points}), got [{f.min()}, {f.max()}]")
  return f


def validate_normals(normals: object, n_points: int, name: str = "normals") -> np.ndarray:
  """Check that `normals` is an (n_points, 3) array of real numbers. NaN rows are allowed: they
  mark missing normals, and the frames that need them come out invalid.

  Returns:
    The normals as an array (dtype unchanged).
  """
  try:
    nrm = np.asarray(normals)
  except (TypeError, ValueError):  # e.g. rows of different lengths
    nrm = np.empty(())  # reported as shape ()
  if nrm.shape != (n_points, 3):
    raise ValueError(f"{name}: expected shape {(n_points, 3)} (one per point), got {nrm.shape}")
  if nrm.dtype.kind not in "fiu":
    raise ValueError(f"{name}: expected real numbers, got dtype {nrm.dtype}")
  return nrm


# Seeds are integers in [0, MAX_SEED): JAX's keys take 32 bits (`jax.random.key(2**32 + 5)` is
# `jax.random.key(5)`, and 2**64 overflows), so a larger seed would repeat a smaller one.
MAX_SEED = 2**32


def validate_seed(seed: object, name: str = "seed") -> int:
  """Check that a seed is an integer in [0, `MAX_SEED`): the one rule of every seed, in the
  library and on every command line (`name`: the option or flag named in the message)."""
  if (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))
      or not 0 <= seed < MAX_SEED):
    raise ValueError(f"{name}: expected an integer in [0, 2**32), got {seed!r}")
  return int(seed)


def derived_seed(seed: int, k: int) -> int:
  """The k-th seed derived from a checked `seed` (effort's seeds: seed, seed + 1, ...), wrapped
  into [0, `MAX_SEED`)."""
  return (int(seed) + int(k)) % MAX_SEED


def validate_viewpoint(viewpoint: object, name: str = "viewpoint") -> np.ndarray | None:
  """None, or the sensor position as a finite (3,) float64 array.

  Raises:
    ValueError: naming `name`, when it is not a finite (3,) position within `MAX_COORDINATE` of
      the origin in every coordinate.
  """
  if viewpoint is None:
    return None
  try:
    vp = np.asarray(viewpoint, np.float64)
  except (TypeError, ValueError):
    raise ValueError(f"{name}: expected a finite (3,) sensor position, got {viewpoint!r}") from None
  if vp.shape != (3,) or not np.all(np.isfinite(vp)):
    raise ValueError(f"{name}: expected a finite (3,) sensor position, got {viewpoint!r}")
  if np.abs(vp).max() > MAX_COORDINATE:
    raise ValueError(f"{name}: expected a sensor position with coordinates of magnitude at most "
                     f"{MAX_COORDINATE:.0e} (the largest a cloud may hold), "
                     f"got {vp.tolist()}")
  return vp


def validate_frames(frames, valid, n: int) -> tuple[np.ndarray, np.ndarray]:
  """Check frames (n, 3, 3) and valid (n,) for n keypoints; return them as float32 / bool arrays.

  Raises:
    ValueError: naming the argument, the expected and the found shape.
  """
  f = np.asarray(frames)
  if f.dtype.kind not in "fiu" or f.shape != (n, 3, 3):
    raise ValueError(f"frames: expected a float array of shape ({n}, 3, 3) (one frame per "
                     f"keypoint, rows x, y, z), got shape {f.shape} and dtype {f.dtype}")
  if valid is None:
    v = np.all(np.isfinite(f), axis=(1, 2))
  else:
    v = np.asarray(valid)
    if v.shape != (n,):
      raise ValueError(f"valid: expected shape ({n},) (one flag per keypoint), got {v.shape}")
    v = v.astype(bool)
  return f.astype(np.float32), v


def validate_choice(name: str, value: Any, choices: tuple[str, ...]) -> str:
  """`value` if it is one of the strings `choices`, else a ValueError naming `name`."""
  if not (isinstance(value, str) and value in choices):
    listed = ", ".join(repr(c) for c in choices[:-1]) + f" or {choices[-1]!r}"
    raise ValueError(f"{name}: expected {listed}, got {value!r}")
  return value


def validate_voxel_size(voxel_size: Any) -> float | None:
  """None, 0.0 or a positive finite voxel edge (`voxel_size=` of `register` and
  `compute_frames`: None chooses, 0 keeps every point, a positive edge in cloud units).

  Raises:
    ValueError: anything else (a negative or non-finite number, a string, a bool).
  """
  if voxel_size is None:
    return None
  if is_positive(voxel_size):
    return float(voxel_size)
  if not isinstance(voxel_size, (bool, str, bytes, np.bool_)):
    try:
      if voxel_size == 0:
        return 0.0
    except (TypeError, ValueError):
      pass
  raise ValueError(f"voxel_size: expected None, 0 or a positive voxel edge in the clouds' "
                   f"units, got {voxel_size!r}")


def is_positive(val: Any) -> bool:
  """A positive finite number (False for strings, bools, None, lists: no TypeError)."""
  if isinstance(val, (str, bytes, bool, np.bool_)):
    return False
  try:
    return bool(np.isfinite(val) and val > 0)
  except (TypeError, ValueError):
    return False


def is_count(val: Any, minimum: int) -> bool:
  """An integer-valued number >= minimum (1000.0 counts; strings, bools, None and 2.5 do not)."""
  if isinstance(val, (str, bytes, bool, np.bool_)):
    return False
  try:
    return bool(int(val) == val and val >= minimum)
  except (TypeError, ValueError, OverflowError):
    return False
