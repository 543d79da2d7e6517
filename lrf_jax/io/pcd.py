"""PCD clouds (PCL's format: ascii, binary, binary_compressed/LZF) on top of `pypcd4`."""

from __future__ import annotations

import os
import struct

import numpy as np

from lrf_jax.io.cloud import Cloud
from lrf_jax.io.validation import bad_input, check_normals, check_points, require_file, unreadable

_NORMALS = ("normal_x", "normal_y", "normal_z")
# pypcd4 reads at most this many header lines (comments and blank lines aside), DATA the last.
_HEADER_LINES = 10
# LZF codes at most 264 bytes in a 3-byte back reference (88x): a stored uncompressed size above
# this multiple of the compressed size cannot be genuine (and would be allocated up front).
_LZF_MAX_RATIO = 128
# pypcd4 builds one numpy field per value of a point (PCL's largest, ESF, has 640).
_MAX_VALUES_PER_POINT = 1 << 16


def read_pcd(path: str | os.PathLike, *, drop_nonfinite: bool = False) -> Cloud:
  """Reads a PCD file (any of PCL's three encodings).

  Args:
    path: the `.pcd` file.
    drop_nonfinite: organised PCL clouds mark missing pixels with NaN coordinates. If True,
      the points whose x/y/z are not all finite are dropped (their normals with them); if
      False (default) they are an error like in every reader. Only the coordinates decide.

  Returns:
    A Cloud with (n, 3) float64 points (fields x y z, units as stored) and normals when the
    file has normal_x/normal_y/normal_z. A point whose normal is not finite (PCL writes NaN
    where it could not estimate one) is kept, with a NaN normal row (`check_normals`).

  Raises:
    FileNotFoundError: missing file.
    ValueError: an unreadable file (e.g. no read permission), a corrupt header or body, a stored
      point count that differs from the header's POINTS (more or fewer; for DATA binary and
      ascii this is checked against the file size before anything is allocated), no x/y/z
      field, an empty cloud, or NaN/inf coordinates (unless dropped).
  """
  p = require_file(path)
  header = _sniff_header(p)
  _check_body_size(p, header)
  from pypcd4 import PointCloud  # imported on the first PCD read, not with lrf_jax
  try:
    pc = PointCloud.from_path(p)
  except OSError as e:  # e.g. permissions changed since `require_file`
    raise unreadable(p, e) from e
  except (ValueError, RuntimeError, TypeError, KeyError, IndexError, OverflowError,
          struct.error) as e:
    # pypcd4 raises pydantic ValidationError (a ValueError) for a bad header, ValueError from
    # numpy for a short binary buffer and RuntimeError/struct.error for bad LZF data.
    raise bad_input(p, f"DATA {header.get('DATA', '?')}",
                    f"{header.get('POINTS', '?')} points with fields {header.get('FIELDS', '?')}",
                    f"an unreadable file ({type(e).__name__}: {str(e).splitlines()[0]})") from e
  fields = pc.fields
  missing = [a for a in "xyz" if a not in fields]
  if missing:
    raise bad_input(p, "FIELDS", "x, y, z", f"{list(fields)} (missing {', '.join(missing)})")
  data = pc.pc_data
  if len(data) != pc.metadata.points:
    raise bad_input(p, "POINTS", f"{pc.metadata.points} points (header)",
                    f"{len(data)} points in the body (truncated?)")
  points = np.stack([data[a] for a in "xyz"], axis=1).astype(np.float64)
  normals = None
  if all(a in fields for a in _NORMALS):
    normals = np.stack([data[a] for a in _NORMALS], axis=1).astype(np.float64)
  if drop_nonfinite:  # the coordinates alone decide: a NaN normal is a missing normal
    keep = np.isfinite(points).all(axis=1)
    points = points[keep]
    normals = normals[keep] if normals is not None else None
  points = check_points(points, p, "fields x/y/z")
  if normals is not None:
    normals = check_normals(normals, p, "fields normal_x/normal_y/normal_z")
  return Cloud(points, None, normals, p)


