"""Readers and writers: round trips against independent references, and every bad input."""

from __future__ import annotations

import gzip

import numpy as np
import plyfile
import pytest
from pypcd4 import Encoding, PointCloud
from scipy.spatial.transform import Rotation

from lrf_jax import io
import builtins
import os
from lrf_jax.io import ply as ply_module


def _rng(seed=0):
  return np.random.default_rng(seed)


def _cloud(n=50, seed=0):
  return _rng(seed).normal(size=(n, 3))


def _tetra():
  pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
  faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
  return pts, faces


def _raises(exc, path, *fragments):
  """pytest.raises that also checks the message names the file and the given fragments."""

  class _Ctx:

    def __enter__(self):
      self._ctx = pytest.raises(exc)
      self.info = self._ctx.__enter__()
      return self.info

    def __exit__(self, *a):
      out = self._ctx.__exit__(*a)
      msg = str(self.info.value)
      assert str(path) in msg, msg
      for f in fragments:
        assert f in msg, f"{f!r} not in {msg!r}"
      return out

  return _Ctx()


# ---------------------------------------------------------------------------------------------
# PLY


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
  pts, faces = _tetra()
  normals = pts - pts.mean(0)
  path = io.write_ply(tmp_path / "t.ply", pts, faces, normals, binary=binary, dtype="float64")
  m = io.read_ply(path)
  np.testing.assert_array_equal(m.points, pts)
  np.testing.assert_array_equal(m.faces, faces)
  np.testing.assert_array_equal(m.normals, normals)
  assert m.points.dtype == np.float64 and m.faces.dtype == np.int64
  assert m.text is (not binary)


def test_ply_float32_cloud_without_faces(tmp_path):
  pts = _cloud()
  m = io.read_ply(io.write_ply(tmp_path / "c.ply", pts))
  assert m.faces is None and m.normals is None
  np.testing.assert_allclose(m.points, pts, rtol=1e-6, atol=1e-6)


def _write_with_plyfile(path, text, n=20, ragged=True):
  """A PLY with colours, triangles and an extra ragged list element, written by plyfile."""
  rng = _rng(1)
  v = np.empty(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                         ("confidence", "f8")])
  for a in "xyz":
    v[a] = rng.normal(size=n)
  v["red"] = rng.integers(0, 255, n)
  v["confidence"] = rng.uniform(size=n)
  f = np.empty(n - 2, dtype=[("vertex_indices", "O")])
  f["vertex_indices"] = [np.array([i, i + 1, i + 2], dtype=np.int32) for i in range(n - 2)]
  grid = np.empty(3 * n, dtype=[("vertex_indices", "O")])
  grid["vertex_indices"] = [np.array([i // 3] if (i % 3 or not ragged) else [], dtype=np.int32)
                            for i in range(3 * n)]
  plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"),
                   plyfile.PlyElement.describe(f, "face"),
                   plyfile.PlyElement.describe(grid, "range_grid")],
                  text=text, comments=["made by test"], obj_info=["num_cols 3"]).write(str(path))
  return v, f, grid


@pytest.mark.parametrize("text", [True, False])
@pytest.mark.parametrize("ragged", [True, False])
def test_ply_matches_plyfile_and_keeps_extra_elements(tmp_path, text, ragged):
  path = tmp_path / "x.ply"
  v, f, grid = _write_with_plyfile(path, text, ragged=ragged)
  m = io.read_ply(path)
  np.testing.assert_array_equal(m.points, np.stack([v[a] for a in "xyz"], 1).astype(np.float64))
  np.testing.assert_array_equal(m.faces, np.stack(f["vertex_indices"]))
  np.testing.assert_array_equal(m.vertex_attributes["red"], v["red"])
  np.testing.assert_array_equal(m.vertex_attributes["confidence"], v["confidence"])
  assert m.vertex_attributes["red"].dtype == np.uint8
  kept = m.elements["range_grid"]["vertex_indices"]
  assert len(kept) == len(grid)
  for got, want in zip(kept, grid["vertex_indices"]):
    np.testing.assert_array_equal(got, want)
  assert m.comments == ("made by test",) and m.obj_info == ("num_cols 3",)


def test_ply_without_elements_reads_the_same_geometry(tmp_path):
  path = tmp_path / "x.ply"
  _write_with_plyfile(path, True, ragged=True)
  full, bare = io.read_ply(path), io.read_ply(path, elements=False)
  np.testing.assert_array_equal(bare.points, full.points)
  np.testing.assert_array_equal(bare.faces, full.faces)
  assert "range_grid" in full.elements and bare.elements == {}
  np.testing.assert_array_equal(io.read_cloud(path).points, full.points)
  lines = path.read_text().splitlines()
  (tmp_path / "short.ply").write_text("\n".join(lines[:-2]) + "\n")  # range_grid rows missing
  with pytest.raises(ValueError, match="range_grid"):
    io.read_ply(tmp_path / "short.ply", elements=False)


