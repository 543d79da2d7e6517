"""LAS and LAZ point clouds (ASPRS LAS 1.0-1.4; LAZ: LASzip-compressed) on top of `laspy`, with
its `lazrs` backend for LAZ: the `formats` extra (`pip install 'lrf_jax[formats]'`).

A LAS file stores each coordinate as a 32-bit integer count X with a scale and an offset per
axis in its header: x = X * scale + offset, in the file's units (metres for projected
coordinate systems, whatever the file's CRS says otherwise). The reader applies them in float64
(laspy's `.x/.y/.z`), so a georeferenced file (offsets of 10^5-10^6 m) keeps its millimetres.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from lrf_jax.io.cloud import Cloud
from lrf_jax.io.validation import bad_input, check_points, missing_reader, require_file, unreadable


def _laspy(p: Any, suffix: str) -> Any:
  """The laspy module, or a `MissingReaderError` naming the extra."""
  try:
    import laspy
  except ImportError as e:
    package = "laspy[lazrs]" if suffix == ".laz" else "laspy"
    raise missing_reader(p, suffix, package, e.name) from e
  return laspy


def read_las(path: str | os.PathLike) -> Cloud:
  """Reads a `.las` or `.laz` file (any LAS version and point format laspy reads).

  Args:
    path: the file; whether its points are compressed is read from its header, not its suffix.

  Returns:
    A Cloud with (n, 3) float64 points: the stored integer coordinates with the header's scale
    and offset applied (`x = X * scale + offset`), in the file's units. The per-point
    intensity, classification, colours and GPS times are not kept (a `Cloud` holds coordinates,
    faces and normals only).

  Raises:
    FileNotFoundError: missing file.
    MissingReaderError: laspy (or, for compressed points, its lazrs backend) is not installed;
      also a ValueError, naming the `formats` extra.
    ValueError: an unreadable file or header, a body shorter than the header's point count
      (checked against the file size before anything is allocated for uncompressed points), an
      empty cloud, or non-finite coordinates.
  """
  p = require_file(path)
  suffix = p.suffix.lower() or ".las"
  laspy = _laspy(p, suffix)
  with _guarded(p, lambda: laspy.open(p)) as reader:
    header = reader.header
    count = int(header.point_count)
    if header.are_points_compressed and not laspy.LazBackend.detect_available():
      raise missing_reader(p, "compressed LAS (.laz)", "laspy[lazrs]", "lazrs")
    if not header.are_points_compressed:
      _check_body_size(p, header, count)
    data = _guarded(p, reader.read)
  if len(data.points) != count:
    raise bad_input(p, "point count", f"{count} points (header)",
                    f"{len(data.points)} points stored (truncated?)")
  xyz = np.stack([np.asarray(data.x, np.float64), np.asarray(data.y, np.float64),
                  np.asarray(data.z, np.float64)], axis=1)
  return Cloud(check_points(xyz, p, "x/y/z (X/Y/Z * scale + offset)"), None, None, p)


def _guarded(p: Any, call: Callable[[], Any]) -> Any:
  """`call()`, laspy's and lazrs' errors raised as one ValueError naming the file: laspy's
  LaspyException for a bad signature or header, numpy's ValueError for a short body, lazrs'
  LazrsError (a RuntimeError) for damaged compressed data."""
  from laspy.errors import LaspyException
  try:
    return call()
  except OSError as e:  # e.g. permissions changed since `require_file`
    raise unreadable(p, e) from e
  except (LaspyException, ValueError, RuntimeError, KeyError, IndexError, OverflowError) as e:
    raise bad_input(p, "file", "a LAS/LAZ point cloud",
                    f"an unreadable file ({type(e).__name__}: {str(e).splitlines()[0]})") from e


def _check_body_size(p: Any, header: Any, count: int) -> None:
  """Compare the header's point count with the bytes an uncompressed file stores after its
  point data offset, before the points are allocated."""
  record = int(header.point_format.size)
  body = p.stat().st_size - int(header.offset_to_point_data)
  if count * record > body:
    raise bad_input(p, "point count", f"{count} points x {record} bytes = {count * record} "
                    "bytes of point records (header)", f"{max(body, 0)} bytes after the "
                    "header (truncated?)")