def _sniff_header(p) -> dict[str, str]:
  """The header as pypcd4 reads it (up to `_HEADER_LINES` lines besides comments and blank lines,
  up to DATA) as {KEY: value text}; "_BODY" is the byte offset of the data.

  Raises:
    ValueError: a key given twice, or no DATA line among those lines (pypcd4 would then read
      the rest of the header as binary_compressed data).
  """
  out: dict[str, str] = {}
  lines, data = 0, False
  with open(p, "rb") as f:
    while lines < _HEADER_LINES and not data:
      raw = f.readline()
      if not raw:
        break
      line = raw.decode("ascii", "replace").strip()
      if not line or line.startswith("#"):
        continue
      lines += 1
      data = line.startswith("DATA")  # pypcd4's test (its keys are case-insensitive)
      key, _, value = line.partition(" ")
      if key.upper() in out:
        raise bad_input(p, f"header line {key}", "each header line once", f"{key} again")
      out[key.upper()] = value
    out["_BODY"] = str(f.tell())
  if not data:
    raise bad_input(p, "header", f"a DATA line within the first {_HEADER_LINES} header lines",
                    f"none (keys {[k for k in out if k != '_BODY']})")
  return out


def _check_body_size(p, header: dict[str, str]) -> None:
  """Compare the header's POINTS with what the file stores, before anything is allocated:
  the exact byte count for DATA binary, the stored LZF sizes for DATA binary_compressed, the
  number of data lines for DATA ascii."""
  try:
    points = int(header.get("POINTS", ""))
    sizes = [int(v) for v in header.get("SIZE", "").split()]
    counts = [int(v) for v in header.get("COUNT", "").split()] or [1] * len(sizes)
  except ValueError:
    return  # a malformed header: pypcd4's own error names it
  mode = header.get("DATA", "").strip().lower()
  if mode not in ("ascii", "binary", "binary_compressed"):  # pypcd4 reads others as compressed
    raise bad_input(p, "DATA", "ascii, binary or binary_compressed", repr(header.get("DATA")))
  if sum(counts) > _MAX_VALUES_PER_POINT:
    raise bad_input(p, "COUNT", f"at most {_MAX_VALUES_PER_POINT} values per point",
                    f"{sum(counts)} ({header.get('COUNT')})")
  body = p.stat().st_size - int(header["_BODY"])
  if mode == "binary":
    want = points * sum(s * c for s, c in zip(sizes, counts))
    if want != body:
      raise bad_input(p, "POINTS", f"{points} points x {want // max(points, 1)} bytes = "
                      f"{want} bytes of DATA binary (header)", f"{body} bytes stored")
  elif mode == "binary_compressed" and points > 0:
    want = points * sum(s * c for s, c in zip(sizes, counts))
    with open(p, "rb") as f:
      f.seek(int(header["_BODY"]))
      stored = f.read(8)
    if len(stored) < 8:
      raise bad_input(p, "DATA binary_compressed", f"{points} points: 8 bytes of LZF sizes "
                      "after the header", f"{len(stored)} bytes")
    compressed, uncompressed = struct.unpack("II", stored)  # as pypcd4 reads them
    if uncompressed != want:
      raise bad_input(p, "POINTS", f"{points} points x {want // points} bytes = {want} bytes "
                      "of DATA binary_compressed (header)",
                      f"an uncompressed size of {uncompressed} bytes stored")
    if compressed > body - 8:
      raise bad_input(p, "DATA binary_compressed", f"{points} points in {compressed} bytes of "
                      "LZF data (stored size)", f"{body - 8} bytes after the sizes (truncated?)")
    if uncompressed > _LZF_MAX_RATIO * compressed:
      raise bad_input(p, "DATA binary_compressed", f"{points} points: LZF data that expands at "
                      f"most {_LZF_MAX_RATIO}x", f"{compressed} bytes for {uncompressed}")
  elif mode == "ascii":
    if points > body:  # every point takes at least one byte: checked before reading
      raise bad_input(p, "POINTS", f"{points} points (header)", f"only {body} bytes of data")
    with open(p, "rb") as f:
      f.seek(int(header["_BODY"]))
      lines = sum(1 for line in f if line.strip())
    if lines != points:
      raise bad_input(p, "POINTS", f"{points} points (header)", f"{lines} data lines stored")