def test_ascii_lists_with_odd_whitespace_match_plyfile(tmp_path):
  # The vectorised ascii reader counts tokens per row from the bytes; tabs, runs of spaces,
  # CRLF line ends and lists of 0..4 values must split exactly as plyfile's row-by-row reader.
  rng = _rng(3)
  lens = rng.integers(0, 5, 200)
  seps = [" ", "\t", "  ", " \t "]
  rows = []
  for i, k in enumerate(lens):
    vals = [str(k)] + [str(int(x)) for x in rng.integers(0, 3, k)]
    rows.append(seps[i % 4].join(vals) + (" " if i % 3 == 0 else "") + ("\r" if i % 5 == 0 else ""))
  head = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
          f"property float z\nelement grid {len(rows)}\nproperty list uchar int idx\nend_header\n")
  path = tmp_path / "odd.ply"
  path.write_bytes((head + "0 0 0\n1 0 0\n0 1 0\n" + "\n".join(rows) + "\n").encode())
  got = io.read_ply(path).elements["grid"]["idx"]
  want = plyfile.PlyData.read(str(path))["grid"]["idx"]
  assert len(got) == len(want) == len(rows)
  for g, w in zip(got, want):
    np.testing.assert_array_equal(g, w)


def test_ply_polygons_are_fan_triangulated(tmp_path):
  path = tmp_path / "quad.ply"
  path.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
                  "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
                  "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 0 0\n4 0 1 2 3\n3 1 4 2\n")
  m = io.read_ply(path)
  np.testing.assert_array_equal(m.faces, [[1, 4, 2], [0, 1, 2], [0, 2, 3]])


_HEADER = ("ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
           "property float z\nelement face {f}\nproperty list uchar int vertex_indices\n"
           "end_header\n")


def _ascii_ply(path, rows, faces=(), n=None, f=None):
  body = "".join(r + "\n" for r in rows) + "".join(r + "\n" for r in faces)
  path.write_text(_HEADER.format(n=len(rows) if n is None else n,
                                 f=len(faces) if f is None else f) + body)
  return path


def test_ply_errors(tmp_path):
  good = ["0 0 0", "1 0 0", "0 1 0"]
  with _raises(FileNotFoundError, tmp_path / "missing.ply"):
    io.read_ply(tmp_path / "missing.ply")
  p = tmp_path / "garbage.ply"
  p.write_bytes(b"hello world\n")
  with _raises(ValueError, p, "header"):
    io.read_ply(p)
  p = tmp_path / "badformat.ply"
  p.write_text("ply\nformat foo 1.0\nend_header\n")
  with _raises(ValueError, p, "header"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "short.ply", good[:2], n=3)
  with _raises(ValueError, p, "element 'vertex'", "3 rows", "2 rows"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "long.ply", good, ["3 0 1 2"], n=2, f=1)
  with _raises(ValueError, p, "element 'face'"):  # the third vertex row is read as a face
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "extra.ply", good + ["3 0 1 2"], n=3, f=0)
  with _raises(ValueError, p, "body", "more non-empty rows"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "cols.ply", ["0 0 0", "1 0", "0 1 0"])
  with _raises(ValueError, p, "element 'vertex'"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "nan.ply", ["0 0 0", "nan 0 0", "0 1 0"])
  with _raises(ValueError, p, "finite", "row 1"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "inf.ply", ["0 0 0", "1 0 0", "0 inf 0"])
  with _raises(ValueError, p, "finite", "row 2"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "empty.ply", [])
  with _raises(ValueError, p, "empty cloud"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "index.ply", good, ["3 0 1 7"])
  with _raises(ValueError, p, "element 'face'", "[0, 3)", "index 7"):
    io.read_ply(p)
  p = _ascii_ply(tmp_path / "listlen.ply", good, ["3 0 1"])
  with _raises(ValueError, p, "element 'face' row 0"):
    io.read_ply(p)
  p = tmp_path / "noxyz.ply"
  p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
               "property float w\nend_header\n0 0 0\n")
  with _raises(ValueError, p, "element 'vertex'", "x, y, z", "missing z"):
    io.read_ply(p)
  p = tmp_path / "novertex.ply"
  p.write_text("ply\nformat ascii 1.0\nelement point 1\nproperty float x\nend_header\n0\n")
  with _raises(ValueError, p, "'vertex' element", "point"):
    io.read_ply(p)


