"""PLY meshes and clouds (ascii and binary) on top of `plyfile`.

`plyfile` parses the header lines and binary bodies. The header is read here, at most
`MAX_HEADER_BYTES` of it, and split into lines in one pass (plyfile reads it one byte at a time);
plyfile then interprets those lines. Its ascii body reader converts row by row in Python (about
2 s for one Stanford bunny scan, whose `range_grid` element has 204,800 rows), so ascii bodies are
parsed here with numpy, element by element, under the same rule as plyfile's (one element per
line); any layout this fast path does not handle goes back to plyfile.

Names: vertex normals are `nx ny nz` or, as PCL writes them, `normal_x normal_y normal_z`; the
triangles are the element `face` or `triangle`, with a list property `vertex_indices` or
`vertex_index`.
"""

from __future__ import annotations

import dataclasses
import io
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import plyfile

from lrf_jax.io.atomic import atomic_path
from lrf_jax.io.cloud import Cloud
from lrf_jax.io.validation import (bad_input, check_normals, check_points, require_file,
                                   unreadable)

# Names of the face element and of its list property used by common writers.
_FACE_ELEMENTS = ("face", "triangle")
_FACE_LISTS = ("vertex_indices", "vertex_index")
_NORMALS = ("nx", "ny", "nz")  # what write_ply writes
_NORMAL_NAMES = (_NORMALS, ("normal_x", "normal_y", "normal_z"))  # read: the first one present
# The longest header read, in bytes ("ply" to "end_header" and its newline included): real
# headers take a few hundred bytes; a file without "end_header" is rejected after this many.
MAX_HEADER_BYTES = 1 << 20


@dataclasses.dataclass(frozen=True, eq=False)
class PlyMesh:
  """The contents of a PLY file.

  Attributes:
    points: (n, 3) float64 vertex coordinates (units as stored).
    faces: (f, 3) int64 triangles, or None when the file has no (or an empty) face element.
      Polygons with more than 3 vertices are fan-triangulated.
    normals: (n, 3) float64 vertex normals (nx ny nz, or normal_x normal_y normal_z) as stored
      (not renormalised; a row with a NaN/inf value is a NaN row, a missing normal), or None.
    vertex_attributes: other vertex properties by name, each (n,) (e.g. colours, confidence).
    elements: every element other than vertex and the one read as faces, as
      {element: {property: array}}.
      Scalar properties are (count,) arrays; a list property is a (count, k) array when all
      its lists have length k, else an object array of 1-D arrays (e.g. the Stanford bunny
      scans' `range_grid`, whose rows hold zero or one vertex index).
    comments: the header's comment lines.
    obj_info: the header's obj_info lines.
    text: True for an ascii file.
    path: the file, or None.
  """

  points: np.ndarray
  faces: np.ndarray | None
  normals: np.ndarray | None
  vertex_attributes: dict[str, np.ndarray]
  elements: dict[str, dict[str, np.ndarray]]
  comments: tuple[str, ...] = ()
  obj_info: tuple[str, ...] = ()
  text: bool = False
  path: Path | None = None

  def to_cloud(self) -> Cloud:
    """The geometry as a `Cloud` (points, faces, normals, path)."""
    return Cloud(self.points, self.faces, self.normals, self.path)


