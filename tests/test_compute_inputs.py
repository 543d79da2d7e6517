"""compute_frames for users: the default method, every cloud input kind, radius_mr, warnings;
every bad argument refused by name (a seeded fuzz judged by `tests.lrf_testing.judge`, and one
regression test per bug it found), the patch size cap."""

import inspect
import warnings

import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets, io
from lrf_jax.descriptors import compute_descriptors
from pathlib import Path
from collections.abc import Callable
from lrf_jax.frames.compute import patch_size_cap
from tests.lrf_testing import (FUZZ_CASES, FUZZ_SEED, Case, check_frames, pick, rejects, run_cases,
                               short_repr, unit_sphere)


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
  from lrf_jax.frames import patch_frames
  from lrf_jax.geometry import normals
  pts, faces, mr = demo
  lrf_jax.compute_frames(pts, np.arange(0, len(pts), 97), 15 * mr, "flare")
  lrf_jax.compute_frames(pts, np.arange(0, len(pts), 97), 15 * mr, "lrf_net")
  # the jitted path too (on a CPU both methods above run host kernels): fills
  # patch_frames.jitted_method
  lrf_jax.compute_frames(pts, np.arange(0, len(pts), 97), 15 * mr, "lrf_net", kernel="jit")
  assert normals.CLOUD_CACHE and patch_frames.WEIGHT_TABLES
  assert patch_frames.jitted_method.cache_info().currsize
  lrf_jax.clear_caches()
  assert not normals.CLOUD_CACHE and not patch_frames.WEIGHT_TABLES
  assert patch_frames.jitted_method.cache_info().currsize == 0


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


# ---------------------------------------------------------------------------------------------
# compute_frames arguments: the fuzz (`tests.lrf_testing.judge`) and its regressions

N_POINTS, N_KEYPOINTS, RADIUS = 300, 8, 0.9


class _Ragged:
  """A .points attribute that numpy cannot make rectangular."""

  points = [[0.0, 0.0, 0.0], [1.0, 2.0]]