def test_ply_binary_corrupt_and_truncated(tmp_path):
  pts, faces = _tetra()
  path = io.write_ply(tmp_path / "b.ply", pts, faces)
  data = path.read_bytes()
  for cut in (10, 60):  # inside the vertex block, inside the face block
    p = tmp_path / f"cut{cut}.ply"
    p.write_bytes(data[:len(data) - cut])
    with _raises(ValueError, p, "element"):
      io.read_ply(p)
  p = tmp_path / "trailing.ply"
  p.write_bytes(data + b"\x00" * 8)
  with _raises(ValueError, p, "8 more bytes"):
    io.read_ply(p)
  p = tmp_path / "badcount.ply"  # header claims 5 vertices: faces are read from the wrong place
  p.write_bytes(data.replace(b"element vertex 4", b"element vertex 5"))
  with pytest.raises(ValueError, match=str(p.name)):
    io.read_ply(p)


def test_write_ply_rejects_bad_input(tmp_path):
  pts, faces = _tetra()
  with pytest.raises(ValueError, match="finite"):
    io.write_ply(tmp_path / "a.ply", np.where(pts == 1, np.nan, pts))
  with pytest.raises(ValueError, match=r"\[0, 4\)"):
    io.write_ply(tmp_path / "a.ply", pts, faces + 1)
  with pytest.raises(ValueError, match=r"\(n, 3\)"):
    io.write_ply(tmp_path / "a.ply", pts[:, :2])


# ---------------------------------------------------------------------------------------------
# PCD, XYZ, NPY, dispatch


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
def test_pcd_encodings(tmp_path, encoding):
  pts = _compressible()
  nrm = pts[::-1] * 0.5
  path = tmp_path / "c.pcd"
  PointCloud.from_points(np.concatenate([pts, nrm], 1),
                         ("x", "y", "z", "normal_x", "normal_y", "normal_z"),
                         (np.float32,) * 6).save(path, encoding=encoding)
  assert f"DATA {encoding.value}".encode() in path.read_bytes()[:300]
  c = io.read_pcd(path)
  np.testing.assert_allclose(c.points, pts, rtol=1e-6)
  np.testing.assert_allclose(c.normals, nrm, rtol=1e-6)
  assert c.faces is None and c.points.dtype == np.float64


def _compressible(n=50):
  """Points with repeated values (pypcd4 silently falls back to binary when LZF cannot shrink
  the data, so random points would not exercise binary_compressed)."""
  i = np.arange(n)
  return np.stack([i % 5, i % 3, np.zeros(n)], axis=1).astype(np.float32)


def test_pcd_errors(tmp_path):
  pts = _compressible()
  p = tmp_path / "xy.pcd"
  PointCloud.from_points(pts[:, :2], ("x", "y"), (np.float32,) * 2).save(p)
  with _raises(ValueError, p, "FIELDS", "missing z"):
    io.read_pcd(p)
  p = tmp_path / "cut.pcd"
  PointCloud.from_xyz_points(pts).save(p, encoding=Encoding.BINARY)
  p.write_bytes(p.read_bytes()[:-30])
  with _raises(ValueError, p, "DATA binary", "50 points"):
    io.read_pcd(p)
  p = tmp_path / "lzf.pcd"
  PointCloud.from_xyz_points(pts).save(p, encoding=Encoding.BINARY_COMPRESSED)
  p.write_bytes(p.read_bytes()[:-40])  # truncated LZF stream
  with _raises(ValueError, p, "DATA binary_compressed", "50 points"):
    io.read_pcd(p)
  nan = pts.copy()
  nan[3] = np.nan
  p = tmp_path / "nan.pcd"
  PointCloud.from_xyz_points(nan).save(p)
  with _raises(ValueError, p, "finite", "row 3"):
    io.read_pcd(p)
  assert len(io.read_pcd(p, drop_nonfinite=True)) == len(pts) - 1
  p = tmp_path / "empty.pcd"
  PointCloud.from_xyz_points(np.zeros((0, 3), np.float32)).save(p)
  with _raises(ValueError, p, "empty cloud"):
    io.read_pcd(p)


def test_xyz_plain_and_gz(tmp_path):
  pts = _cloud()
  text = "# comment\n" + "".join(f"{a:.17g} {b:.17g} {c:.17g} 7 8\n" for a, b, c in pts)
  (tmp_path / "c.xyz").write_text(text)
  with gzip.open(tmp_path / "c.txt.gz", "wt") as f:
    f.write(text)
  for name in ("c.xyz", "c.txt.gz"):
    np.testing.assert_array_equal(io.read_xyz(tmp_path / name).points, pts)
    np.testing.assert_array_equal(io.read_cloud(tmp_path / name).points, pts)


