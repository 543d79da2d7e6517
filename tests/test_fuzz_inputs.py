"""Inputs that used to give silently wrong answers: caches handing out their own arrays, an index
of another cloud, a huge k, reader names and NaN normals, unreadable files, unbounded headers."""

from __future__ import annotations

import builtins
import os

import numpy as np
import pytest

import lrf_jax
from lrf_jax import io
from lrf_jax.geometry import normals
from lrf_jax.api import host_frames, patch_size_cap
from lrf_jax.io import ply as ply_module
from lrf_jax.search.neighborhoods import SearchIndex


def _sphere(n=600, seed=0):
  pts = np.random.default_rng(seed).normal(size=(n, 3))
  return pts / np.linalg.norm(pts, axis=1, keepdims=True)


def _tetra():
  pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
  faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
  return pts, faces


# ------------------------------------------------------------------------------------- caches


def test_estimated_normals_are_the_callers_own_copy():
  pts = _sphere()
  first = normals.estimate_normals(pts, 0.3)
  expected = first.copy()
  first[:] = 7.0  # writing into what the cache gave must not reach the next caller
  again = normals.estimate_normals(pts, 0.3)
  np.testing.assert_array_equal(again, expected)
  assert again is not first


def test_writing_into_estimated_normals_does_not_change_later_frames():
  pts = _sphere()
  kp = np.arange(0, len(pts), 20)
  f0, v0 = lrf_jax.compute_frames(pts, kp, 0.5, "board")
  nrm = normals.estimate_normals(pts, normals.NORMAL_RADIUS_RATIO * 0.5)
  nrm[:] = -nrm[::-1]
  f1, v1 = lrf_jax.compute_frames(pts, kp, 0.5, "board")
  np.testing.assert_array_equal(np.asarray(f1), np.asarray(f0))
  np.testing.assert_array_equal(np.asarray(v1), np.asarray(v0))


def test_cache_last_copies_arrays_in_tuples():
  calls = []

  def fn():
    calls.append(1)
    return np.arange(3.0), (np.ones(2), "tag")

  key = (np.arange(5),)
  a, (b, tag) = normals.cache_last("test_fuzz_inputs", key, fn)
  a[:] = -1
  b[:] = -1
  a2, (b2, tag2) = normals.cache_last("test_fuzz_inputs", key, fn)
  assert len(calls) == 1 and tag2 == tag == "tag"
  np.testing.assert_array_equal(a2, np.arange(3.0))
  np.testing.assert_array_equal(b2, np.ones(2))
  normals._CACHE.pop("test_fuzz_inputs")


def test_mean_curvature_cache_hands_out_copies():
  pts, faces = _tetra()
  h = normals.mean_curvature(pts, faces)
  expected = h.copy()
  h[:] = 1e9
  np.testing.assert_array_equal(normals.mean_curvature(pts, faces), expected)


def test_cached_host_weight_table_is_read_only():
  from lrf_jax import api
  params = lrf_jax.default_params("lrf_net")
  table = api._weight_table(params, 17, host=True)
  with pytest.raises(ValueError, match="read-only"):
    table.values[0, 0] = 1.0
  assert api._weight_table(params, 17, host=True) is table


# ---------------------------------------------------------------------- index and patch size


def test_host_frames_refuses_an_index_of_another_cloud():
  a, b = _sphere(seed=1), _sphere(seed=2)  # same shape, other points
  with pytest.raises(ValueError, match="index: a SearchIndex of a different cloud"):
    host_frames(b, np.arange(5), 0.5, "shot", index=SearchIndex(a))
  with pytest.raises(ValueError, match="index: expected a SearchIndex"):
    host_frames(b, np.arange(5), 0.5, "shot", index=a)


def test_host_frames_accepts_an_index_of_equal_points():
  pts = _sphere()
  kp = np.arange(0, len(pts), 50)
  own, v_own = host_frames(pts, kp, 0.5, "shot", index=SearchIndex(pts))  # the same array
  copy, v_copy = host_frames(pts, kp, 0.5, "shot", index=SearchIndex(pts.copy()))  # equal values
  np.testing.assert_array_equal(copy, own)
  np.testing.assert_array_equal(v_copy, v_own)
  assert v_own.all()


def test_patch_size_cap():
  assert [patch_size_cap(n) for n in (1, 2, 3, 200, 256, 257, 3000)] == [
      1, 2, 4, 256, 256, 512, 4096]


def test_k_above_the_cloud_size_is_capped():
  pts = _sphere(n=3000)
  kp = np.arange(10)
  huge, v_huge = lrf_jax.compute_frames(pts, kp, 0.5, "toldi", k=10**8)
  cap, v_cap = lrf_jax.compute_frames(pts, kp, 0.5, "toldi", k=patch_size_cap(len(pts)))
  np.testing.assert_array_equal(np.asarray(huge), np.asarray(cap))
  np.testing.assert_array_equal(np.asarray(v_huge), np.asarray(v_cap))
  assert np.asarray(v_huge).all()


# --------------------------------------------------------------------------------- readers

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


# ------------------------------------------------------------------------------ PLY headers


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


def test_build_patches_refuses_an_index_of_another_cloud():
  from lrf_jax.search.neighborhoods import SearchIndex, build_patches
  rng = np.random.default_rng(0)
  a, b = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
  with pytest.raises(ValueError, match="different cloud"):
    build_patches(b, np.arange(5), 0.5, k=16, index=SearchIndex(a))
  ok = build_patches(b, np.arange(5), 0.5, k=16, index=SearchIndex(b.copy()))
  ref = build_patches(b, np.arange(5), 0.5, k=16)
  np.testing.assert_array_equal(np.asarray(ok.mask), np.asarray(ref.mask))


def test_uint64_keypoint_out_of_range_is_reported_exactly():
  from lrf_jax.checks import validate_keypoints
  with pytest.raises(ValueError, match="9223372036854775813"):
    validate_keypoints(np.array([2**63 + 5], np.uint64), 100)


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


@pytest.mark.parametrize("points,fragment", [
    (np.ones((50, 3)), "all 50 points coincide"),
    (np.repeat(np.random.default_rng(0).random((25, 3)), 2, axis=0),
     "every point is duplicated (25 distinct positions among 50 points)")])
def test_cloud_without_spacing_says_so_not_radius(points, fragment):
  """A cloud of duplicated points said "radius: ... got 0.0" although no radius was given."""
  with pytest.raises(ValueError, match=r"^source: the cloud has no spacing") as e:
    lrf_jax.register(points, points)
  assert fragment in str(e.value) and "radius" not in str(e.value)
  with pytest.raises(ValueError, match=r"^points: the cloud has no spacing"):
    lrf_jax.mesh_resolution(points)