def _frames_templates(rng: np.random.Generator, pts: np.ndarray, kp: np.ndarray,
                      tmp_path: Path) -> list[Callable[[], tuple[str, dict, str, str]]]:
  """Each template draws (label, kwargs changed from the valid call, name, outcome)."""
  n = len(pts)

  def nan_points():
    p = pts.copy()
    p[int(rng.integers(0, n)), int(rng.integers(0, 3))] = rng.choice([np.nan, np.inf, -np.inf])
    return "points with a NaN/inf", {"points": p}, "points", "error"

  def shape_points():
    shape = pick(rng, [(n, 2), (n, 4), (n,), (n, 3, 1), (), (3, n)])
    return f"points shape {shape}", {"points": np.zeros(shape)}, "points", "error"

  def empty_points():
    return "points (0, 3)", {"points": np.zeros((0, 3)), "keypoints": np.zeros(0, int)}, \
        "points", "error"

  def dtype_points():
    dt = pick(rng, [complex, bool, "U4", object, "M8[s]"])
    return f"points dtype {dt}", {"points": pts.astype(dt)}, "points", "error"

  def ragged_points():
    x = pick(rng, [[[0.0, 0.0, 0.0], [1.0, 2.0]], _Ragged(), [[0, 0, "a"]], None,
                    [pts[0], pts[1][:2]]])
    return f"points {short_repr(x)[:40]}", {"points": x}, "points", "error"

  def missing_file():
    p = tmp_path / f"missing{int(rng.integers(0, 1000))}.ply"
    return "points: missing file", {"points": str(p)}, str(p), "error"

  def kp_range():
    k = kp.copy()
    k[int(rng.integers(0, len(k)))] = n + int(rng.integers(0, 5)) * int(rng.integers(1, 10**6))
    return "keypoint out of range", {"keypoints": k}, "keypoints", "error"

  def kp_negative():
    k = kp.copy()
    k[int(rng.integers(0, len(k)))] = -int(rng.integers(1, n + 5))
    return "negative keypoint", {"keypoints": k}, "keypoints", "error"

  def kp_float():
    k = kp.astype(float) + pick(rng, [0.0, 0.5])
    return f"float keypoints {k[:2]}", {"keypoints": k}, "keypoints", "error"

  def kp_dim():
    k = pick(rng, [kp.reshape(2, -1), kp.reshape(-1, 1), np.int64(3), kp[None]])
    return f"keypoints shape {np.shape(k)}", {"keypoints": k}, "keypoints", "error"

  def kp_other():
    k = pick(rng, [kp > 3, kp.astype(str), [[0, 1], [2]], None, "0 1 2", [1, "a"],
                    kp.astype(complex), np.array([2**70]), [1.5, 2]])
    return f"keypoints {short_repr(k)[:40]}", {"keypoints": k}, "keypoints", "error"

  def radius_bad():
    r = pick(rng, [0, 0.0, -RADIUS, -1e-30, np.nan, np.inf, -np.inf, "abc", "0.9", True,
                    [RADIUS], None, np.array([RADIUS, RADIUS]), 1j])
    return f"radius {r!r}", {"radius": r}, "radius", "error"

  def radius_both():
    return "radius and radius_mr", {"radius_mr": 15.0}, "radius", "error"

  def radius_mr_bad():
    r = pick(rng, [0, -15.0, np.nan, np.inf, "x", "15", [15.0]])
    return f"radius_mr {r!r}", {"radius": None, "radius_mr": r}, "radius_mr", "error"

  def k_bad():
    k = pick(rng, [0, -1, 2.5, "16", True, False, "defaultx", 16.0, [16], np.float64(16)])
    return f"k {k!r}", {"k": k}, "k", "error"

  def viewpoint_bad():
    v = pick(rng, [np.zeros(2), np.zeros(4), np.zeros((3, 1)), [0, 0, np.nan],
                    [np.inf, 0, 0], "abc", [0, 0, "x"], 0.0, [[0, 0, 0]]])
    return f"viewpoint {short_repr(v)[:40]}", {"viewpoint": v}, "viewpoint", "error"

  def method_bad():
    m = pick(rng, ["lrf-net", "", "LRF_NET", None, 3, ["toldi"], ("toldi",)])
    return f"method {m!r}", {"method": m}, "method", "error"

  def option_bad():
    name = pick(rng, ["foo", "x_modes", "radius2", "lut"])
    return f"option {name}", {name: 1}, name, "error"

  def chunk_bad():
    c = pick(rng, [0, -1, 2.5, "8", True, None])
    return f"chunk_size {c!r}", {"chunk_size": c}, "chunk_size", "error"

  def seed_bad():
    s = pick(rng, ["x", None, 2.5, [1], "1"])
    return f"seed {s!r}", {"seed": s}, "seed", "error"

  def search_bad():
    s = pick(rng, ["gpu", "", None, ["host"]])
    return f"search {s!r}", {"search": s}, "search", "error"

  def faces_bad():
    f = pick(rng, [np.zeros((5, 2), int), np.array([[0, 1, n]]), np.array([[-1, 0, 1]]),
                    np.full((4, 3), 0.5), np.zeros(3, int), "abc", [[0, 1], [2]]])
    return f"faces {short_repr(f)[:40]}", {"faces": f, "method": "rops"}, "faces", "error"

  def normals_bad():  # (NaN normals are allowed: they make their frames invalid)
    v = pick(rng, [np.zeros((n, 2)), np.zeros((n - 1, 3)), [[0, 0, 1], [0, 1]], "abc",
                    np.zeros((n, 3), complex)])
    return f"normals {short_repr(v)[:40]}", {"normals": v, "method": "board"}, "normals", "error"

  def valid():
    kw = pick(rng, [
        {"keypoints": kp.tolist()}, {"keypoints": kp.astype(np.int32)},
        {"keypoints": kp.astype(np.uint16)}, {"radius": np.float32(RADIUS)},
        {"radius": 1}, {"viewpoint": [0.0, 0.0, 10.0]}, {"points": pts.tolist()},
        {"points": pts.astype(np.float32)}, {"keypoints": np.zeros(0, int)},
        {"k": np.int64(48)}, {"seed": np.int64(3)}, {"points": io.Cloud(pts)},
        {"chunk_size": np.int32(4)}, {"keypoints": np.full(N_KEYPOINTS, n - 1)},
    ])
    m = len(kw.get("keypoints", kp))
    return f"valid {short_repr(kw)[:60]}", kw, "", f"result:{m}"

  return [nan_points, shape_points, empty_points, dtype_points, ragged_points, missing_file,
          kp_range, kp_negative, kp_float, kp_dim, kp_other, radius_bad, radius_both,
          radius_mr_bad, k_bad, viewpoint_bad, method_bad, option_bad, chunk_bad, seed_bad,
          search_bad, faces_bad, normals_bad, valid, valid]