def test_xyz_errors(tmp_path):
  cases = {"two.xyz": ("1 2\n3 4\n", "3 columns"), "word.xyz": ("1 2 3\n1 x 3\n", "rows"),
           "ragged.xyz": ("1 2 3\n1 2 3 4\n", "rows"), "empty.xyz": ("# nothing\n", "empty"),
           "nan.xyz": ("1 2 3\nnan 1 1\n", "finite")}
  for name, (text, fragment) in cases.items():
    p = tmp_path / name
    p.write_text(text)
    with _raises(ValueError, p, fragment):
      io.read_xyz(p)
  p = tmp_path / "broken.xyz.gz"
  p.write_bytes(gzip.compress(b"1 2 3\n" * 100)[:-20])
  with _raises(ValueError, p):
    io.read_xyz(p)


def test_npy(tmp_path):
  pts = _cloud()
  np.save(tmp_path / "a.npy", pts)
  np.save(tmp_path / "b.npy", np.concatenate([pts, pts], 1))
  np.testing.assert_array_equal(io.read_npy(tmp_path / "a.npy").points, pts)
  c = io.read_cloud(tmp_path / "b.npy")
  np.testing.assert_array_equal(c.normals, pts)
  np.save(tmp_path / "bad.npy", pts[:, :2])
  with _raises(ValueError, tmp_path / "bad.npy", "(n, 3)", "(50, 2)"):
    io.read_npy(tmp_path / "bad.npy")
  np.save(tmp_path / "empty.npy", np.zeros((0, 3)))
  with _raises(ValueError, tmp_path / "empty.npy", "empty cloud"):
    io.read_npy(tmp_path / "empty.npy")


def test_read_cloud_dispatch(tmp_path):
  pts, faces = _tetra()
  c = io.read_cloud(io.write_ply(tmp_path / "m.ply", pts, faces))
  np.testing.assert_array_equal(c.faces, faces)
  PointCloud.from_xyz_points(pts.astype(np.float32)).save(tmp_path / "m.pcd")
  np.testing.assert_array_equal(io.read_cloud(tmp_path / "m.pcd").points, pts)
  for bad in ("m.obj", "m.ply.gz"):
    (tmp_path / bad).write_bytes(b"x")
    with _raises(ValueError, tmp_path / bad, "suffix"):
      io.read_cloud(tmp_path / bad)
  with _raises(FileNotFoundError, tmp_path / "none.ply"):
    io.read_cloud(tmp_path / "none.ply")


# ---------------------------------------------------------------------------------------------
# Poses


def _rigid(seed=0):
  t = np.eye(4)
  t[:3, :3] = Rotation.random(random_state=seed).as_matrix()
  t[:3, 3] = _rng(seed).normal(size=3)
  return t


def test_xf_round_trip(tmp_path):
  t = _rigid()
  np.testing.assert_array_equal(io.read_xf(io.write_xf(tmp_path / "a.xf", t)), t)


def test_xf_errors(tmp_path):
  t = _rigid()

  def write(name, m):
    p = tmp_path / name
    p.write_text("\n".join(" ".join(str(v) for v in row) for row in m) + "\n")
    return p

  with _raises(ValueError, write("a.xf", t[:3]), "4x4", "3x4"):
    io.read_xf(tmp_path / "a.xf")
  with _raises(ValueError, write("b.xf", t[:, :3]), "4x4", "4x3"):
    io.read_xf(tmp_path / "b.xf")
  scaled = t.copy()
  scaled[:3, :3] *= 1.01
  with _raises(ValueError, write("c.xf", scaled), "orthonormal", "not a rigid"):
    io.read_xf(tmp_path / "c.xf")
  mirror = t.copy()
  mirror[:3, 0] *= -1
  with _raises(ValueError, write("d.xf", mirror), "det R = +1", "reflection"):
    io.read_xf(tmp_path / "d.xf")
  row = t.copy()
  row[3, 0] = 0.5
  with _raises(ValueError, write("e.xf", row), "last row"):
    io.read_xf(tmp_path / "e.xf")
  (tmp_path / "f.xf").write_text("1 0 0 0\n0 1 0 0\n0 0 one 0\n0 0 0 1\n")
  with _raises(ValueError, tmp_path / "f.xf", "numbers"):
    io.read_xf(tmp_path / "f.xf")
  nan = t.copy()
  nan[0, 3] = np.nan
  with _raises(ValueError, write("g.xf", nan), "finite"):
    io.read_xf(tmp_path / "g.xf")
  with _raises(FileNotFoundError, tmp_path / "h.xf"):
    io.read_xf(tmp_path / "h.xf")


