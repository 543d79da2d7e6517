"""E57 point clouds (ASTM E2807: terrestrial laser scans) on top of `pye57`: the `formats` extra
(`pip install 'lrf_jax[formats]'`).

An E57 file holds one or more scans ("data3D"), each in its scanner's own frame with an
optional pose (a rotation quaternion and a translation: scanner -> file frame). The rule here:

* `read_cloud` (and so every command line) reads the whole file as one cloud: each scan's pose
  applied, the scans concatenated in file order: the registered model the file describes;
* `read_e57(path, scan=k)` reads scan k alone, its pose applied, or with `apply_pose=False` in
  its scanner's own frame: the form in which the scans of one file are registered to each other
  (read each, save it as .npy or .ply, register those).

Points whose `cartesianInvalidState` (or `sphericalInvalidState`) is set are left out; scans
stored in spherical coordinates (range, azimuth, elevation) are converted to Cartesian ones.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from lrf_jax.io.cloud import Cloud
from lrf_jax.io.poses import quaternion_to_matrix
from lrf_jax.io.validation import bad_input, check_points, missing_reader, require_file, unreadable

_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
# Each point takes at least one bit of a scan's compressed vector unless every field of the
# scan is constant; a header's count beyond this many points a byte of the file is refused
# before pye57 allocates its buffers.
_MAX_POINTS_PER_BYTE = 8


def read_e57(path: str | os.PathLike, *, scan: int | None = None,
             apply_pose: bool = True) -> Cloud:
  """Reads an `.e57` file: every scan (`scan=None`), or scan `scan` alone.

  Args:
    path: the file.
    scan: None: every scan, each with its pose applied (`apply_pose` must be True), the scans
      concatenated in file order; an index: that scan alone (0-based).
    apply_pose: whether to apply the scan's pose (scanner -> file frame; a scan without one is
      in the file frame already); False: the scan in its scanner's own frame (only with
      `scan`).

  Returns:
    A Cloud with (n, 3) float64 points in the file's units (metres by the standard). The
    intensity and colours are not kept (a `Cloud` holds coordinates, faces and normals only).

  Raises:
    FileNotFoundError: missing file.
    MissingReaderError: pye57 is not installed (also a ValueError, naming the `formats` extra).
    ValueError: a bad `scan`/`apply_pose`, an unreadable file, no scan, a scan with neither
      Cartesian nor spherical coordinates, a point count the file is too short to hold, no
      valid point, or non-finite coordinates.
  """
  p = require_file(path)
  try:
    import pye57
    from pye57 import libe57
  except ImportError as e:
    raise missing_reader(p, ".e57", "pye57", e.name) from e
  try:
    with pye57.E57(str(p)) as f:
      n_scans = f.scan_count
      if n_scans == 0:
        raise bad_input(p, "data3D", "at least one scan", "none")
      indices = _indices(p, scan, apply_pose, n_scans)
      limit = _MAX_POINTS_PER_BYTE * p.stat().st_size
      parts = [_read_scan(p, f, k, apply_pose, limit) for k in indices]
  except OSError as e:
    raise unreadable(p, e) from e
  except (libe57.E57Exception, RuntimeError, KeyError, IndexError, TypeError) as e:
    # libE57Format's E57Exception (a bad signature, checksum, length or node), each message
    # followed by lines of debug information: the first line says what.
    raise bad_input(p, "file", "an E57 point cloud",
                    f"an unreadable file ({type(e).__name__}: {str(e).splitlines()[0]})") from e
  points = np.concatenate(parts) if parts else np.zeros((0, 3))
  field = "data3D" if scan is None else f"scan {scan}"
  return Cloud(check_points(points, p, f"{field} x/y/z"), None, None, p)


def _indices(p: Any, scan: int | None, apply_pose: bool, n_scans: int) -> list[int]:
  """The scans to read."""
  if scan is None:
    if not apply_pose:
      raise ValueError(f"{p}: apply_pose=False: expected a scan index with it (each scan is in "
                       f"its own frame: concatenating {n_scans} scans without their poses "
                       "mixes frames), got scan=None")
    return list(range(n_scans))
  if isinstance(scan, bool) or not isinstance(scan, (int, np.integer)) or not (
      0 <= scan < n_scans):
    raise bad_input(p, "scan", f"an index in [0, {n_scans}) ({n_scans} scans in data3D)",
                    repr(scan))
  return [int(scan)]


def _read_scan(p: Any, f: Any, k: int, apply_pose: bool, limit: int) -> np.ndarray:
  """Scan `k` of the open file `f`: its valid points (m, 3) float64, its pose applied or not."""
  header = f.get_header(k)
  fields = set(header.point_fields)
  if not (set(_CARTESIAN) <= fields or set(_SPHERICAL) <= fields):
    raise bad_input(p, f"scan {k} points", f"fields {', '.join(_CARTESIAN)} or "
                    f"{', '.join(_SPHERICAL)}", ", ".join(sorted(fields)) or "none")
  count = int(header.point_count)
  if count > limit:
    raise bad_input(p, f"scan {k} points", f"at most {_MAX_POINTS_PER_BYTE} points a byte of "
                    f"the file ({limit})", f"{count} points (header)")
  data = f.read_scan(k, transform=False, ignore_missing_fields=True)  # valid points only
  if set(_CARTESIAN) <= fields:
    xyz = np.stack([np.asarray(data[c], np.float64) for c in _CARTESIAN], axis=1)
  else:  # range, azimuth, elevation (radians) -> x, y, z, as pye57 converts them
    r, az, el = (np.asarray(data[c], np.float64) for c in _SPHERICAL)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)],
                   axis=1)
  if apply_pose and header.has_pose():
    w, x, y, z = np.asarray(header.rotation, np.float64)  # E57: scalar first
    q = np.array([x, y, z, w])
    with np.errstate(invalid="ignore", divide="ignore"):  # a zero quaternion: NaN, refused
      q = q / np.linalg.norm(q)  # normalised, as pye57 and the E57 library's readers do
    rotation = quaternion_to_matrix(q, source=f"{p}: scan {k} pose")
    xyz = xyz @ rotation.T + np.asarray(header.translation, np.float64)
  return xyz