def test_fuzz_compute_frames_arguments(tmp_path: Path) -> None:
  """FUZZ_CASES["compute_frames"] bad (and some unusual but valid) arguments to compute_frames."""
  rng = np.random.default_rng([FUZZ_SEED, 6])
  pts = rng.normal(size=(N_POINTS, 3))
  kp = rng.choice(N_POINTS, N_KEYPOINTS, replace=False)
  templates = _frames_templates(rng, pts, kp, tmp_path)
  cases = []
  for i in range(FUZZ_CASES["compute_frames"]):
    label, kw, name, outcome = templates[i % len(templates)]()
    args = {"points": pts, "keypoints": kp, "radius": RADIUS, "method": "toldi"} | kw
    m = 0
    if outcome.startswith("result:"):
      outcome, m = "result", int(outcome.split(":")[1])
    cases.append(Case(f"compute_frames case {i}: {label}",
                      lambda a=args: lrf_jax.compute_frames(**a), name, check_frames(m),
                      outcome, file=False))
  run_cases(cases, FUZZ_CASES["compute_frames"])


_PTS = np.random.default_rng(0).normal(size=(N_POINTS, 3))


@pytest.mark.parametrize("kw, name", [
    ({"method": ["toldi"]}, "method"),  # TypeError: unhashable type: 'list'
    ({"seed": "x"}, "seed"),  # ValueError from int() without the name
    ({"seed": None}, "seed"),  # TypeError from int()
    ({"seed": 2.5}, "seed"),  # silently int(2.5)
    ({"points": [[0.0, 0.0, 0.0], [1.0, 2.0]]}, "points"),  # numpy's inhomogeneous-shape error
    ({"points": _Ragged()}, "points"),
    ({"keypoints": [[0, 1], [2]]}, "keypoints"),
    ({"normals": _PTS.astype(complex), "method": "board"}, "normals"),  # imaginary part dropped
    ({"normals": [[0, 0, 1], [0, 1]], "method": "board"}, "normals"),  # numpy's error, unnamed
    ({"faces": [[0, 1], [2]], "method": "rops"}, "faces"),  # numpy's error without the name
    ({"faces": np.array([[0, 1, N_POINTS]])}, "faces"),  # silently ignored by toldi
    ({"radius": True}, "radius"),  # silently radius 1
    ({"radius": "0.9"}, "radius"),  # a string silently converted
    ({"radius": None, "radius_mr": "15"}, "radius_mr"),
])
def test_regression_compute_frames_arguments(kw: dict, name: str) -> None:
  args = {"points": _PTS, "keypoints": np.arange(N_KEYPOINTS), "radius": RADIUS,
          "method": "toldi"} | kw
  rejects(lambda: lrf_jax.compute_frames(**args), name, file=False)


# ----------------------------------------------------------------------------------- patch size


def test_patch_size_cap():
  assert [patch_size_cap(n) for n in (1, 2, 3, 200, 256, 257, 3000)] == [
      1, 2, 4, 256, 256, 512, 4096]


def test_k_above_the_cloud_size_is_capped():
  pts = unit_sphere(n=3000)
  kp = np.arange(10)
  huge, v_huge = lrf_jax.compute_frames(pts, kp, 0.5, "toldi", k=10**8)
  cap, v_cap = lrf_jax.compute_frames(pts, kp, 0.5, "toldi", k=patch_size_cap(len(pts)))
  np.testing.assert_array_equal(np.asarray(huge), np.asarray(cap))
  np.testing.assert_array_equal(np.asarray(v_huge), np.asarray(v_cap))
  assert np.asarray(v_huge).all()