def test_quaternion_to_matrix_matches_scipy():
  for seed in range(5):
    q = Rotation.random(random_state=seed).as_quat()  # scalar last
    np.testing.assert_allclose(io.quaternion_to_matrix(q),
                               Rotation.from_quat(q).as_matrix(), atol=1e-12)


def test_stanford_conf_uses_conjugate_rotation(tmp_path):
  q = Rotation.random(random_state=3).as_quat()
  p = tmp_path / "s.conf"
  p.write_text("camera 0 0 0 0 0 0 1\n\nbmesh a.ply 0 0 0 0 0 0 1\n"
               f"bmesh b.ply 1 2 3 {q[0]} {q[1]} {q[2]} {q[3]}\n")
  poses = io.read_stanford_conf(p)
  assert list(poses) == ["a.ply", "b.ply"]
  np.testing.assert_array_equal(poses["a.ply"], np.eye(4))
  np.testing.assert_allclose(poses["b.ply"][:3, :3], Rotation.from_quat(q).as_matrix().T,
                             atol=1e-12)
  np.testing.assert_array_equal(poses["b.ply"][:3, 3], [1, 2, 3])


def test_stanford_conf_errors(tmp_path):
  cases = {"norm": ("bmesh a.ply 0 0 0 0 0 0 2\n", "unit norm", "norm 2"),
           "zero": ("bmesh a.ply 0 0 0 0 0 0 0\n", "unit norm", "norm 0"),
           "nan": ("bmesh a.ply 0 0 0 0 nan 0 1\n", "quaternion"),
           "short": ("bmesh a.ply 0 0 0 0 0 1\n", "line 1", "9 tokens", "8 tokens"),
           "word": ("frobnicate a.ply 0 0 0 0 0 0 1\n", "line 1", "bmesh"),
           "dup": ("bmesh a.ply 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\n", "line 2", "once"),
           "empty": ("camera 0 0 0 0 0 0 1\n", "bmesh", "none")}
  for name, (text, *fragments) in cases.items():
    p = tmp_path / f"{name}.conf"
    p.write_text(text)
    with _raises(ValueError, p, *fragments):
      io.read_stanford_conf(p)


def test_3dmatch_log(tmp_path):
  ts = [_rigid(s) for s in range(3)]
  text = "".join(f"{i}\t{i + 1}\t60\n" + "\n".join(" ".join(f"{v:.17g}" for v in row)
                                                  for row in t) + "\n"
                 for i, t in enumerate(ts))
  p = tmp_path / "gt.log"
  p.write_text(text)
  entries = io.read_3dmatch_log(p)
  assert [(e.i, e.j, e.n) for e in entries] == [(0, 1, 60), (1, 2, 60), (2, 3, 60)]
  for e, t in zip(entries, ts):
    np.testing.assert_array_equal(e.transform, t)
  lines = text.splitlines()
  bad = {"trunc": ("\n".join(lines[:-1]), "multiple of 5"),
         "head": ("\n".join(["0 1"] + lines[1:]), "record 0", "three integers"),
         "wide": ("\n".join(lines[:1] + [r + " 0" for r in lines[1:5]] + lines[5:]),
                  "record 0", "4x4", "4x5"),
         "rigid": ("\n".join(lines[:1] + ["2 0 0 0"] + lines[2:]), "record 0", "orthonormal")}
  for name, (content, *fragments) in bad.items():
    q = tmp_path / f"{name}.log"
    q.write_text(content + "\n")
    with _raises(ValueError, q, *fragments):
      io.read_3dmatch_log(q)


def test_pcd_point_count_must_match_what_is_stored(tmp_path):
  pts = np.random.default_rng(0).normal(size=(1000, 3)).astype(np.float32)
  for enc in (Encoding.BINARY, Encoding.ASCII):
    p = tmp_path / f"lie_{enc.value}.pcd"
    PointCloud.from_xyz_points(pts).save(p, encoding=enc)
    raw = p.read_bytes()
    for lie in (b"POINTS 10\n", b"POINTS 1000000000000\n"):
      fake = raw.replace(b"POINTS 1000\n", lie).replace(b"WIDTH 1000\n",
                                                          lie.replace(b"POINTS", b"WIDTH"))
      p.write_bytes(fake)
      with _raises(ValueError, p, "POINTS"):
        io.read_pcd(p)