def read_ply(path: str | os.PathLike, *, elements: bool = True) -> PlyMesh:
  """Reads an ascii or binary PLY file.

  Args:
    path: the `.ply` file.
    elements: parse the elements other than vertex and face into `PlyMesh.elements`. False: an
      ascii file's other elements are checked for their row count only and `elements` is empty
      (what `read_cloud` does: e.g. a Stanford bunny scan's 204,800-row `range_grid`).

  Returns:
    A PlyMesh: points (n, 3) float64, faces (f, 3) int64 or None, normals or None, the other
    vertex properties and every other element (kept, not interpreted).

  Raises:
    FileNotFoundError: missing file.
    ValueError: an unreadable file (e.g. no read permission), a corrupt header, no
      `end_header` within `MAX_HEADER_BYTES`, a truncated body, rows that do not match the header
      (wrong element counts, wrong number of values), data after the last element, no
      `vertex` element or no x/y/z property, an empty cloud, NaN/inf coordinates, or face
      indices outside [0, n). The message names the file, the element/property and the
      expected versus found value.
  """
  p = require_file(path)
  try:
    raw = open(p, "rb", buffering=0)
  except OSError as e:  # e.g. permissions changed since `require_file`
    raise unreadable(p, e) from e
  with _BoundedReader(raw, p.stat().st_size) as stream:
    lines, body_start = _header_lines(stream, p)
    header = _parse_header(lines, p)
    stream.seek(body_start)
    if header.text:
      body = stream.read()
      data = _read_ascii_body(header, body, p, elements, lines, body_start)
    else:
      data = _read_binary(stream, lines, body_start, p)
  return _assemble(header, data, p)


def _header_lines(stream, p: Path) -> tuple[list[str], int]:
  """The header's lines after "ply" up to "end_header" (newline removed; plyfile's rule: the
  newline is the one after "ply", LF, CR or CRLF) and the body's byte offset, from one read of
  at most `MAX_HEADER_BYTES` and one search (linear in the header's length).

  Raises:
    ValueError: no "ply" magic, undecodable bytes, or a file longer than `MAX_HEADER_BYTES`
      without an "end_header" line within them. A shorter file without one gives all its lines
      (the parser then reports the error).
  """
  cap = int(MAX_HEADER_BYTES)
  head = stream.read(cap)
  if not head:
    raise bad_input(p, "header line 1", "a PLY file starting with 'ply'", "an empty file (0 bytes)")
  if head[:3] != b"ply":
    raise bad_input(p, "header line 1", "a PLY file starting with 'ply'",
                    f"{head[:16]!r} (not a PLY file?)")
  nl = b"\r\n" if head[3:5] == b"\r\n" else head[3:4]
  if nl not in (b"\n", b"\r", b"\r\n"):
    raise bad_input(p, "header line 1", "a valid PLY header", "unexpected characters after 'ply'")
  start = 3 + len(nl)  # the first line after "ply"
  marker = nl + b"end_header" + nl
  end = head.find(marker, 3)
  if end < 0 and len(head) >= cap:
    raise bad_input(p, "header", "a PLY header ending with an 'end_header' line",
                    f"no end_header within {cap} bytes (MAX_HEADER_BYTES)")
  text = head[start:end] if end >= 0 else head[start:]
  try:
    lines = text.decode("ascii").split(nl.decode("ascii")) if end != 3 else []
  except UnicodeDecodeError as e:
    raise bad_input(p, "header", "an ascii PLY header", f"undecodable bytes ({e})") from e
  if end < 0:
    return lines, len(head)
  return lines + ["end_header"], end + len(marker)


def _parse_header(lines: list[str], p: Path) -> plyfile.PlyData:
  """A fresh header-only `PlyData` (elements without data) from `_header_lines`' lines,
  interpreted by plyfile's header parser."""
  try:
    parser = plyfile._PlyHeaderParser(lines)
    return plyfile.PlyData([plyfile.PlyElement(*e) for e in parser.elements],
                           parser.format == "ascii", plyfile._byte_order_map[parser.format],
                           parser.comments, parser.obj_info)
  except plyfile.PlyHeaderParseError as e:
    raise bad_input(p, f"header line {e.line}", "a valid PLY header", e.message) from e
  except ValueError as e:  # plyfile: two elements or properties with the same name
    raise bad_input(p, "header", "a valid PLY header", str(e)) from e


