"""Seeded, bounded fuzz of the readers (`lrf_jax.io`): PLY, PCD, XYZ, NPY and pose files.

From one seeded numpy Generator per format, valid files (written by `io.write_ply`,
`io.write_xf`, plyfile, pypcd4 or numpy) are mutated -- truncated at a random byte, bytes
flipped, header lines deleted / duplicated / swapped, counts, sizes, types and DATA modes
changed, tokens made non-numeric or NaN/inf, counts made huge. The same oracle judges the bad
arguments drawn for `compute_frames` (tests/test_compute_inputs.py) and `register`
(tests/test_registration.py); the oracle and the shared mutations are in tests/lrf_testing.py.

The oracle for every case: the call returns a valid result (finite float64 (n, 3) points, faces
in range, rigid poses, orthonormal frames), or raises ValueError / FileNotFoundError from lrf_jax
code (not from inside a dependency) whose message names the input (the file's path, or the
argument's name). Anything else fails: another exception type (IndexError, struct.error,
MemoryError, ...), a message without the name, no answer within `CASE_SECONDS`, more than
`MAX_TRACED_BYTES` allocated while reading a file of a few KB (huge counts must be rejected
before allocating), a result for a case that must fail (NaN coordinates, a wrong count, a
truncated binary body, a bad argument) or an error for a valid argument.

Cases tried: 200 PLY + 200 PCD + 100 XYZ + 100 NPY + 100 pose + 60 compute_frames +
16 register = 776 (`FUZZ_CASES`, `FUZZ_TOTAL_CASES`), about 10 s on 2 cores; plus one
deterministic regression test per bug the fuzz found (`test_regression_*`, each failed before
its fix).
"""

from __future__ import annotations

import gzip
import io as pyio
import re
from pathlib import Path
from collections.abc import Callable

import numpy as np
import plyfile
import pytest
from pypcd4 import Encoding, PointCloud
from scipy.spatial.transform import Rotation

from lrf_jax import io
from tests.lrf_testing import (FUZZ_CASES, FUZZ_SEED, FUZZ_TOTAL_CASES, HUGE, Case,
                               append_garbage, binary_must_fail, check_cloud, check_pose,
                               edit_lines, empty_file, file_cases, flip, header_op, pick,
                               rejects, replace_token, run_cases, simple_mutation, truncate,
                               write_file)



# ---------------------------------------------------------------------------------------------
# PLY


def _ply_split(data: bytes) -> tuple[list[bytes], bytes]:
  end = data.index(b"end_header\n") + len(b"end_header\n")
  return data[:end].splitlines(keepends=True), data[end:]


def _ply_bases(tmp_path: Path, rng: np.random.Generator) -> list[tuple[str, bytes, dict]]:
  n = 24
  pts = rng.normal(size=(n, 3))
  faces = np.stack([rng.permutation(n)[:3] for _ in range(30)])
  normals = rng.normal(size=(n, 3))
  out = []
  for label, kw in (("binary mesh + normals", dict(faces=faces, normals=normals)),
                    ("ascii mesh float64", dict(faces=faces, binary=False, dtype="float64")),
                    ("binary cloud float64", dict(dtype="float64")),
                    ("ascii cloud + normals", dict(normals=normals, binary=False))):
    p = io.write_ply(tmp_path / "base.ply", pts, **kw)
    out.append((label, p.read_bytes(), {"binary": kw.get("binary", True), "n": n,
                                        "tri": "faces" in kw}))
  # plyfile: big-endian with extra vertex properties and quads; ascii with ragged polygons.
  v = np.empty(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                         ("confidence", "f8")])
  for i, a in enumerate("xyz"):
    v[a] = pts[:, i]
  v["red"], v["confidence"] = rng.integers(0, 255, n), rng.uniform(size=n)
  quads = np.empty(10, dtype=[("vertex_indices", "i4", (4,))])
  quads["vertex_indices"] = np.stack([rng.permutation(n)[:4] for _ in range(10)])
  ragged = np.empty(10, dtype=[("vertex_indices", "O")])
  ragged["vertex_indices"] = [rng.permutation(n)[:3 + i % 3].astype(np.int32) for i in range(10)]
  for label, f, text, order in (("big-endian quads + attributes", quads, False, ">"),
                                ("ascii ragged polygons", ragged, True, "=")):
    buf = pyio.BytesIO()
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"),
                     plyfile.PlyElement.describe(f, "face", len_types={"vertex_indices": "u1"},
                                                 val_types={"vertex_indices": "i4"})],
                    text=text, byte_order=order, comments=["fuzz base"]).write(buf)
    out.append((label, buf.getvalue(), {"binary": not text, "n": n, "tri": False}))
  return out


def _ply_vertex_layout(data: bytes) -> tuple[plyfile.PlyElement, bool, str]:
  header = plyfile.PlyData._parse_header(pyio.BytesIO(data))
  return header["vertex"], header.text, header.byte_order