def test_npy_rejects_huge_shapes_and_non_real_dtypes(tmp_path):
  np.save(tmp_path / "huge.npy", np.zeros((4, 3)))
  raw = (tmp_path / "huge.npy").read_bytes().replace(b"(4, 3)", b"(4000000000000, 3)")
  (tmp_path / "huge.npy").write_bytes(raw)
  with _raises(ValueError, tmp_path / "huge.npy"):
    io.read_npy(tmp_path / "huge.npy")
  for name, arr in (("c.npy", np.zeros((5, 3), complex)), ("b.npy", np.zeros((5, 3), bool)),
                    ("s.npy", np.full((5, 3), "a"))):
    np.save(tmp_path / name, arr)
    with _raises(ValueError, tmp_path / name, "dtype"):
      io.read_npy(tmp_path / name)


# ---------------- readers: PCL's normal names, triangle elements, NaN normals, unreadable files


_VERTS = "0 0 0 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0 1\n"


_XYZ = "property float x\nproperty float y\nproperty float z\n"


def test_ply_reads_pcl_normal_names(tmp_path):
  p = tmp_path / "pcl.ply"
  p.write_text("ply\nformat ascii 1.0\nelement vertex 3\n" + _XYZ
               + "property float normal_x\nproperty float normal_y\nproperty float normal_z\n"
               "end_header\n" + _VERTS)
  m = io.read_ply(p)
  np.testing.assert_array_equal(m.normals, np.tile([0.0, 0.0, 1.0], (3, 1)))
  assert m.vertex_attributes == {}
  np.testing.assert_array_equal(io.read_cloud(p).normals, m.normals)


@pytest.mark.parametrize("binary", [False, True])
def test_ply_reads_a_triangle_element(tmp_path, binary):
  import plyfile
  pts, faces = _tetra()
  vertex = np.array([tuple(r) for r in pts], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
  tri = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
  tri["vertex_indices"] = faces
  p = tmp_path / "tri.ply"
  plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"),
                   plyfile.PlyElement.describe(tri, "triangle")], text=not binary).write(str(p))
  m = io.read_ply(p)
  np.testing.assert_array_equal(m.faces, faces)
  assert "triangle" not in m.elements
  np.testing.assert_array_equal(io.read_cloud(p).faces, faces)


def test_ply_refuses_two_non_empty_face_elements(tmp_path):
  p = tmp_path / "both.ply"
  p.write_text("ply\nformat ascii 1.0\nelement vertex 3\n" + _XYZ
               + "element face 1\nproperty list uchar int vertex_indices\n"
               "element triangle 1\nproperty list uchar int vertex_indices\nend_header\n"
               "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 2 1\n")
  with pytest.raises(ValueError, match=r"both\.ply: elements: expected one face element"):
    io.read_ply(p)


def test_ply_triangle_element_without_a_face_list_stays_an_element(tmp_path):
  p = tmp_path / "other.ply"
  p.write_text("ply\nformat ascii 1.0\nelement vertex 3\n" + _XYZ
               + "element triangle 1\nproperty float quality\nend_header\n"
               "0 0 0\n1 0 0\n0 1 0\n0.5\n")
  m = io.read_ply(p)
  assert m.faces is None and m.elements["triangle"]["quality"].tolist() == [0.5]


def test_ply_nan_normals_are_nan_rows(tmp_path):
  p = tmp_path / "nan.ply"
  p.write_text("ply\nformat ascii 1.0\nelement vertex 3\n" + _XYZ
               + "property float nx\nproperty float ny\nproperty float nz\nend_header\n"
               "0 0 0 0 0 1\n1 0 0 nan 0 1\n0 1 0 inf 0 0\n")
  m = io.read_ply(p)
  assert len(m.points) == 3
  np.testing.assert_array_equal(m.normals[0], [0, 0, 1])
  assert np.isnan(m.normals[1:]).all()


def _pcd(tmp_path, rows):
  p = tmp_path / "c.pcd"
  p.write_text("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\n"
               "SIZE 4 4 4 4 4 4\nTYPE F F F F F F\nCOUNT 1 1 1 1 1 1\n"
               f"WIDTH {len(rows)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(rows)}\n"
               "DATA ascii\n" + "".join(r + "\n" for r in rows))
  return p


