"""compute_frames for users: the default method, every cloud input kind, radius_mr, warnings."""

import inspect
import warnings

import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets, io
from lrf_jax.descriptors import compute_descriptors


@pytest.fixture(scope="module")
def demo():
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.0, partial=False)
  return pair.model_points, pair.model_faces, pair.mr


def test_default_method_is_lrf_net_plus():
  for fn in (lrf_jax.compute_frames, lrf_jax.frames_from_patches):
    assert inspect.signature(fn).parameters["method"].default == "lrf_net_plus", fn
  from lrf_jax.registration.options import DEFAULTS
  assert DEFAULTS.method == "lrf_net_plus"
  from lrf_jax.cli.register import build_parser
  assert build_parser().get_default("method") == "lrf_net_plus"


class _PointsOnly:
  """A stand-in for Open3D's PointCloud: `.points` convertible to (n, 3)."""

  def __init__(self, points):
    self.points = [tuple(p) for p in points]


class _MeshLike:
  """A stand-in for Open3D's TriangleMesh: `.vertices` and `.triangles`."""

  def __init__(self, points, faces):
    self.vertices, self.triangles = points, faces


def test_every_input_kind_gives_the_array_frames(demo, tmp_path):
  pts, faces, mr = demo
  kp = np.arange(0, len(pts), 97)
  ref, v = lrf_jax.compute_frames(pts, kp, 15 * mr, "lrf_net")
  path = tmp_path / "cloud.ply"
  io.write_ply(path, pts, dtype="float64")
  for x in (io.Cloud(points=pts), str(path), path, _PointsOnly(pts)):
    f, w = lrf_jax.compute_frames(x, kp, 15 * mr, "lrf_net")
    np.testing.assert_allclose(np.asarray(f), np.asarray(ref), atol=1e-6)
    np.testing.assert_array_equal(w, v)
  # A mesh object's faces are used (rops needs them) and an explicit faces= wins.
  f_mesh, _ = lrf_jax.compute_frames(_MeshLike(pts, faces), kp, 15 * mr, "rops")
  f_expl, _ = lrf_jax.compute_frames(pts, kp, 15 * mr, "rops", faces=faces)
  np.testing.assert_allclose(np.asarray(f_mesh), np.asarray(f_expl), atol=1e-6)
  with pytest.raises(ValueError, match="needs a triangle mesh"):
    lrf_jax.compute_frames(_PointsOnly(pts), kp, 15 * mr, "rops")


def test_radius_mr_measures_mr_with_the_calls_faces(demo):
  pts, faces, mr = demo
  assert lrf_jax.mesh_resolution(pts, faces) == pytest.approx(mr)
  assert lrf_jax.mesh_resolution(pts) < lrf_jax.mesh_resolution(pts, faces)  # nn < edge
  kp = np.arange(0, len(pts), 131)
  a, _ = lrf_jax.compute_frames(pts, kp, method="toldi", radius_mr=15, faces=faces)
  b, _ = lrf_jax.compute_frames(pts, kp, 15 * lrf_jax.mesh_resolution(pts, faces), "toldi",
                                faces=faces)
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  with pytest.raises(ValueError, match="exactly one of them"):
    lrf_jax.compute_frames(pts, kp, 0.1, "toldi", radius_mr=15)
  with pytest.raises(ValueError, match="exactly one of them"):
    lrf_jax.compute_frames(pts, kp, method="toldi")


def test_radius_warnings_both_ways(demo):
  pts, _, mr = demo
  kp = np.arange(0, len(pts), 211)
  with pytest.warns(UserWarning, match="fewer than 10"):
    lrf_jax.compute_frames(pts, kp, 0.5 * mr, "toldi")
  with pytest.warns(UserWarning, match="more than 50%"):
    lrf_jax.compute_frames(pts, kp, 1e3 * mr, "toldi")
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    lrf_jax.compute_frames(pts, kp, 15 * mr, "toldi")