def _ply_nonfinite(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  """A NaN/inf x, y or z in a random vertex (poked into the body, binary or ascii)."""
  elt, text, order = _ply_vertex_layout(data)
  head, body = _ply_split(data)
  hlen = len(b"".join(head))
  row, axis = int(rng.integers(0, elt.count)), str(rng.choice(list("xyz")))
  value = float(rng.choice([np.nan, np.inf, -np.inf]))
  if text:
    lines = body.split(b"\n")
    tokens = lines[row].split()
    tokens[[q.name for q in elt.properties].index(axis)] = repr(value).encode()
    lines[row] = b" ".join(tokens)
    out = data[:hlen] + b"\n".join(lines)
  else:
    dtype = elt.dtype(order)
    field, offset = dtype.fields[axis][0], dtype.fields[axis][1]
    at = hlen + row * dtype.itemsize + offset
    out = data[:at] + np.array(value, field).tobytes() + data[at + field.itemsize:]
  return out, f"vertex {row} {axis} = {value}", "error"


def _ply_count(element: str, values: tuple[str, ...] | None = None) -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    m = re.search(rb"element " + element.encode() + rb" (\d+)", data)
    if m is None:  # a cloud: no face element
      m = re.search(rb"element vertex (\d+)", data)
    old = int(m.group(1))
    if values is None:
      new = str(max(0, old + int(rng.choice([-1, 1]) * rng.integers(1, 6))))
      if int(new) == old:
        new = str(old + 1)
    else:
      new = str(rng.choice(values))
    out = data[:m.start(1)] + new.encode() + data[m.end(1):]
    return out, f"{m.group(0).decode()} -> {new}", "error"
  return mutate


def _ply_property_type(data: bytes, rng: np.random.Generator,
                       info: dict) -> tuple[bytes, str, str]:
  spans = list(re.finditer(rb"property (list \w+ \w+|\w+) (\w+)", data))
  m = pick(rng, spans)
  new = str(rng.choice(["char", "uchar", "short", "ushort", "int", "uint", "float", "double",
                        "int8", "uint32", "float64", "flaot", "list uchar int", "list int float",
                        "list float int", "list uint uint", "list double"]))
  out = data[:m.start(1)] + new.encode() + data[m.end(1):]
  return out, f"{m.group(0).decode()} -> type {new}", "either"


def _ply_rename_xyz(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  axis = str(rng.choice(list("xyz")))
  new = str(rng.choice(["w", "q", "xx", "X", "y" if axis != "y" else "z"]))
  out = re.sub(rb"(property \w+) " + axis.encode() + rb"\n", rb"\1 " + new.encode() + b"\n",
               data, count=1)
  return out, f"property {axis} renamed {new}", "error"


def _ply_format(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  new = str(rng.choice(["ascii 1.0", "binary_little_endian 1.0", "binary_big_endian 1.0",
                        "binary 1.0", "ascii 2.0", "ascii", "", "ASCII 1.0"]))
  out = re.sub(rb"format [^\n]*\n", b"format " + new.encode() + b"\n", data, count=1)
  return out, f"format -> {new!r}", "either"


def _ply_body_token(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  start = data.index(b"end_header\n") + len(b"end_header\n")
  if info["binary"]:
    out, label = flip(data[start:], rng)
    return data[:start] + out, f"body {label}", "either"
  out, label = replace_token(data, rng, start=start)
  return out, f"body {label}", "either"


def _ply_face_index(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  """A face index set to -1, n or a large value (write_ply's triangle layout only)."""
  if not info["tri"]:
    return _ply_nonfinite(data, rng, info)
  n = info["n"]
  bad = int(rng.choice([-1, n, n + 7, 2**31 - 1]))
  head, body = _ply_split(data)
  hlen = len(b"".join(head))
  face, j = int(rng.integers(0, 30)), int(rng.integers(0, 3))
  if info["binary"]:
    elt, _, order = _ply_vertex_layout(data)
    at = hlen + n * elt.dtype(order).itemsize + face * 13 + 1 + 4 * j
    out = data[:at] + np.array(bad, "<i4").tobytes() + data[at + 4:]
  else:
    lines = body.split(b"\n")
    tokens = lines[n + face].split()
    tokens[1 + j] = str(bad).encode()
    lines[n + face] = b" ".join(tokens)
    out = data[:hlen] + b"\n".join(lines)
  return out, f"face {face} index {j} = {bad}", "error"


def _ply_no_end_header(data: bytes, rng: np.random.Generator,
                       info: dict) -> tuple[bytes, str, str]:
  return data.replace(b"end_header\n", b"", 1), "end_header removed", "error"


def _ply_header_only(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  head, _ = _ply_split(data)
  return b"".join(head), "body removed", "error"


def _crlf(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  if info.get("binary"):
    head, body = _ply_split(data)
    return b"".join(h.replace(b"\n", b"\r\n") for h in head) + body, "CRLF header", "either"
  return data.replace(b"\n", b"\r\n"), "CRLF line ends", "either"


def _ply_list_length(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  """A face's list length byte set to 0, 2, 4 or 255 (write_ply's binary triangles only)."""
  if not (info["tri"] and info["binary"]):
    return _ply_count("face")(data, rng, info)
  elt, _, order = _ply_vertex_layout(data)
  head, _ = _ply_split(data)
  face = int(rng.integers(0, 30))
  at = len(b"".join(head)) + info["n"] * elt.dtype(order).itemsize + face * 13
  new = int(rng.choice([0, 2, 4, 255]))
  return data[:at] + bytes([new]) + data[at + 1:], f"face {face} list length {new}", "error"


PLY_MUTATIONS = [
    simple_mutation(truncate, binary_must_fail), simple_mutation(flip),
    simple_mutation(append_garbage, binary_must_fail),
    header_op(_ply_split, "delete"), header_op(_ply_split, "duplicate"),
    header_op(_ply_split, "swap"), _ply_count("vertex"), _ply_count("face"),
    _ply_count("vertex", HUGE), _ply_count("face", HUGE),
    _ply_count("vertex", ("-1", "abc", "1.5", "", "0x10", "1e3")), _ply_property_type,
    _ply_rename_xyz, _ply_format, _ply_body_token, _ply_nonfinite, empty_file, _ply_header_only,
    _ply_no_end_header, _ply_face_index, _crlf, _ply_list_length,
]
BYTE_LEVEL = [truncate, flip, append_garbage]


def test_fuzz_ply(tmp_path: Path) -> None:
  """FUZZ_CASES["ply"] malformed PLY files through read_ply and read_cloud."""
  rng = np.random.default_rng([FUZZ_SEED, 1])
  cases = file_cases(tmp_path, "ply", FUZZ_CASES["ply"], _ply_bases(tmp_path, rng), PLY_MUTATIONS,
                      BYTE_LEVEL, ".ply", [io.read_ply, io.read_cloud], check_cloud, rng)
  run_cases(cases, FUZZ_CASES["ply"])


# ---------------------------------------------------------------------------------------------
# PCD


def _pcd_split(data: bytes) -> tuple[list[bytes], bytes]:
  m = re.search(rb"^DATA[^\n]*\n", data, re.M)
  return data[:m.end()].splitlines(keepends=True), data[m.end():]


def _pcd_bytes(tmp_path: Path, arr: np.ndarray, fields: tuple[str, ...], types: tuple,
               encoding: Encoding) -> bytes:
  p = tmp_path / "base.pcd"
  PointCloud.from_points(arr, fields, types).save(p, encoding=encoding)
  return p.read_bytes()


def _pcd_bases(tmp_path: Path, rng: np.random.Generator) -> list[tuple[str, bytes, dict]]:
  n = 40
  pts = (rng.integers(-4, 4, (n, 3)) * 0.25).astype(np.float32)  # compressible (LZF)
  out = []
  specs = [("xyz", pts, ("x", "y", "z"), (np.float32,) * 3),
           ("xyz+normals", np.concatenate([pts, pts[::-1]], 1),
            ("x", "y", "z", "normal_x", "normal_y", "normal_z"), (np.float32,) * 6),
           ("xyz f64 + intensity u1", np.concatenate([pts, np.abs(pts[:, :1]) * 4], 1),
            ("x", "y", "z", "intensity"), (np.float64,) * 3 + (np.uint8,))]
  for enc in (Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED):
    for label, arr, fields, types in specs:
      data = _pcd_bytes(tmp_path, arr, fields, types, enc)
      mode = re.search(rb"^DATA (\w+)", data, re.M).group(1).decode()
      out.append((f"{label} {mode}", data, {"binary": mode != "ascii", "mode": mode,
                                            "spec": (arr, fields, types, enc)}))
  return out


def _pcd_key(key: str, values: tuple[str, ...] | None = None, outcome: str = "error",
             width: bool = False) -> Callable:
  """Changes the value of header line `key` (small delta, or one of `values`); `width` changes
  WIDTH to the same value (so that WIDTH x HEIGHT = POINTS still holds)."""

  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    m = re.search(rb"^" + key.encode() + rb" ([^\n]*)\n", data, re.M)
    old = m.group(1).decode()
    if values is None:
      new = str(max(0, int(old) + int(rng.choice([-1, 1]) * rng.integers(1, 6))))
      new = str(int(old) + 1) if new == old else new
    else:
      new = str(rng.choice(values))
    out = data[:m.start(1)] + new.encode() + data[m.end(1):]
    if width:
      out = re.sub(rb"^WIDTH [^\n]*\n", b"WIDTH " + new.encode() + b"\n", out, count=1,
                   flags=re.M)
    return out, f"{key} {old} -> {new}" + (" (and WIDTH)" if width else ""), outcome

  return mutate


def _pcd_token(key: str, values: tuple[str, ...]) -> Callable:
  """Replaces one token of header line `key` (SIZE, TYPE, COUNT, FIELDS)."""

  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    m = re.search(rb"^" + key.encode() + rb" ([^\n]*)\n", data, re.M)
    tokens = m.group(1).decode().split()
    i = int(rng.integers(0, len(tokens)))
    old, tokens[i] = tokens[i], str(rng.choice(values))
    out = data[:m.start(1)] + " ".join(tokens).encode() + data[m.end(1):]
    outcome = "error" if key == "FIELDS" and old in "xyz" and tokens[i] not in "xyz" else "either"
    return out, f"{key} token {i} {old} -> {tokens[i]}", outcome

  return mutate


def _pcd_nonfinite(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  arr, fields, types, enc = info["spec"]
  arr = arr.copy()
  row, col = int(rng.integers(0, len(arr))), int(rng.integers(0, 3))
  arr[row, col] = rng.choice([np.nan, np.inf, -np.inf])
  data = _pcd_bytes(info["tmp"], arr, fields, types, enc)
  return data, f"point {row} {'xyz'[col]} = {arr[row, col]}", "error"


def _pcd_comments(huge: bool) -> Callable:
  """20-40 comment lines after the first line (PCL allows them), optionally with a huge POINTS."""

  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    k = int(rng.integers(20, 41))
    first = data.index(b"\n") + 1
    out = data[:first] + b"# comment\n" * k + data[first:]
    if not huge:
      return out, f"{k} comment lines", "result"
    out, label, _ = _pcd_key("POINTS", HUGE, width=True)(out, rng, info)
    return out, f"{k} comment lines, {label}", "error"

  return mutate


def _pcd_lzf_sizes(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  """binary_compressed: the stored compressed / uncompressed sizes made wrong or huge."""
  if info["mode"] != "binary_compressed":
    return _pcd_key("POINTS", HUGE)(data, rng, info)
  head, body = _pcd_split(data)
  sizes = np.frombuffer(body[:8], "<u4").copy()
  which = int(rng.integers(0, 2))
  sizes[which] = int(rng.choice([0, 1, sizes[which] - 1, sizes[which] + 1, 2**31, 2**32 - 1]))
  label = f"LZF {'un' if which else ''}compressed size -> {sizes[which]}"
  return b"".join(head) + sizes.tobytes() + body[8:], label, "error"


def _pcd_body_token(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  head, body = _pcd_split(data)
  if info["binary"]:
    out, label = flip(body, rng)
  else:
    out, label = replace_token(body, rng)
  return b"".join(head) + out, f"body {label}", "either"


def _pcd_header_only(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  head, _ = _pcd_split(data)
  return b"".join(head), "body removed", "error"


PCD_MUTATIONS = [
    simple_mutation(truncate, binary_must_fail), simple_mutation(flip),
    simple_mutation(append_garbage),
    header_op(_pcd_split, "delete"), header_op(_pcd_split, "duplicate"),
    header_op(_pcd_split, "swap"), _pcd_key("POINTS"), _pcd_key("POINTS", width=True),
    _pcd_key("WIDTH", outcome="either"), _pcd_key("HEIGHT", ("0", "2", "-1", "x"), "either"),
    _pcd_key("POINTS", HUGE, width=True), _pcd_key("POINTS", ("-1", "abc", "1.5", "", "1e3")),
    _pcd_token("SIZE", ("1", "2", "4", "8", "0", "-1", "3", "x")),
    _pcd_token("TYPE", ("F", "I", "U", "X", "f", "")),
    _pcd_token("COUNT", ("0", "2", "3", "-1", "1000000000000", "x")),
    _pcd_token("FIELDS", ("w", "q", "x", "rgb", "normal_x")),
    _pcd_key("DATA", ("ascii", "binary", "binary_compressed", "binary_lzf", "", "ASCII"),
             "either"),
    _pcd_key("VERSION", (".7", "0.6", "2", "x"), "either"), _pcd_body_token, _pcd_nonfinite,
    empty_file, _pcd_header_only, _pcd_comments(False), _pcd_comments(True), _pcd_lzf_sizes,
]


def test_fuzz_pcd(tmp_path: Path) -> None:
  """FUZZ_CASES["pcd"] malformed PCD files (ascii, binary, binary_compressed) through read_pcd and
  read_cloud."""
  rng = np.random.default_rng([FUZZ_SEED, 2])
  bases = [(label, data, info | {"tmp": tmp_path}) for label, data, info in
           _pcd_bases(tmp_path, rng)]
  cases = file_cases(tmp_path, "pcd", FUZZ_CASES["pcd"], bases, PCD_MUTATIONS, BYTE_LEVEL, ".pcd",
                      [io.read_pcd, io.read_cloud], check_cloud, rng)
  run_cases(cases, FUZZ_CASES["pcd"])


# ---------------------------------------------------------------------------------------------
# XYZ text (plain and gzip'ed)


def _xyz_text(pts: np.ndarray) -> bytes:
  return ("# x y z extra\n" + "".join(" ".join(f"{v:.9g}" for v in row) + "\n"
                                      for row in pts)).encode()


def _xyz_bases(rng: np.random.Generator) -> list[tuple[str, bytes, dict]]:
  pts3, pts5 = rng.normal(size=(30, 3)), rng.normal(size=(30, 5))
  return [("3 columns", _xyz_text(pts3), {"cols": 3}),
          ("5 columns", _xyz_text(pts5), {"cols": 5}),
          ("3 columns gz", _xyz_text(pts3), {"cols": 3, "gz": True}),
          ("5 columns gz", _xyz_text(pts5), {"cols": 5, "gz": True})]


def _xyz_gz(mutate: Callable, compressed: bool = False) -> Callable:
  """Applies `mutate` to the text, then compresses for .gz bases; with `compressed`, applies a
  byte-level mutation to the compressed stream instead (a truncated gz stream must fail)."""

  def wrapped(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    if compressed and info.get("gz"):
      out, label = mutate(gzip.compress(data, mtime=0), rng)
      return out, f"gz stream {label}", "error" if mutate is truncate else "either"
    if compressed:
      out, label = mutate(data, rng)
      outcome = "either"
    else:
      out, label, outcome = mutate(data, rng, info)
    return (gzip.compress(out, mtime=0) if info.get("gz") else out), label, outcome

  return wrapped


def _xyz_token(values: tuple[str, ...], outcome: str) -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    start = data.index(b"\n") + 1
    lines = data[start:].split(b"\n")
    row = int(rng.integers(0, len(lines) - 1))
    tokens = lines[row].split()
    col = int(rng.integers(0, 3))
    tokens[col] = str(rng.choice(values)).encode("latin-1")
    lines[row] = b" ".join(tokens)
    return data[:start] + b"\n".join(lines), f"row {row} column {col} -> {tokens[col]!r}", outcome
  return mutate


def _xyz_drop_column(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  start = data.index(b"\n") + 1
  lines = data[start:].split(b"\n")
  row = int(rng.integers(0, len(lines) - 1))
  lines[row] = b" ".join(lines[row].split()[:-1])
  return data[:start] + b"\n".join(lines), f"row {row} lost its last column", "error"


def _xyz_two_columns(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  rows = [b" ".join(line.split()[:2]) for line in data.split(b"\n")[1:]]
  return b"\n".join(rows), "every row cut to 2 columns", "error"


def _xyz_comments_only(data: bytes, rng: np.random.Generator,
                       info: dict) -> tuple[bytes, str, str]:
  return b"# only\n# comments\n\n", "comments only", "error"


def _xyz_layout(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  how = str(rng.choice(["crlf", "tabs", "blank lines", "no final newline"]))
  out = {"crlf": data.replace(b"\n", b"\r\n"), "tabs": data.replace(b" ", b"\t"),
         "blank lines": data.replace(b"\n", b"\n\n"), "no final newline": data.rstrip(b"\n")}[how]
  return out, how, "result"


def _xyz_non_utf8(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  start = data.index(b"\n") + 1
  at = int(rng.integers(start, len(data)))
  return data[:at] + b"\xff\xfe\x80" + data[at:], f"bytes ff fe 80 at {at}", "either"


XYZ_MUTATIONS = [
    _xyz_gz(truncate, True), _xyz_gz(flip, True), _xyz_gz(append_garbage, True),
    _xyz_gz(_xyz_token(("nan", "inf", "-inf", "1e999"), "error")),
    _xyz_gz(_xyz_token(("abc", "0x10", "1,5", "--1", "\x00", "1..2"), "error")),
    _xyz_gz(_xyz_drop_column), _xyz_gz(_xyz_two_columns), _xyz_gz(_xyz_comments_only),
    _xyz_gz(empty_file), _xyz_gz(_xyz_layout), _xyz_gz(_xyz_non_utf8),
]


def test_fuzz_xyz(tmp_path: Path) -> None:
  """FUZZ_CASES["xyz"] malformed text clouds (.xyz and .xyz.gz) through read_xyz and read_cloud."""
  rng = np.random.default_rng([FUZZ_SEED, 3])
  cases = file_cases(tmp_path, "xyz", FUZZ_CASES["xyz"], _xyz_bases(rng), XYZ_MUTATIONS, [],
                      ".xyz", [io.read_xyz, io.read_cloud], check_cloud, rng)
  run_cases(cases, FUZZ_CASES["xyz"])


# ---------------------------------------------------------------------------------------------
# NPY


def _npy_bytes(arr: np.ndarray, allow_pickle: bool = False) -> bytes:
  buf = pyio.BytesIO()
  np.save(buf, arr, allow_pickle=allow_pickle)
  return buf.getvalue()


def _npy_arrays(rng: np.random.Generator) -> list[tuple[str, np.ndarray, str]]:
  """(label, array, outcome) for every dtype and shape worth trying."""
  n = 20
  x = rng.normal(size=(n, 3))
  obj = np.empty((n, 3), object)
  obj[:] = 1.0
  rec = np.zeros(n, [("x", "f8"), ("y", "f8"), ("z", "f8")])
  return [
      ("float64 (n, 3)", x, "result"), ("float32 (n, 6)", np.concatenate([x, x], 1)
                                        .astype(np.float32), "result"),
      ("int32 (n, 3)", rng.integers(-9, 9, (n, 3)).astype(np.int32), "result"),
      (">f8 (n, 3)", x.astype(">f8"), "result"), ("float16 (n, 3)", x.astype(np.float16),
                                                  "result"),
      ("uint64 (n, 3)", rng.integers(0, 2**63, (n, 3), dtype=np.uint64), "result"),
      ("fortran (n, 3)", np.asfortranarray(x), "result"), ("(1, 3)", x[:1], "result"),
      ("object", obj, "error"), ("complex", x.astype(complex), "error"),
      ("bool", x > 0, "error"), ("unicode", x.astype("U8"), "error"),
      ("bytes", x.astype("S8"), "error"), ("datetime64", np.zeros((n, 3), "M8[s]"), "error"),
      ("timedelta64", np.zeros((n, 3), "m8[s]"), "error"), ("structured xyz", rec, "error"),
      ("1-D", x[:, 0], "error"), ("(n, 4)", rng.normal(size=(n, 4)), "error"),
      ("(n, 2)", x[:, :2], "error"), ("(0, 3)", np.zeros((0, 3)), "error"),
      ("(0, 6)", np.zeros((0, 6)), "error"), ("(n, 0)", np.zeros((n, 0)), "error"),
      ("(2, n, 3)", np.stack([x, x]), "error"), ("0-d", np.array(1.0), "error"),
      ("(3,)", x[0], "error"),
  ]


def _npy_array(arrays: list) -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    label, arr, outcome = pick(rng, arrays)
    return _npy_bytes(arr, allow_pickle=arr.dtype == object), f"array {label}", outcome
  return mutate


def _npy_split(data: bytes) -> tuple[bytes, bytes, bytes]:
  """(magic + version + length, header dict text, body) of a version 1.0 file."""
  hlen = int.from_bytes(data[8:10], "little")
  return data[:10], data[10:10 + hlen], data[10 + hlen:]


def _npy_header(field: str, values: tuple[str, ...], outcome: str) -> Callable:
  """Replaces the header's `field` value (keeping the header length, padded with spaces)."""

  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    pre, head, body = _npy_split(data)
    text = head.decode("latin-1")
    pattern = {"shape": r"'shape': \([^)]*\)", "descr": r"'descr': '[^']*'",
               "fortran_order": r"'fortran_order': \w+"}[field]
    new = str(rng.choice(values))
    text2 = re.sub(pattern, f"'{field}': {new}", text, count=1)
    if len(text2) <= len(text):
      text2 = text2[:-1].ljust(len(text) - 1) + "\n"
    else:  # longer: a new length field
      text2 = text2.rstrip("\n ") + "\n"
      pre = pre[:8] + len(text2).to_bytes(2, "little")
    return pre + text2.encode("latin-1") + body, f"header {field} -> {new}", outcome

  return mutate


def _npy_nonfinite(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  x = rng.normal(size=(20, int(rng.choice([3, 6]))))
  row, col = int(rng.integers(0, 20)), int(rng.integers(0, x.shape[1]))
  x[row, col] = rng.choice([np.nan, np.inf, -np.inf])
  # a non-finite coordinate must be refused; a non-finite normal (columns 3-5) may come back as
  # a NaN row, an invalid normal that the frames treat as missing
  return _npy_bytes(x), f"value [{row}, {col}] = {x[row, col]}", "error" if col < 3 else "either"


def _npy_magic(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  at = int(rng.integers(0, 8))
  b = bytearray(data)
  b[at] = (b[at] + 1 + int(rng.integers(0, 255))) % 256
  outcome = "error" if at < 6 else "either"  # bytes 6, 7: the version
  return bytes(b), f"magic/version byte {at} -> {b[at]}", outcome


def _npy_header_length(data: bytes, rng: np.random.Generator,
                       info: dict) -> tuple[bytes, str, str]:
  new = int(rng.choice([0, 1, 65535, int.from_bytes(data[8:10], "little") + 16]))
  return data[:8] + new.to_bytes(2, "little") + data[10:], f"header length -> {new}", "error"


NPY_MUTATIONS = [
    simple_mutation(truncate, "error"), simple_mutation(flip),
    simple_mutation(append_garbage, "error"), _npy_nonfinite,
    empty_file,
    _npy_header("shape", ("(1000000000000, 3)", "(4611686018427387904, 3)", "(-1, 3)",
                          "(25, 3)", "(20, 3, 1000000000000)", "(9223372036854775807, 6)",
                          "(10, 3)"), "error"),
    _npy_header("shape", ("(3,)", "()", "abc", "(20, 3.5)", "[20, 3]", "(20, -3)"),
                "either"),
    _npy_header("descr", ("'<f4'", "'<c16'", "'|O'", "'<U2'", "'<f16'", "'xyz'", "'<i8'",
                          "'<f2'", "''"), "either"),
    _npy_header("fortran_order", ("True", "None", "1", "'x'"), "either"),
    _npy_magic, _npy_header_length,
]


def test_fuzz_npy(tmp_path: Path) -> None:
  """FUZZ_CASES["npy"] malformed .npy files (wrong dtype/shape, bad headers, huge shapes) through
  read_npy and read_cloud."""
  rng = np.random.default_rng([FUZZ_SEED, 4])
  arrays = _npy_arrays(rng)
  bases = [(label, _npy_bytes(a), {"binary": True}) for label, a, ok in arrays if ok == "result"]
  mutations = NPY_MUTATIONS + [_npy_array(arrays)] * 4  # every dtype/shape is likely drawn
  cases = file_cases(tmp_path, "npy", FUZZ_CASES["npy"], bases, mutations, BYTE_LEVEL, ".npy",
                      [io.read_npy, io.read_cloud], check_cloud, rng)
  run_cases(cases, FUZZ_CASES["npy"])


# ---------------------------------------------------------------------------------------------
# Poses: .xf, Stanford .conf, 3DMatch gt.log


def _rigid(rng: np.random.Generator) -> np.ndarray:
  t = np.eye(4)
  t[:3, :3] = Rotation.random(random_state=int(rng.integers(0, 2**31))).as_matrix()
  t[:3, 3] = rng.normal(size=3)
  return t


def _matrix_text(t: np.ndarray) -> str:
  return "\n".join(" ".join(f"{v:.17g}" for v in row) for row in t) + "\n"


def _pose_bases(tmp_path: Path, rng: np.random.Generator) -> list[tuple[str, bytes, dict]]:
  xf = io.write_xf(tmp_path / "base.xf", _rigid(rng)).read_bytes()
  quats = [Rotation.random(random_state=s).as_quat() for s in range(3)]
  conf = "camera 0 0 0 0 0 0 1\n\n" + "".join(
      f"bmesh scan{i}.ply {' '.join(f'{v:.9g}' for v in rng.normal(size=3))} "
      f"{' '.join(f'{v:.17g}' for v in q)}\n" for i, q in enumerate(quats))
  log = "".join(f"{i}\t{i + 1}\t4\n" + _matrix_text(_rigid(rng)) for i in range(3))
  return [("xf", xf, {"kind": "xf"}), ("conf", conf.encode(), {"kind": "conf"}),
          ("log", log.encode(), {"kind": "log"})]


def _pose_outcome(strict: tuple[str, ...]) -> Callable[[dict], str]:
  return lambda info: "error" if info["kind"] in strict else "either"


def _pose_lines(op: str, strict: tuple[str, ...]) -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    lines = [line for line in data.splitlines(keepends=True) if line.strip()]
    lines, label = edit_lines(lines, rng, op)
    outcome = _pose_outcome(strict)(info)
    if op == "swap" and label.split()[1] == label.split()[3]:
      outcome = "either"  # a line swapped with itself
    return b"".join(lines), label, outcome
  return mutate


def _pose_token(values: tuple[str, ...], strict: tuple[str, ...]) -> Callable:
  def mutate(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
    out, label = replace_token(data, rng, values)
    return out, label, _pose_outcome(strict)(info)
  return mutate


def _pose_matrix(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  """Not a rotation: scaled, sheared, reflected, last row changed (conf: a non-unit
  quaternion)."""
  how = str(rng.choice(["scale", "shear", "reflect", "last row", "zero"]))
  if info["kind"] == "conf":
    q = {"scale": "0 0 0 1.01", "shear": "0.5 0.5 0.5 0.1", "reflect": "0 0 0 -2",
         "last row": "nan 0 0 1", "zero": "0 0 0 0"}[how]
    return f"bmesh a.ply 0 0 0 {q}\n".encode(), f"quaternion {q}", "error"
  t = _rigid(rng)
  if how == "scale":
    t[:3, :3] *= 1.01
  elif how == "shear":
    t[0, 1] += 0.1
  elif how == "reflect":
    t[:3, 0] *= -1
  elif how == "last row":
    t[3, int(rng.integers(0, 3))] = 0.5
  else:
    t[:3, :3] = 0
  text = _matrix_text(t)
  if info["kind"] == "log":
    text = "0 1 2\n" + text
  return text.encode(), f"matrix {how}", "error"


def _pose_column(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  lines = data.split(b"\n")
  i = int(rng.integers(0, len(lines) - 1))
  while not lines[i].strip():
    i = (i + 1) % len(lines)
  lines[i] += b" 0"
  strict = info["kind"] != "conf" or lines[i].startswith(b"bmesh")
  return b"\n".join(lines), f"line {i} gained a column", "error" if strict else "either"


def _pose_layout(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  how = str(rng.choice(["crlf", "tabs", "blank lines", "no final newline"]))
  out = {"crlf": data.replace(b"\n", b"\r\n"), "tabs": data.replace(b" ", b"\t"),
         "blank lines": data.replace(b"\n", b"\n\n"), "no final newline": data.rstrip(b"\n")}[how]
  return out, how, "result"


def _pose_garbage(data: bytes, rng: np.random.Generator, info: dict) -> tuple[bytes, str, str]:
  return rng.bytes(int(rng.integers(1, 200))), "random bytes", "error"


POSE_MUTATIONS = [
    simple_mutation(truncate), simple_mutation(flip), _pose_lines("delete", ("xf", "log")),
    _pose_lines("duplicate", ("xf", "log")), _pose_lines("swap", ("xf",)),
    _pose_token(("nan", "inf", "-inf", "1e999"), ("xf", "log")),
    _pose_token(("abc", "0x10", "1,5", "--1", "\x00", "1..2"), ("xf", "log")),
    _pose_token(("1e308", "-0", "1.5", "99999999999999999999"), ()), _pose_matrix, _pose_column,
    _pose_layout, empty_file, _pose_garbage,
]
POSE_READERS = {"xf": io.read_xf, "conf": io.read_stanford_conf, "log": io.read_3dmatch_log}


def test_fuzz_poses(tmp_path: Path) -> None:
  """FUZZ_CASES["pose"] malformed .xf, .conf and gt.log files through their readers."""
  rng = np.random.default_rng([FUZZ_SEED, 5])
  bases = _pose_bases(tmp_path, rng)
  cases = []
  for i in range(FUZZ_CASES["pose"]):
    label, data, info = bases[i % 3]
    data, what, outcome = POSE_MUTATIONS[(i // 3) % len(POSE_MUTATIONS)](data, rng, info)
    path = write_file(tmp_path, f"pose{i:03d}.{info['kind']}", data)
    cases.append(Case(f"{path.name} {what}", lambda r=POSE_READERS[info["kind"]], p=path: r(p),
                      str(path), check_pose, outcome))
  run_cases(cases, FUZZ_CASES["pose"])


def test_case_counts_match_the_docstring() -> None:
  """The module docstring states the number of cases tried."""
  assert FUZZ_TOTAL_CASES == 776
  assert f"= {FUZZ_TOTAL_CASES} " in __doc__
  for fmt, n in (("PLY", "ply"), ("PCD", "pcd"), ("XYZ", "xyz"), ("NPY", "npy"),
                 ("pose", "pose"), ("compute_frames", "compute_frames"),
                 ("register", "register")):
    assert f"{FUZZ_CASES[n]} {fmt}" in " ".join(__doc__.split()), fmt


# ---------------------------------------------------------------------------------------------
# Regressions: one deterministic case per bug the fuzz found (each failed before its fix).



_PLY_XYZ = ("ply\nformat {fmt} 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\n")


def test_regression_ply_duplicate_property_names(tmp_path: Path) -> None:
  """plyfile's "two properties with same name" ValueError did not name the file."""
  p = write_file(tmp_path, "dup.ply", (_PLY_XYZ.format(fmt="ascii") + "property float x\n"
                                   "end_header\n0 0 0 0\n1 0 0 0\n0 1 0 0\n").encode())
  rejects(lambda: io.read_ply(p), str(p), "header", "same name")


def test_regression_ply_huge_binary_list_length(tmp_path: Path) -> None:
  """A corrupt binary list length made plyfile read (allocate) up to 16 GiB before failing."""
  head = _PLY_XYZ.format(fmt="binary_little_endian") + ("element face 1\nproperty list uint int "
                                                         "vertex_indices\nend_header\n")
  body = np.eye(3, dtype="<f4").tobytes() + np.array([2**32 - 16, 0, 1, 2], "<u4").tobytes()
  p = write_file(tmp_path, "list.ply", head.encode() + body)
  rejects(lambda: io.read_ply(p), str(p), "element 'face'")


def test_regression_ply_ascii_lists_with_undecodable_bytes(tmp_path: Path) -> None:
  """plyfile's row-by-row ascii reader raised UnicodeDecodeError on a non-ascii byte."""
  head = _PLY_XYZ.format(fmt="ascii") + ("element face 1\nproperty uchar flags\n"
                                         "property list uchar int vertex_indices\nend_header\n")
  p = write_file(tmp_path, "bytes.ply", head.encode() + b"0 0 0\n1 0 0\n0 1 0\n1 3 0 1 \xff2\n")
  rejects(lambda: io.read_ply(p), str(p), "body")


@pytest.mark.parametrize("length", ["nan", "1e999"])
def test_regression_ply_ascii_list_length_not_finite(tmp_path: Path, length: str) -> None:
  """A NaN/inf list length broke the error message itself (ValueError/OverflowError)."""
  head = _PLY_XYZ.format(fmt="ascii") + ("element face 1\nproperty list uchar int "
                                         "vertex_indices\nend_header\n")
  p = write_file(tmp_path, "len.ply", (head + f"0 0 0\n1 0 0\n0 1 0\n{length} 0 1 2\n").encode())
  rejects(lambda: io.read_ply(p), str(p), "element 'face' row 0")


def _pcd(tmp_path: Path, name: str, encoding: Encoding, points: int = 40) -> Path:
  pts = (np.arange(points * 3).reshape(points, 3) % 7 * 0.5 + 1).astype(np.float32)
  p = tmp_path / name
  PointCloud.from_xyz_points(pts).save(p, encoding=encoding)
  return p


def _edit(p: Path, old: bytes, new: bytes) -> Path:
  data = p.read_bytes()
  assert old in data
  p.write_bytes(data.replace(old, new, 1))
  return p


def test_regression_pcd_header_line_twice(tmp_path: Path) -> None:
  """An 11th header line pushed DATA out of pypcd4's header: the DATA line was then decoded as
  LZF sizes (1 GiB allocated)."""
  p = _edit(_pcd(tmp_path, "dup.pcd", Encoding.BINARY), b"WIDTH 40\n", b"WIDTH 40\nWIDTH 40\n")
  rejects(lambda: io.read_pcd(p), str(p), "WIDTH", "once")


def test_regression_pcd_many_comment_lines(tmp_path: Path) -> None:
  """Comment lines hid DATA from the size check (it read 16 raw lines): a huge POINTS then
  reached pypcd4 (OverflowError). Comments alone are fine."""
  p = _edit(_pcd(tmp_path, "comments.pcd", Encoding.BINARY), b"VERSION 0.7\n",
            b"VERSION 0.7\n" + b"# comment\n" * 30)
  assert len(io.read_pcd(p)) == 40
  _edit(_edit(p, b"POINTS 40\n", b"POINTS %d\n" % 2**62), b"WIDTH 40\n", b"WIDTH %d\n" % 2**62)
  rejects(lambda: io.read_pcd(p), str(p), "POINTS")


@pytest.mark.parametrize("points", [38, 10**12])
def test_regression_pcd_compressed_point_count(tmp_path: Path, points: int) -> None:
  """binary_compressed with a POINTS that differs from what is stored: fewer gave silently
  scrambled points (pypcd4 slices its field-major buffer by POINTS), more allocated POINTS rows
  first (23 TiB for 10**12)."""
  p = _pcd(tmp_path, "lzf.pcd", Encoding.BINARY_COMPRESSED)
  _edit(_edit(p, b"POINTS 40\n", b"POINTS %d\n" % points), b"WIDTH 40\n", b"WIDTH %d\n" % points)
  rejects(lambda: io.read_pcd(p), str(p), "POINTS", "uncompressed size of 480 bytes")


@pytest.mark.parametrize("data", [b"DATA binary_compressed\n", b"DATA \n"])
def test_regression_pcd_data_mode(tmp_path: Path, data: bytes) -> None:
  """A binary body under DATA binary_compressed (or an empty DATA, which pypcd4 reads as
  binary_compressed) had its first 8 bytes (here the floats 1.0, 1.5) taken as LZF sizes:
  3 GiB allocated."""
  p = _edit(_pcd(tmp_path, "mode.pcd", Encoding.BINARY), b"DATA binary\n", data)
  rejects(lambda: io.read_pcd(p), str(p), "DATA")


def test_regression_pcd_huge_count(tmp_path: Path) -> None:
  """COUNT 10**12 hung pypcd4 (one numpy field name per value) under DATA ascii."""
  p = _edit(_pcd(tmp_path, "count.pcd", Encoding.ASCII), b"COUNT 1 1 1\n",
            b"COUNT 1 1000000000000 1\n")
  rejects(lambda: io.read_pcd(p), str(p), "COUNT")


@pytest.mark.parametrize("how", ["header length 1", "negative shape", "smaller shape",
                                 "trailing bytes"])
def test_regression_npy_header(tmp_path: Path, how: str) -> None:
  """numpy's TokenError (garbled header) and OverflowError (negative shape) escaped read_npy; a
  header shape smaller than the data, or bytes after it, silently dropped data."""
  data = _npy_bytes(np.arange(60.0).reshape(20, 3))
  data = {"header length 1": data[:8] + b"\x01\x00" + data[10:],
          "negative shape": data.replace(b"(20, 3)", b"(20,-3)"),
          "smaller shape": data.replace(b"(20, 3)", b"(10, 3)"),
          "trailing bytes": data + b"\x00" * 24}[how]
  p = write_file(tmp_path, "a.npy", data)
  rejects(lambda: io.read_npy(p), str(p))


def test_regression_xyz_gz_corrupt_deflate(tmp_path: Path) -> None:
  """A corrupt deflate stream raised zlib.error (not an OSError) from read_xyz."""
  p = write_file(tmp_path, "bad.xyz.gz",
                 bytes.fromhex("1f8b0800000000000003") + b"\x07" + bytes(16))
  rejects(lambda: io.read_xyz(p), str(p), "gzip")


def test_regression_empty_path() -> None:
  """"" became Path("."): the message was ".: is a directory, not a file"."""
  rejects(lambda: io.read_cloud(""), "''", "empty path")