def test_pcd_drop_nonfinite_keeps_points_with_nan_normals(tmp_path):
  p = _pcd(tmp_path, ["0 0 0 0 0 1", "1 0 0 nan nan nan", "nan nan nan nan nan nan",
                      "0 1 0 0 0 1"])
  c = io.read_pcd(p, drop_nonfinite=True)
  np.testing.assert_array_equal(c.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
  np.testing.assert_array_equal(c.normals[[0, 2]], [[0, 0, 1], [0, 0, 1]])
  assert np.isnan(c.normals[1]).all()


def test_pcd_nan_normals_without_drop_are_nan_rows(tmp_path):
  p = _pcd(tmp_path, ["0 0 0 0 0 1", "1 0 0 nan 0 1", "0 1 0 0 0 1"])
  c = io.read_pcd(p)
  assert len(c.points) == 3 and np.isnan(c.normals[1]).all()
  with pytest.raises(ValueError, match="fields x/y/z: expected finite coordinates"):
    io.read_pcd(_pcd(tmp_path, ["0 0 0 0 0 1", "nan 0 0 0 0 1"]))


def test_npy_nan_normals_are_nan_rows(tmp_path):
  arr = np.zeros((3, 6))
  arr[:, 5] = 1
  arr[1, 3] = np.nan
  np.save(tmp_path / "c.npy", arr)
  c = io.read_npy(tmp_path / "c.npy")
  assert np.isnan(c.normals[1]).all() and np.isfinite(c.normals[[0, 2]]).all()


def _files(tmp_path):
  pts, faces = _tetra()
  out = {"ply": io.write_ply(tmp_path / "a.ply", pts, faces),
         "pcd": _pcd(tmp_path, ["0 0 0 0 0 1", "1 0 0 0 0 1"]),
         "xyz": tmp_path / "a.xyz", "npy": tmp_path / "a.npy"}
  out["xyz"].write_text("0 0 0\n1 0 0\n")
  np.save(out["npy"], pts)
  return out


@pytest.mark.parametrize("kind", ["ply", "pcd", "xyz", "npy"])
def test_unreadable_file_is_a_value_error_naming_it(tmp_path, monkeypatch, kind):
  path = _files(tmp_path)[kind]
  real_open = builtins.open

  def denied(file, *args, **kwargs):  # what the OS says without read permission
    if isinstance(file, (str, os.PathLike)) and os.fspath(file) == os.fspath(path):
      raise PermissionError(13, "Permission denied", os.fspath(path))
    return real_open(file, *args, **kwargs)

  monkeypatch.setattr(builtins, "open", denied)
  with pytest.raises(ValueError, match="expected a readable file, found PermissionError") as e:
    io.read_cloud(path)
  assert str(path) in str(e.value)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="needs a POSIX user whom file permissions bind (not root)")
def test_unreadable_file_by_permissions(tmp_path):
  path = _files(tmp_path)["ply"]
  path.chmod(0)
  with pytest.raises(ValueError, match="expected a readable file"):
    io.read_cloud(path)


# ---------------------------------------------------------------------------------- PLY headers


def test_ply_without_end_header_stops_at_the_cap(tmp_path, monkeypatch):
  monkeypatch.setattr(ply_module, "MAX_HEADER_BYTES", 4096)
  p = tmp_path / "noend.ply"
  p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
                + b"comment x\n" * 2000)
  with pytest.raises(ValueError, match=r"noend\.ply: header: .* no end_header within 4096 bytes"):
    io.read_ply(p)


def test_ply_header_longer_than_the_cap_is_refused(tmp_path, monkeypatch):
  monkeypatch.setattr(ply_module, "MAX_HEADER_BYTES", 4096)
  pts, faces = _tetra()
  p = io.write_ply(tmp_path / "long.ply", pts, faces, comments=("a" * 5000,))
  with pytest.raises(ValueError, match="no end_header within 4096 bytes"):
    io.read_ply(p)
  monkeypatch.setattr(ply_module, "MAX_HEADER_BYTES", 1 << 20)
  m = io.read_ply(p)
  assert m.comments == ("a" * 5000,)
  np.testing.assert_array_equal(m.faces, faces)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("newline", [b"\n", b"\r\n", b"\r"])
def test_ply_header_newlines_and_exact_cap(tmp_path, monkeypatch, binary, newline):
  pts, faces = _tetra()
  p = io.write_ply(tmp_path / "t.ply", pts, faces, binary=binary, comments=("c1", "c2"))
  raw = p.read_bytes()
  cut = raw.index(b"end_header\n") + len(b"end_header\n")
  header = raw[:cut].replace(b"\n", newline)  # the body (ascii rows too) keeps its LFs
  p.write_bytes(header + raw[cut:])
  monkeypatch.setattr(ply_module, "MAX_HEADER_BYTES", len(header))  # exactly fits
  m = io.read_ply(p)
  np.testing.assert_allclose(m.points, pts)
  np.testing.assert_array_equal(m.faces, faces)
  assert m.comments == ("c1", "c2")
  monkeypatch.setattr(ply_module, "MAX_HEADER_BYTES", len(header) - 1)
  with pytest.raises(ValueError, match="no end_header within"):
    io.read_ply(p)


