"""PCD clouds (PCL's format: ascii, binary, binary_compressed/LZF) on top of `pypcd4`."""

from __future__ import annotations

import os
import struct

import numpy as np
from pypcd4 import PointCloud

from lrf_jax.io.cloud import Cloud
from lrf_jax.io.validation import bad_input, check_points, require_file

_NORMALS = ("normal_x", "normal_y", "normal_z")


def read_pcd(path: str | os.PathLike, *, drop_nonfinite: bool = False) -> Cloud:
  """Reads a PCD file (any of PCL's three encodings).

  Args:
    path: the `.pcd` file.
    drop_nonfinite: organised PCL clouds mark missing pixels with NaN. If True, such points are
      dropped (normals with them); if False (default) they are an error like in every reader.

  Returns:
    A Cloud with (n, 3) float64 points (fields x y z, units as stored) and normals when the
    file has normal_x/normal_y/normal_z.

  Raises:
    FileNotFoundError: missing file.
    ValueError: a corrupt header or body, a stored point count that differs from the header's
      POINTS (more or fewer; for DATA binary and ascii this is checked against the file size
      before anything is allocated), no x/y/z field, an empty cloud, or NaN/inf coordinates
      (unless dropped).
  """
  p = require_file(path)
  header = _sniff_header(p)
  _check_body_size(p, header)
  try:
    pc = PointCloud.from_path(p)
  except (ValueError, RuntimeError, TypeError, KeyError, IndexError, struct.error) as e:
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
  if drop_nonfinite:
    keep = np.isfinite(points).all(axis=1)
    if normals is not None:
      keep &= np.isfinite(normals).all(axis=1)
    points = points[keep]
    normals = normals[keep] if normals is not None else None
  points = check_points(points, p, "fields x/y/z")
  if normals is not None:
    normals = check_points(normals, p, "fields normal_x/normal_y/normal_z")
  return Cloud(points, None, normals, p)


def _sniff_header(p) -> dict[str, str]:
  """The first header lines as {KEY: value text}; "_BODY" is the byte offset of the data."""
  out: dict[str, str] = {}
  with open(p, "rb") as f:
    for _ in range(16):
      line = f.readline().decode("ascii", "replace").strip()
      if line and not line.startswith("#"):
        key, _, value = line.partition(" ")
        out[key.upper()] = value
      if line.upper().startswith("DATA"):
        break
    out["_BODY"] = str(f.tell())
  return out


def _check_body_size(p, header: dict[str, str]) -> None:
  """Compare the header's POINTS with what the file stores, before anything is allocated:
  the exact byte count for DATA binary, the number of data lines for DATA ascii."""
  try:
    points = int(header.get("POINTS", ""))
    sizes = [int(v) for v in header.get("SIZE", "").split()]
    counts = [int(v) for v in header.get("COUNT", "").split()] or [1] * len(sizes)
  except ValueError:
    return  # a malformed header: pypcd4's own error names it
  mode = header.get("DATA", "").strip().lower()
  body = p.stat().st_size - int(header["_BODY"])
  if mode == "binary":
    want = points * sum(s * c for s, c in zip(sizes, counts))
    if want != body:
      raise bad_input(p, "POINTS", f"{points} points x {want // max(points, 1)} bytes = "
                      f"{want} bytes of DATA binary (header)", f"{body} bytes stored")
  elif mode == "ascii":
    if points > body:  # every point takes at least one byte: checked before reading
      raise bad_input(p, "POINTS", f"{points} points (header)", f"only {body} bytes of data")
    with open(p, "rb") as f:
      f.seek(int(header["_BODY"]))
      lines = sum(1 for line in f if line.strip())
    if lines != points:
      raise bad_input(p, "POINTS", f"{points} points (header)", f"{lines} data lines stored")