def test_methods_print_as_a_table_with_descriptions_and_the_default_marked():
  lines = str(lrf_jax.METHODS).splitlines()
  assert lines[0].split() == ["name", "kind", "needs", "default", "K", "weights", "description"]
  assert len(lines) == len(lrf_jax.METHODS) + 2  # a header and a footer naming the default
  row = next(line for line in lines if line.split()[:2] == ["*", "lrf_net_plus"])
  assert row.split()[1:6] == ["lrf_net_plus", "learned", "params", "512", "lrf_net_plus"]
  assert "Beyond the paper" in row
  assert [line.split()[0] for line in lines[1:-1]].count("*") == 1  # one default
  toldi = next(line for line in lines if line.split()[0] == "toldi")
  assert lrf_jax.METHODS["toldi"].description in toldi  # short enough to be whole
  assert all(len(line) < 200 for line in lines)
  assert "default" in lines[-1] and "lrf_net_plus" in lines[-1]
  assert repr(lrf_jax.METHODS) == str(lrf_jax.METHODS)
  assert lrf_jax.METHODS.describe("rops").startswith("rops: RoPS")
  assert "(the default)" in lrf_jax.METHODS.describe("lrf_net_plus")
  with pytest.raises(KeyError, match="nope"):
    lrf_jax.METHODS.describe("nope")


def test_default_method_is_the_one_the_entry_points_use():
  from lrf_jax.frames import DEFAULT_METHOD
  from lrf_jax.cli.frames import build_parser as frames_parser
  from lrf_jax.cli.register import build_parser as register_parser
  from lrf_jax.registration.options import DEFAULTS
  assert inspect.signature(lrf_jax.compute_frames).parameters["method"].default == DEFAULT_METHOD
  assert DEFAULTS.method == DEFAULT_METHOD
  for parser in (frames_parser(), register_parser()):
    assert parser.get_default("method") == DEFAULT_METHOD


def test_clear_caches_empties_them(demo):
  from lrf_jax import api
  from lrf_jax.geometry import normals
  pts, faces, mr = demo
  lrf_jax.compute_frames(pts, np.arange(0, len(pts), 97), 15 * mr, "flare")
  lrf_jax.compute_frames(pts, np.arange(0, len(pts), 97), 15 * mr, "lrf_net")
  # the jitted path too (on a CPU both methods above run host kernels): fills api._jitted
  lrf_jax.compute_frames(pts, np.arange(0, len(pts), 97), 15 * mr, "lrf_net", kernel="jit")
  assert normals._CACHE and api._TABLES and api._jitted.cache_info().currsize
  lrf_jax.clear_caches()
  assert not normals._CACHE and not api._TABLES and api._jitted.cache_info().currsize == 0


def test_kernel_and_search_are_checked_with_no_keypoints_too(demo):
  pts, _, mr = demo
  none = np.zeros(0, np.int64)
  with pytest.raises(ValueError, match="kernel: expected"):
    lrf_jax.compute_frames(pts, none, radius=15 * mr, method="toldi", kernel="gpu")
  with pytest.raises(ValueError, match="search: expected"):
    lrf_jax.compute_frames(pts, none, radius=15 * mr, method="toldi", search="kdtree")
  with pytest.raises(ValueError, match="kernel: expected"):
    compute_descriptors(pts, none, 15 * mr, np.zeros((0, 3, 3)), np.zeros(0, bool),
                                kernel="gpu")
  frames, valid = lrf_jax.compute_frames(pts, none, radius=15 * mr, method="toldi")
  assert frames.shape == (0, 3, 3) and valid.shape == (0,)


def test_descriptors_refuse_an_index_of_another_cloud(demo):
  from lrf_jax.search.neighborhoods import SearchIndex
  pts, _, mr = demo
  kp = np.arange(0, len(pts), 50)
  frames, valid = lrf_jax.compute_frames(pts, kp, radius=15 * mr, method="toldi")
  other = pts + np.array([0.5, 0.0, 0.0])  # the same size, other points
  with pytest.raises(ValueError, match="index: a SearchIndex of a different cloud"):
    compute_descriptors(pts, kp, 15 * mr, frames, valid, index=SearchIndex(other, 0))
  with pytest.raises(ValueError, match="got dict"):
    compute_descriptors(pts, kp, 15 * mr, frames, valid, index={})
  own = compute_descriptors(pts, kp, 15 * mr, frames, valid, index=SearchIndex(pts, 0))
  fresh = compute_descriptors(pts, kp, 15 * mr, frames, valid)
  np.testing.assert_array_equal(np.asarray(own[0]), np.asarray(fresh[0]))


def test_default_params_refuses_a_name_without_shipped_weights():
  with pytest.raises(ValueError, match="no shipped weights named 'lrf_nett'.*lrf_net, lrf_net_plus"):
    lrf_jax.default_params("lrf_nett")
  assert set(lrf_jax.default_params("lrf_net")) == set(lrf_jax.init_params(0))