def test_ply_header_errors_keep_their_line(tmp_path):
  p = tmp_path / "bad.ply"
  p.write_text("ply\nformat ascii 1.0\nelement vertex x\nend_header\n")
  with pytest.raises(ValueError, match=r"bad\.ply: header line 3: .*integer count"):
    io.read_ply(p)
  p.write_text("ply\nformat ascii 1.0\nelement vertex 1\n" + _XYZ)  # ends without end_header
  with pytest.raises(ValueError, match="early end-of-file"):
    io.read_ply(p)
  p.write_bytes(b"plx\n")
  with pytest.raises(ValueError, match="header line 1: .*starting with 'ply', found b'plx"):
    io.read_ply(p)


_ASCII_HEAD = "ply\nformat ascii 1.0\nelement vertex 3\n"


@pytest.mark.parametrize("props,rows,where,found", [
    ("property float x\nproperty float y\nproperty float z\nproperty uchar red\n",
     ["0 0 0 10", "1 0 0 300", "0 1 0 20"], "row 1 property 'red'", "found 300"),
    ("property int x\nproperty int y\nproperty int z\n",
     ["0 0 0", "1 0 0", "0 0.7 0"], "row 2 property 'y'", "found 0.69999999999999996"),
    ("property uchar x\nproperty float y\nproperty float z\n",
     ["0 0 0", "-1 0 0", "1 1 0"], "row 1 property 'x'", "found -1"),
])
def test_ascii_ply_integer_out_of_range_or_fractional_is_refused(tmp_path, props, rows, where,
                                                                  found):
  """An ascii `uchar` holding 300 read as 44 and an `int` holding 0.7 as 0 (plyfile raises):
  the message names the file, element, row and property."""
  p = tmp_path / "bad.ply"
  p.write_text(_ASCII_HEAD + props + "end_header\n" + "\n".join(rows) + "\n")
  with pytest.raises(ValueError, match=rf"bad\.ply: element 'vertex' {where}: expected an "
                                       rf"integer in .*{found}"):
    io.read_ply(p)


def test_ascii_ply_face_index_out_of_range_is_refused(tmp_path):
  p = tmp_path / "faces.ply"
  p.write_text(_ASCII_HEAD + "property float x\nproperty float y\nproperty float z\n"
               "element face 2\nproperty list uchar uchar vertex_indices\nend_header\n"
               "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 258\n")
  with pytest.raises(ValueError, match=r"element 'face' row 1 property 'vertex_indices': "
                                       r"expected an integer in \[0, 255\].*found 258"):
    io.read_ply(p)
  p.write_text(p.read_text().replace("258", "2"))
  assert io.read_ply(p).faces.tolist() == [[0, 1, 2], [0, 1, 2]]


def test_empty_ply_says_the_file_is_empty(tmp_path):
  p = tmp_path / "empty.ply"
  p.write_bytes(b"")
  with pytest.raises(ValueError, match=r"empty\.ply: header line 1: .*found an empty file"):
    io.read_cloud(p)


def test_npz_named_npy_is_one_clean_error(tmp_path):
  p = tmp_path / "cloud.npy"
  with open(p, "wb") as f:
    np.savez(f, points=np.random.default_rng(0).random((20, 3)))
  with pytest.raises(ValueError, match=r"cloud\.npy: array: .*found an \.npz archive "
                                       r"\(arrays: points\)"):
    io.read_cloud(p)


# -------------------------------------------------------------------------------- special files


def test_reading_a_fifo_says_it_is_not_a_regular_file(tmp_path):
  """Before: "no such file" for a FIFO that exists."""
  from lrf_jax.io import read_cloud
  fifo = tmp_path / "scan.bin"
  os.mkfifo(fifo)
  with pytest.raises(FileNotFoundError, match="not a regular file"):
    read_cloud(fifo)


def test_a_nuscenes_pcd_bin_is_refused_not_misread_as_kitti(tmp_path):
  """Before: 8 points of 5 float32 (160 bytes, a multiple of 16) read as 10 KITTI points of
  shuffled columns, silently."""
  from lrf_jax.io import read_cloud
  sweep = np.arange(40, dtype="<f4").reshape(8, 5)
  sweep.tofile(tmp_path / "n008__LIDAR_TOP__1.pcd.bin")
  with pytest.raises(ValueError, match=r"nuScenes-style \.pcd\.bin"):
    read_cloud(tmp_path / "n008__LIDAR_TOP__1.pcd.bin")
  sweep[:, :4].tofile(tmp_path / "kitti.bin")  # a KITTI layout still reads
  assert read_cloud(tmp_path / "kitti.bin").points.shape == (8, 3)