def write_ply(path: str | os.PathLike, points: np.ndarray, faces: np.ndarray | None = None,
              normals: np.ndarray | None = None, binary: bool = True, *,
              dtype: str = "float32", comments: tuple[str, ...] = ()) -> Path:
  """Writes points (and optionally triangles and normals) as a PLY file (to a temporary name
  beside `path`, renamed into place: `lrf_jax.io.atomic.atomic_path`).

  Args:
    path: destination file (parent folders must exist).
    points: (n, 3) coordinates.
    faces: (f, 3) vertex indices, or None for a cloud.
    normals: (n, 3) normals, or None.
    binary: binary little-endian if True, else ascii.
    dtype: "float32" (PLY `float`, the usual choice) or "float64" (`double`) for coordinates.
    comments: header comment lines.

  Returns:
    The path written.

  Raises:
    ValueError: wrong shapes, non-finite coordinates or face indices outside [0, n).
  """
  pts = check_points(points, "write_ply", "points")
  if dtype not in ("float32", "float64"):
    raise bad_input("write_ply", "dtype", "'float32' or 'float64'", repr(dtype))
  fields = [(a, dtype) for a in "xyz"]
  cols = [pts]
  if normals is not None:
    nrm = check_points(normals, "write_ply", "normals")
    if nrm.shape != pts.shape:
      raise bad_input("write_ply", "normals", f"shape {pts.shape}", f"shape {nrm.shape}")
    fields += [(a, dtype) for a in _NORMALS]
    cols.append(nrm)
  vertex = np.empty(len(pts), dtype=fields)
  stacked = np.concatenate(cols, axis=1)
  for i, (name, _) in enumerate(fields):
    vertex[name] = stacked[:, i]
  elements = [plyfile.PlyElement.describe(vertex, "vertex")]
  if faces is not None:
    f = _check_faces(np.asarray(faces), len(pts), "write_ply")
    face = np.empty(len(f), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = f
    elements.append(plyfile.PlyElement.describe(face, "face",
                                                len_types={"vertex_indices": "u1"},
                                                val_types={"vertex_indices": "i4"}))
  out = Path(path)
  with atomic_path(out) as tmp:  # a temporary name beside it, renamed into place
    plyfile.PlyData(elements, text=not binary, byte_order="<",
                    comments=list(comments)).write(str(tmp))
  return out


# ----------------------------------------------------------------------------------------------
# Bodies -> {element: {property: array}}


class _BoundedReader(io.BufferedReader):
  """A binary file whose `read(n)` never asks for more than the bytes left: plyfile reads a
  list of its declared length in one `read`, which allocates that length first (gigabytes for
  a corrupt length)."""

  def __init__(self, raw: io.RawIOBase, size: int):
    super().__init__(raw)
    self._size = size

  def read(self, n: int | None = -1) -> bytes:
    if n is not None and n > 1 << 16:  # small reads (the header, rows) allocate little anyway
      n = min(n, max(self._size - self.tell(), 0))
    return super().read(n)


def _read_elements(stream, header: plyfile.PlyData, known_list_len: dict) -> None:
  """plyfile's body reader (`PlyData.read` after its header parse), from the stream's position:
  fills every element of `header` in place."""
  data_stream = io.TextIOWrapper(stream, "ascii") if header.text else stream
  for elt in header.elements:
    elt._read(data_stream, header.text, header.byte_order, "c",
              known_list_len=known_list_len.get(elt.name, {}))
  if header.text:
    data_stream.detach()  # leave the binary stream open for its owner


def _read_binary(stream, lines: list[str], body_start: int,
                 p: Path) -> dict[str, dict[str, np.ndarray]]:
  """Binary body via plyfile; triangles are memory-mapped when every face has 3 vertices."""
  header = _parse_header(lines, p)
  known = {e.name: {e.properties[0].name: 3} for e in header.elements
           if e.name in _FACE_ELEMENTS and len(e.properties) == 1
           and isinstance(e.properties[0], plyfile.PlyListProperty)}
  size = p.stat().st_size
  ply = None
  for known_len in (known, {}) if known else ({},):
    stream.seek(body_start)
    ply = _parse_header(lines, p)  # fresh elements: a failed attempt leaves partial data
    try:
      # Scalar-only elements and fixed-length lists are memory-mapped; others read row by row.
      _read_elements(stream, ply, known_len)
      break
    except plyfile.PlyElementParseError as e:
      if e.message == "unexpected list length" and known_len:
        continue  # not all triangles: read the variable-length lists instead
      raise _element_error(p, e) from e
    except (ValueError, OverflowError, MemoryError) as e:
      # plyfile raises these when a corrupt body yields impossible list lengths.
      raise bad_input(p, "body", "data matching the header", f"unreadable ({e})") from e
  assert ply is not None  # every pass of the loop (at least one) sets it before leaving
  trailing = size - stream.tell()
  if trailing > 0:
    raise bad_input(p, "body", f"{stream.tell()} bytes for the elements in the header",
                    f"{trailing} more bytes after the last element (wrong element count?)")
  return {e.name: {q.name: np.array(e.data[q.name]) for q in e.properties} for e in ply.elements}


def _read_ascii_body(header: plyfile.PlyData, body: bytes, p: Path, elements: bool,
                     header_lines: list[str], body_start: int
                     ) -> dict[str, dict[str, np.ndarray]]:
  """Ascii body, one element per line, parsed per element with numpy (with `elements` False,
  only vertex and faces; the others are skipped by their row counts). `header_lines` and
  `body_start` (`_header_lines`) serve the plyfile fallback."""
  lines = body.split(b"\n")
  if lines and not lines[-1].strip():
    lines.pop()  # the final newline
  out: dict[str, dict[str, np.ndarray]] = {}
  pos = 0
  for elt in header.elements:
    rows = lines[pos:pos + elt.count]
    if len(rows) < elt.count:
      raise bad_input(p, f"element '{elt.name}'", f"{elt.count} rows (header count)",
                      f"{len(rows)} rows before the end of the file (truncated?)")
    pos += elt.count
    if not elements and elt.name not in ("vertex",) + _FACE_ELEMENTS:
      continue
    parsed = _parse_ascii_element(elt, rows, p)
    if parsed is None:  # a layout the fast path does not handle: plyfile, row by row
      return _read_ascii_with_plyfile(p, header_lines, body_start)
    out[elt.name] = parsed
  extra = [i for i, line in enumerate(lines[pos:]) if line.strip()]
  if extra:
    raise bad_input(p, "body", f"{pos} data rows (sum of the header's element counts)",
                    f"{len(extra)} more non-empty rows after the last element "
                    "(wrong element count in the header?)")
  return out


def _parse_ascii_element(elt: plyfile.PlyElement, rows: list[bytes],
                         p: Path) -> dict[str, np.ndarray] | None:
  props = list(elt.properties)
  lists = [q for q in props if isinstance(q, plyfile.PlyListProperty)]
  if not rows:
    return {q.name: np.empty((0,) if q not in lists else (0, 0)) for q in props}
  if not lists:
    try:
      with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = np.loadtxt(rows, dtype=np.float64, ndmin=2, encoding="latin1")
    except ValueError as e:
      raise bad_input(p, f"element '{elt.name}'", f"{len(props)} numeric values per row "
                      f"({', '.join(q.name for q in props)})", str(e)) from e
    if table.shape != (len(rows), len(props)):
      raise bad_input(p, f"element '{elt.name}'", f"{len(props)} values per row",
                      f"{table.shape[1]} values per row")
    return {q.name: _checked_cast(table[:, i], q.val_dtype, p, elt.name, q.name,
                                  np.arange(len(rows)))
            for i, q in enumerate(props)}
  if len(props) != 1:
    return None
  (prop,) = lists
  text = b"\n".join(rows)
  counts = _tokens_per_row(text, len(rows)) - 1
  try:
    flat = np.array(text.split(), dtype=np.float64)
  except ValueError as e:
    raise bad_input(p, f"element '{elt.name}' property '{prop.name}'", "numeric lists",
                    str(e)) from e
  starts = np.concatenate([[0], np.cumsum(counts + 1)[:-1]])
  declared = flat[np.minimum(starts, len(flat) - 1)] if len(flat) else counts + 1
  if (counts < 0).any() or not np.array_equal(declared, counts):
    row = int(np.flatnonzero((counts < 0) | (declared != counts))[0])
    raise bad_input(p, f"element '{elt.name}' row {row} property '{prop.name}'",
                    f"a length followed by that many values ({declared[row]:g})",
                    f"{max(int(counts[row]), 0)} values")
  values = _checked_cast(np.delete(flat, starts), prop.val_dtype, p, elt.name, prop.name,
                         np.repeat(np.arange(len(rows)), counts))
  if counts.min() == counts.max():
    return {prop.name: values.reshape(len(rows), int(counts[0]))}
  pieces = np.empty(len(rows), dtype=object)
  ends = np.cumsum(counts).tolist()
  pieces[:] = [values[a:b] for a, b in zip([0] + ends[:-1], ends)]
  return {prop.name: pieces}


def _checked_cast(values: np.ndarray, dtype: Any, p: Path, element: str, prop: str,
                  row: np.ndarray) -> np.ndarray:
  """`values` (float64, parsed from text) as `dtype`, the property's declared type; for an
  integer type every value must be a whole number in its range (plyfile raises there too: a
  `uchar` holding 300 would wrap to 44, an `int` holding 0.7 truncate to 0). `row`: each value's
  row, for the message."""
  dt = np.dtype(dtype)
  if dt.kind in "iu":
    info = np.iinfo(dt)
    with np.errstate(invalid="ignore"):
      bad = ~((values == np.floor(values)) & (values >= info.min) & (values <= info.max))
    if bad.any():
      k = int(np.flatnonzero(bad)[0])
      raise bad_input(p, f"element '{element}' row {int(row[k])} property '{prop}'",
                      f"an integer in [{info.min}, {info.max}] (type {dt.name})",
                      f"{values[k]:.17g}")
  return values.astype(dt)


def _tokens_per_row(text: bytes, n_rows: int) -> np.ndarray:
  """(n_rows,) int64 whitespace-separated tokens on each of the newline-joined rows of `text`."""
  buf = np.frombuffer(text, dtype=np.uint8)
  space = (buf == 32) | (buf == 9) | (buf == 13) | (buf == 10) | (buf == 11) | (buf == 12)
  first = ~space & np.concatenate([[True], space[:-1]])  # a token's first byte
  row = np.cumsum(buf == 10)  # a byte's row: newlines seen before it (a newline is a space)
  return np.bincount(row[first], minlength=n_rows).astype(np.int64)


def _read_ascii_with_plyfile(p: Path, lines: list[str],
                             body_start: int) -> dict[str, dict[str, np.ndarray]]:
  ply = _parse_header(lines, p)
  try:
    with open(p, "rb") as stream:
      stream.seek(body_start)
      _read_elements(stream, ply, {})
  except OSError as e:
    raise unreadable(p, e) from e
  except plyfile.PlyElementParseError as e:
    raise _element_error(p, e) from e
  except UnicodeDecodeError as e:
    raise bad_input(p, "body", "ascii text", f"undecodable bytes ({e})") from e
  return {e.name: {q.name: np.array(e.data[q.name]) for q in e.properties} for e in ply.elements}


def _element_error(p: Path, e: plyfile.PlyElementParseError) -> ValueError:
  where = f"element '{e.element.name}'" if e.element is not None else "body"
  if e.row is not None:
    where += f" row {e.row}"
  if e.prop is not None:
    where += f" property '{e.prop.name}'"
  count = e.element.count if e.element is not None else "?"
  return bad_input(p, where, f"{count} well-formed rows (header count)", e.message)


# ----------------------------------------------------------------------------------------------
# Interpretation: points, faces, normals


def _assemble(header: plyfile.PlyData, data: dict[str, dict[str, np.ndarray]],
              p: Path) -> PlyMesh:
  if "vertex" not in data:
    raise bad_input(p, "elements", "a 'vertex' element", f"elements {list(data)}")
  vertex = data["vertex"]
  missing = [a for a in "xyz" if a not in vertex]
  if missing:
    raise bad_input(p, "element 'vertex'", "properties x, y, z",
                    f"properties {list(vertex)} (missing {', '.join(missing)})")
  n = header["vertex"].count
  if n == 0:
    raise bad_input(p, "element 'vertex'", "at least one vertex", "an empty cloud (0 vertices)")
  points = check_points(np.stack([vertex[a] for a in "xyz"], axis=1), p,
                        "element 'vertex' x/y/z")
  normals, names = None, next((q for q in _NORMAL_NAMES if all(a in vertex for a in q)), ())
  if names:
    normals = check_normals(np.stack([vertex[a] for a in names], axis=1), p,
                            f"element 'vertex' {'/'.join(names)}")
  attributes = {k: v for k, v in vertex.items() if k not in set("xyz") | set(names)}
  faces = None
  # `face`, else a `triangle` element with a face list (one of another layout stays an element).
  present = [e for e in _FACE_ELEMENTS
             if e in data and (e == "face" or any(k in data[e] for k in _FACE_LISTS))]
  nonempty = [e for e in present if header[e].count]
  if len(nonempty) > 1:
    raise bad_input(p, "elements", "one face element (" + " or ".join(_FACE_ELEMENTS) + ")",
                    f"both, non-empty: {nonempty}")
  face_name = (nonempty or present or [None])[0]  # type: ignore[list-item]  # str or None
  if face_name is not None:
    face = data[face_name]
    key = next((k for k in _FACE_LISTS if k in face), None)
    if key is None:
      raise bad_input(p, f"element '{face_name}'", "a list property " + " or ".join(_FACE_LISTS),
                      f"properties {list(face)}")
    if len(face[key]):
      faces = _check_faces(_triangulate(face[key], p, face_name), n, p, face_name)
  elements = {k: v for k, v in data.items() if k not in ("vertex", face_name)}
  return PlyMesh(points, faces, normals, attributes, elements, tuple(header.comments),
                 tuple(header.obj_info), bool(header.text), p)


def _triangulate(lists: np.ndarray, source: Any, element: str = "face") -> np.ndarray:
  """(f, k) or ragged polygon lists -> (t, 3) triangles (fan from each polygon's first vertex)."""
  if lists.dtype != object:
    polys = [np.asarray(lists)]
  else:
    lengths = np.array([len(x) for x in lists])
    polys = [np.stack(lists[lengths == k]) for k in np.unique(lengths)]
  tris = []
  for poly in polys:
    k = poly.shape[1]
    if k < 3:
      raise bad_input(source, f"element '{element}'", "polygons with at least 3 vertices",
                      f"{len(poly)} faces with {k} vertices")
    for j in range(1, k - 1):
      tris.append(poly[:, [0, j, j + 1]])
  return np.concatenate(tris).astype(np.int64)


def _check_faces(faces: np.ndarray, n: int, source: Any, element: str = "face") -> np.ndarray:
  if faces.ndim != 2 or faces.shape[1] != 3:
    raise bad_input(source, f"element '{element}'", "an (f, 3) array of triangles",
                    f"shape {faces.shape}")
  faces = faces.astype(np.int64, copy=False)
  if faces.size and (faces.min() < 0 or faces.max() >= n):
    bad = int(faces.min() if faces.min() < 0 else faces.max())
    raise bad_input(source, f"element '{element}' vertex_indices", f"indices in [0, {n})",
                    f"index {bad}")
  return faces
