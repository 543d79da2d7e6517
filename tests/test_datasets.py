"""Datasets: root resolution, mr, nuisances, keypoints, the demo set, and the real data's
ground-truth conventions (tests marked `data` skip, with the reason, when a set is absent)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lrf_jax import datasets as ds
from lrf_jax import io
from lrf_jax.datasets import root as root_mod

# ---------------------------------------------------------------------------------------------
# Real-data fixtures: resolved once per module through find_data_root, skipped when absent.


def _root_or_skip(dataset: str):
  try:
    return ds.find_data_root(dataset=dataset)
  except ds.DataNotFoundError:
    pytest.skip(f"real data set {dataset}/ not found under $LRF_DATA or <repo>/data "
                "(see data/README.md to obtain it)")


@pytest.fixture(scope="module")
def br_root():
  return _root_or_skip("bologna_retrieval")


@pytest.fixture(scope="module")
def uwaor_root():
  return _root_or_skip("uwa_object_recognition")


@pytest.fixture(scope="module")
def uwa3m_root():
  return _root_or_skip("uwa_3d_modeling_views")


@pytest.fixture(scope="module")
def bunny_root():
  return _root_or_skip("stanford_bunny_scans")


def _overlap(src: np.ndarray, dst: np.ndarray, radius: float) -> float:
  """Fraction of `src` points with a `dst` point within `radius`."""
  d, _ = cKDTree(dst).query(src, distance_upper_bound=radius, workers=-1)
  return float(np.isfinite(d).mean())


# ---------------------------------------------------------------------------------------------
# Data root


def test_find_data_root_order(tmp_path, monkeypatch):
  explicit, env, repo = (tmp_path / n for n in ("explicit", "env", "repo"))
  for r in (explicit, env, repo):
    (r / "stanford_bunny_scans").mkdir(parents=True)
  monkeypatch.setattr(root_mod, "REPO_DATA", repo)
  monkeypatch.delenv("LRF_DATA", raising=False)
  assert ds.find_data_root() == repo
  monkeypatch.setenv("LRF_DATA", str(env))
  assert ds.find_data_root() == env
  assert ds.find_data_root(explicit, "stanford_bunny_scans") == explicit
  assert ds.find_data_root(explicit / "stanford_bunny_scans", "stanford_bunny_scans") == explicit
  assert ds.dataset_dir("stanford_bunny_scans", explicit) == explicit / "stanford_bunny_scans"
  with pytest.raises(ValueError, match="expected one of"):
    ds.find_data_root(dataset="nope")


def test_data_not_found_lists_places_and_sources(tmp_path, monkeypatch):
  monkeypatch.setattr(root_mod, "REPO_DATA", tmp_path / "repo_data")
  monkeypatch.setenv("LRF_DATA", str(tmp_path / "env_data"))
  with pytest.raises(ds.DataNotFoundError) as info:
    ds.find_data_root(dataset="bologna_retrieval")
  msg = str(info.value)
  assert isinstance(info.value, FileNotFoundError)
  for fragment in ("$LRF_DATA", str(tmp_path / "env_data"), "<repo>/data",
                   str(tmp_path / "repo_data"), "ppf_matching", "LRF_DATA=", "data/README.md"):
    assert fragment in msg, fragment
  with pytest.raises(ds.DataNotFoundError) as info:
    ds.find_data_root()
  for name, dataset in ds.DATASETS.items():
    assert name in str(info.value) and dataset.obtain in str(info.value)
  with pytest.raises(ds.DataNotFoundError, match="argument"):
    ds.load_br(tmp_path)


# ---------------------------------------------------------------------------------------------
# Mesh resolution


def _grid_mesh(n=30, spacing=0.5):
  i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
  pts = np.stack([i.ravel() * spacing, j.ravel() * spacing, np.zeros(n * n)], 1)
  k = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
  faces = np.concatenate([np.stack([k, k + n, k + 1], 1), np.stack([k + 1, k + n, k + n + 1], 1)])
  return pts, faces


def test_mesh_resolution_mesh_and_cloud():
  n, s = 30, 0.5
  pts, faces = _grid_mesh(n, s)
  mr, how = ds.mesh_resolution(pts, faces)
  # unique edges: 2 n (n - 1) axis-aligned of length s, (n - 1)^2 diagonals of length s sqrt 2
  axis, diag = 2 * n * (n - 1), (n - 1) ** 2
  assert how == "mean_edge_length"
  np.testing.assert_allclose(mr, s * (axis + diag * 2 ** 0.5) / (axis + diag), rtol=1e-12)
  assert len(ds.unique_edges(faces)) == axis + diag
  mr, how = ds.mesh_resolution(pts)
  assert how == "mean_nn_distance"
  np.testing.assert_allclose(mr, s, rtol=1e-12)
  with pytest.raises(ValueError):
    ds.mesh_resolution(pts[:1])


# ---------------------------------------------------------------------------------------------
# Nuisances


def test_gaussian_noise_sigma_and_seed():
  pts = np.zeros((40000, 3))
  noisy = ds.add_gaussian_noise(pts, 0.3, 2.0, seed=5)
  np.testing.assert_allclose(noisy.std(axis=0), 0.6, rtol=0.05)  # per axis = 0.3 * mr
  np.testing.assert_array_equal(noisy, ds.add_gaussian_noise(pts, 0.3, 2.0, seed=5))
  assert not np.array_equal(noisy, ds.add_gaussian_noise(pts, 0.3, 2.0, seed=6))
  rng_a, rng_b = np.random.default_rng(1), np.random.default_rng(1)
  np.testing.assert_array_equal(ds.add_gaussian_noise(pts, 0.1, 1.0, rng_a),
                                ds.add_gaussian_noise(pts, 0.1, 1.0, rng_b))


@pytest.mark.parametrize("fraction", [1 / 2, 1 / 4, 1 / 8, 1 / 16])
def test_decimate_mesh_vertex_fraction(fraction):
  pts, faces = ds.make_demo_mesh("blob", seed=0)
  dec = ds.decimate(pts, faces, fraction)
  assert abs(len(dec.points) / len(pts) - fraction) <= 0.05 * fraction
  assert dec.faces.max() < len(dec.points) and dec.kept is None
  # still the same surface: decimated vertices lie close to the original mesh's vertices
  d, _ = cKDTree(pts).query(dec.points)
  mr, _ = ds.mesh_resolution(pts, faces)
  assert np.median(d) < 1.0 * mr


def test_decimate_takes_a_read_only_mesh():
  """A frozen mesh (the dataset cache's, or one a Ray worker unpickled) decimates as a
  writeable one, and is left as it was."""
  pts, faces = ds.make_demo_mesh("blob", seed=0)
  frozen = [a.copy() for a in (pts, faces)]
  for a in frozen:
    a.flags.writeable = False
  got, want = ds.decimate(*frozen, 0.5), ds.decimate(pts, faces, 0.5)
  np.testing.assert_array_equal(got.points, want.points)
  np.testing.assert_array_equal(got.faces, want.faces)
  np.testing.assert_array_equal(frozen[0], pts)


def test_decimate_open_mesh_is_corrected():
  pts, faces = _grid_mesh(60, 1.0)  # a flat sheet: half its vertices on or near the border
  dec = ds.decimate(pts, faces, 0.25)
  assert abs(len(dec.points) / len(pts) - 0.25) <= 0.05 * 0.25


def test_decimate_cloud_seeded():
  pts = np.random.default_rng(0).normal(size=(1000, 3))
  a, b, c = (ds.decimate(pts, None, 0.25, seed=s) for s in (3, 3, 4))
  assert len(a.points) == 250 and a.faces is None
  np.testing.assert_array_equal(a.points, pts[a.kept])
  np.testing.assert_array_equal(a.kept, b.kept)
  assert not np.array_equal(a.kept, c.kept)
  with pytest.raises(ValueError, match="fraction"):
    ds.decimate(pts, None, 0.0)


def test_rotate_about_axis():
  pts = np.random.default_rng(0).normal(size=(100, 3)) + 5.0
  for angle, axis in ((30, "z"), (90, "x"), (-120, np.array([1.0, 2.0, 3.0]))):
    out, t = ds.rotate_about_axis(pts, angle, axis)
    r = t[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_allclose(out, ds.transform_points(t, pts), atol=1e-12)
    np.testing.assert_allclose(out.mean(0), pts.mean(0), atol=1e-12)  # about the centroid
    np.testing.assert_allclose(np.degrees(np.arccos((np.trace(r) - 1) / 2)), abs(angle))
  _, t = ds.rotate_about_axis(pts, 90, "z", center=np.zeros(3))
  np.testing.assert_allclose(t[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # right-handed
  np.testing.assert_allclose(t[:3, 3], 0, atol=1e-12)


def test_pair_nuisances_keep_mr_and_ground_truth():
  pair = ds.make_demo_pair(0, seed=1, partial=False)
  rotated = ds.with_rotation(pair, 60)
  np.testing.assert_allclose(rotated.model_in_scene(), rotated.scene_points, atol=1e-9)
  noisy = ds.with_noise(pair, 0.3, seed=0)
  np.testing.assert_allclose((noisy.scene_points - pair.scene_points).std(0) / pair.mr, 0.3,
                             rtol=0.05)
  dec = ds.with_decimation(noisy, 0.25)
  for p in (rotated, noisy, dec):
    assert p.mr == pair.mr
  assert dec.correspondence == "nearest" and noisy.correspondence == "index"
  assert dec.meta["decimation"] == 0.25 and dec.meta["added_noise_mr"] == 0.3


def test_rotation_moves_the_scene_viewpoint():
  pair = ds.make_demo_pair(0, seed=1, partial=True)
  assert pair.scene_viewpoint is not None and pair.model_viewpoint is None
  rotated = ds.with_rotation(pair, 90, "x")
  t = rotated.transform @ np.linalg.inv(pair.transform)  # the added rotation
  np.testing.assert_allclose(rotated.scene_viewpoint, ds.transform_points(t, pair.scene_viewpoint[None])[0],
                             atol=1e-9)
  assert ds.with_noise(pair, 0.1, 0).scene_viewpoint is pair.scene_viewpoint
  with pytest.raises(ValueError, match="scene_viewpoint"):
    pair.replace(scene_viewpoint=np.array([1.0, 2.0]))


# ---------------------------------------------------------------------------------------------
# Pair and repeatability keypoints


def test_pair_validation():
  pts = np.zeros((5, 3))
  kw = dict(name="p", dataset="x", model_points=pts, model_faces=None, scene_faces=None,
            transform=np.eye(4), mr=1.0, mr_definition="mean_nn_distance")
  with pytest.raises(ValueError, match="equal point counts"):
    ds.Pair(scene_points=pts[:3], correspondence="index", **kw)
  with pytest.raises(ValueError, match="correspondence"):
    ds.Pair(scene_points=pts, correspondence="closest", **kw)
  with pytest.raises(ValueError, match="mr"):
    ds.Pair(scene_points=pts, correspondence="index", **{**kw, "mr": 0.0})


def test_repeatability_keypoints_index():
  pair = ds.make_demo_pair(0, seed=0, partial=False)
  m, s = ds.repeatability_keypoints(pair, n=1000, seed=3)
  assert len(m) == 1000 and len(np.unique(m)) == 1000 and np.all(np.diff(m) > 0)
  np.testing.assert_array_equal(m, s)
  np.testing.assert_array_equal(m, ds.repeatability_keypoints(pair, n=1000, seed=3)[0])
  assert not np.array_equal(m, ds.repeatability_keypoints(pair, n=1000, seed=4)[0])
  # index keypoints depend only on (seed, n, n_model): the noisy scene shares them
  noisy = ds.with_noise(pair, 0.5, seed=0)
  np.testing.assert_array_equal(m, ds.repeatability_keypoints(noisy, n=1000, seed=3)[0])


def test_repeatability_keypoints_nearest_on_partial_scan():
  pair = ds.make_demo_pair(1, seed=0, noise_mr=0.1, partial=True)
  m, s = ds.repeatability_keypoints(pair, n=1000, seed=0, max_dist_mr=0.5)
  assert len(m) == 1000
  d = np.linalg.norm(pair.model_in_scene()[m] - pair.scene_points[s], axis=1)
  assert d.max() <= 0.5 * pair.mr
  # the visible part only: every chosen model vertex was seen from the viewpoint
  assert np.isin(m, pair.meta["scene_vertex_ids"]).mean() > 0.99


# ---------------------------------------------------------------------------------------------
# Procedural demo dataset


def _edge_face_counts(faces):
  e = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
  _, counts = np.unique(e, axis=0, return_counts=True)
  return counts


@pytest.mark.parametrize("shape,euler", [("blob", 2), ("torus", 0)])
def test_demo_meshes_closed_and_detailed(shape, euler):
  pts, faces = ds.make_demo_mesh(shape, seed=0)
  assert 20000 <= len(pts) <= 50000
  counts = _edge_face_counts(faces)
  assert np.all(counts == 2)  # closed 2-manifold: every edge shared by two faces
  assert len(pts) - len(counts) + len(faces) == euler
  # detail: the bump field moves the surface off the base sphere / torus by mr's
  mr, _ = ds.mesh_resolution(pts, faces)
  if shape == "blob":
    height = np.linalg.norm(pts, axis=1) - 1.0
  else:
    height = np.hypot(np.hypot(pts[:, 0], pts[:, 1]) - 1.0, pts[:, 2]) - 0.4
  assert height.std() > 1.0 * mr
  np.testing.assert_array_equal(pts, ds.make_demo_mesh(shape, seed=0)[0])
  assert not np.allclose(pts, ds.make_demo_mesh(shape, seed=1)[0])


def test_demo_pair_deterministic_and_consistent():
  a = ds.make_demo_pair(2, seed=7, noise_mr=0.2, partial=True)
  b = ds.make_demo_pair(2, seed=7, noise_mr=0.2, partial=True)
  np.testing.assert_array_equal(a.scene_points, b.scene_points)
  np.testing.assert_array_equal(a.transform, b.transform)
  c = ds.make_demo_pair(2, seed=8, noise_mr=0.2, partial=True)
  assert not np.array_equal(a.transform, c.transform)
  io.check_rigid(a.transform, "demo")
  full = ds.make_demo_pair(2, seed=7, partial=False)
  np.testing.assert_allclose(full.scene_points, full.model_in_scene(), atol=1e-12)
  ids = a.meta["scene_vertex_ids"]
  noise = (a.scene_points - a.model_in_scene()[ids]).std(0) / a.mr
  np.testing.assert_allclose(noise, 0.2, rtol=0.05)
  assert 0.2 < a.meta["visible_fraction"] < 0.6
  assert a.scene_faces.max() < len(a.scene_points)
  assert [p.name for p in ds.load_demo(2, seed=7)] == ["demo0/blob", "demo1/torus"]


def _occluded(points, faces, idx, eye):
  """For each point idx, whether the segment to `eye` hits a face not incident to it."""
  tri = points[faces]
  v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
  out = []
  for i in idx:
    o = points[i]
    length = np.linalg.norm(eye - o)
    d = (eye - o) / length
    h = np.cross(d, e2)
    a = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(a) > 1e-12
    f = np.where(ok, 1 / np.where(ok, a, 1), 0)
    s = o - v0
    u = f * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = f * (q @ d)
    t = f * np.einsum("ij,ij->i", e2, q)
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < length)
    out.append(bool((hit & ~(faces == i).any(1)).any()))
  return np.array(out)


def test_demo_partial_view_is_self_occluded_visibility():
  """Visible vertices have a free line of sight (ray cast against the mesh), and the view
  removes front-facing vertices that the surface itself hides (self-occlusion). Hidden point
  removal also drops a few visible vertices in concave folds (0-7 % of the view), so hidden
  front-facing vertices are only mostly occluded."""
  pair = ds.make_demo_pair(3, seed=0, partial=True)  # a torus seen edge-on: the far ring hides
  eye = pair.meta["viewpoint"]
  pts = pair.model_in_scene()
  visible = np.zeros(len(pts), bool)
  visible[pair.meta["scene_vertex_ids"]] = True
  rng = np.random.default_rng(0)
  seen = rng.choice(np.flatnonzero(visible), 30, replace=False)
  assert not _occluded(pts, pair.model_faces, seen, eye).any()
  facing = np.einsum("ij,ij->i", ds.synthetic.vertex_normals(pts, pair.model_faces),
                     eye - pts) > 0
  hidden_facing = np.flatnonzero(~visible & facing)
  assert len(hidden_facing) > 0.02 * len(pts)  # there is self-occlusion to remove
  sample = rng.choice(hidden_facing, 25, replace=False)
  assert _occluded(pts, pair.model_faces, sample, eye).mean() >= 0.5


# ---------------------------------------------------------------------------------------------
# Real data: BR


@pytest.mark.data
def test_br_noise_sigma_every_scene(br_root):
  """Per-axis sigma of scene vertex i minus model vertex i under the .xf, in model mr."""
  measured = {}
  for level in (0.1, 0.3, 0.5):
    for pair in ds.load_br(br_root, level):
      assert pair.meta["noise_source"] == "file" and pair.correspondence == "index"
      diff = pair.scene_points - pair.model_in_scene()
      sigma = diff.std(axis=0) / pair.mr
      measured[(pair.name, level)] = sigma
      np.testing.assert_allclose(sigma, level, rtol=0.03, err_msg=pair.name)
      assert np.abs(diff.mean(axis=0)).max() / pair.mr < 0.02 * level + 0.005
      rms3 = np.sqrt((diff ** 2).sum(1).mean()) / pair.mr
      np.testing.assert_allclose(rms3 / sigma.mean(), 3 ** 0.5, rtol=0.03)
  assert len(measured) == 54


@pytest.mark.data
def test_br_synthesised_levels_and_noise_free(br_root):
  for level in (0.2, 0.4):
    pairs = ds.load_br(br_root, level, scenes=(0, 1), seed=0)
    for pair in pairs:
      assert pair.meta["noise_source"] == "synthesised"
      sigma = (pair.scene_points - pair.model_in_scene()).std(0) / pair.mr
      np.testing.assert_allclose(sigma, level, rtol=0.03)
    again = ds.load_br_pair(1, level, br_root, seed=0)
    np.testing.assert_array_equal(again.scene_points, pairs[1].scene_points)
    other = ds.load_br_pair(1, level, br_root, seed=1)
    assert not np.array_equal(other.scene_points, pairs[1].scene_points)
  clean = ds.load_br_pair(3, 0.0, br_root)
  assert clean.meta["noise_source"] == "none"
  np.testing.assert_array_equal(clean.scene_points, clean.model_in_scene())
  np.testing.assert_array_equal(clean.scene_faces, clean.model_faces)
  with pytest.raises(ValueError, match="noise"):
    ds.load_br_pair(0, 0.25, br_root)


@pytest.mark.data
def test_br_index_models_faces_and_mr(br_root):
  folder = br_root / "bologna_retrieval"
  for i, name in enumerate(ds.BR_SCENE_MODELS):
    ini = (folder / "scenes" / f"ConfigScene{i}.ini").read_text()
    stated = re.search(r'MODEL_0 = "[^"]*/Stanford/([^/]+)/([^/"]+)\.ply"', ini)
    assert stated.group(1) == name
    assert ds.load_br_model(name, br_root).path.stem == stated.group(2) + "_0"
  csv = (folder / "index_DERIVED.csv").read_text().splitlines()[1:]
  for line, name in zip(csv, ds.BR_SCENE_MODELS):
    assert line.split(",")[1].split("/")[1] == name
  pair = ds.load_br_pair(0, 0.5, br_root)  # scenes keep the model's faces
  np.testing.assert_array_equal(pair.scene_faces, pair.model_faces)
  # mr = mean edge length, about 1.4-1.6 x the NN spacing on these meshes
  for name in ds.BR_MODELS:
    model = ds.load_br_model(name, br_root)
    nn, _ = ds.mesh_resolution(model.points)
    assert model.mr_definition == "mean_edge_length" and 1.35 < model.mr / nn < 1.65


@pytest.mark.data
def test_br_models_parsed_once(br_root):
  ds.load_br(br_root, 0.0)
  before = ds.cache_info().misses
  ds.load_br(br_root, 0.0)
  ds.load_br(br_root, 0.4, scenes=(0, 5))
  assert ds.cache_info().misses == before
  model = ds.load_br_model("bunny", br_root)
  with pytest.raises(ValueError):  # cached arrays are read-only
    model.points[0, 0] = 1.0


@pytest.mark.data
def test_br_repeatability_keypoints_shared_across_noise(br_root):
  a = ds.load_br_pair(6, 0.1, br_root)
  b = ds.load_br_pair(0, 0.5, br_root)  # another scene of the bunny
  np.testing.assert_array_equal(ds.repeatability_keypoints(a)[0], ds.repeatability_keypoints(b)[0])


@pytest.mark.data
def test_training_set_disjoint_seeded_and_cached(br_root, tmp_path_factory):
  cache = tmp_path_factory.mktemp("cache")
  ts = ds.build_training_set(br_root, n_keypoints=2000, seed=0, cache_dir=cache)
  assert len(ts) == 2000 and ts.num_pairs == 18
  assert np.bincount(ts.keypoint_pair).min() >= 2000 // 18
  # disjoint from the evaluation keypoints, computed independently on a noisy level
  for k in range(ts.num_pairs):
    pair = ds.load_br_pair(int(ts.pair_scene[k]), 0.3, br_root)
    evaluation, _ = ds.repeatability_keypoints(pair, n=1000, seed=0)
    mine = ts.keypoint_vertex[ts.keypoint_pair == k]
    assert not np.intersect1d(mine, evaluation).size
    model, scene, mr = ts.pair_points(k)
    np.testing.assert_allclose(scene, pair.model_in_scene(), atol=1e-12)
    assert mr == pair.mr and mine.max() < len(model)
  # batches: a seeded permutation per epoch
  batches = list(ts.batches(512, epoch=0))
  assert len(batches) == ts.num_batches(512) == 3 and all(len(b) == 512 for b in batches)
  assert len(np.unique(np.concatenate(batches))) == 3 * 512
  np.testing.assert_array_equal(batches[0], next(ts.batches(512, epoch=0)))
  assert not np.array_equal(batches[0], next(ts.batches(512, epoch=1)))
  assert sum(len(b) for b in ts.batches(512, drop_remainder=False)) == 2000
  # second build: from the .npz cache, no PLY parsed
  ds.clear_cache()
  again = ds.build_training_set(br_root, n_keypoints=2000, seed=0, cache_dir=cache)
  assert ds.cache_info().misses == 0
  np.testing.assert_array_equal(again.keypoint_vertex, ts.keypoint_vertex)
  other = ds.build_training_set(br_root, n_keypoints=2000, seed=1, cache_dir=cache)
  assert not np.array_equal(other.keypoint_vertex, ts.keypoint_vertex)


# ---------------------------------------------------------------------------------------------
# Real data: Stanford bunny scans


@pytest.mark.data
def test_bunny_conf_convention(bunny_root):
  """bun.conf: world = R(q)ᵀ p + t aligns consecutive scans; R(q) p + t does not."""
  folder = bunny_root / "stanford_bunny_scans"
  pairs = ds.load_bunny_pairs(bunny_root)
  assert len(pairs) == 9
  conf = [line.split() for line in (folder / "bun.conf").read_text().splitlines()
          if line.startswith("bmesh")]
  naive = {}
  for tokens in conf:
    t = np.eye(4)
    t[:3, :3] = io.quaternion_to_matrix(np.array(tokens[5:9], float))
    t[:3, 3] = np.array(tokens[2:5], float)
    naive[tokens[1].removesuffix(".ply")] = t
  for pair in pairs:
    a, b = pair.meta["scans"]
    forward = _overlap(pair.model_in_scene(), pair.scene_points, 1e-3)
    backward = _overlap(pair.scene_points, pair.model_in_scene(), 1e-3)
    assert min(forward, backward) >= 0.20, (pair.name, forward, backward)
    wrong = np.linalg.inv(naive[b]) @ naive[a]
    plain = _overlap(ds.transform_points(wrong, pair.model_points), pair.scene_points, 1e-3)
    assert plain < 0.25 * forward and plain < 0.1, (pair.name, plain)
    assert pair.mr_definition == "mean_nn_distance" and 4e-4 < pair.mr < 8e-4  # metres
  grid = io.read_ply(folder / "bun000.ply").elements["range_grid"]["vertex_indices"]
  assert len(grid) == 512 * 400


# ---------------------------------------------------------------------------------------------
# Real data: UWAOR


@pytest.mark.data
def test_uwaor_models_land_on_rs1(uwaor_root):
  """SOURCE.txt: fraction of model points within 1 mm of rs1 under the .xf."""
  stated = {"chef": 0.24, "chicken": 0.15, "parasaurolophus": 0.35, "T-rex": 0.30}
  pairs = ds.load_uwaor(uwaor_root)
  assert [p.meta["object"] for p in pairs] == list(stated)
  for pair in pairs:
    assert pair.correspondence == "nearest" and pair.mr_definition == "mean_edge_length"
    frac = _overlap(pair.model_in_scene(), pair.scene_points, 1.0)
    assert abs(frac - stated[pair.meta["object"]]) < 0.02, (pair.name, frac)
    m, s = ds.repeatability_keypoints(pair, n=1000, seed=0)
    assert len(m) == 1000
    assert pair.meta["occlusion_percent"] > 60
  # without the offset the T-rex GT misses the scene
  trex = pairs[-1]
  shifted = trex.model_points + ds.uwaor.trex_offset(uwaor_root)
  assert _overlap(ds.transform_points(trex.transform, shifted), trex.scene_points, 1.0) < 0.02
  np.testing.assert_allclose(ds.uwaor.trex_offset(uwaor_root), ds.uwaor.TREX_SMALL_OFFSET_MM)


@pytest.mark.data
def test_uwaor_pcd_decoding_matches_derived_scene(uwaor_root):
  full = ds.load_uwaor_scene("rs1", uwaor_root, variant="full")
  pcd = ds.load_uwaor_scene("rs1", uwaor_root, variant="pcd")
  assert full.shape == (289541, 3)
  np.testing.assert_allclose(pcd, full, atol=1e-3)  # float32 mm vs float32 m * 1000
  small = ds.load_uwaor_scene("rs1", uwaor_root, variant="downsampled")
  assert len(small) == 12345
  for xf in (uwaor_root / "uwa_object_recognition" / "GroundTruth_3Dscenes").glob("*.xf"):
    io.read_xf(xf)  # every ground truth is a 4x4 rigid transform


# ---------------------------------------------------------------------------------------------
# Real data: UWA3M


@pytest.mark.data
def test_uwa3m_pseudo_ground_truth_aligns_consecutive_views(uwa3m_root):
  """Criterion: >= 50 % of view v within 1 mm of view v+1 under the pseudo GT, median NN
  residual of that overlap < 0.6 mr (about 0.35 mm), and far less overlap without the GT."""
  pairs = ds.load_uwa3m(uwa3m_root, kind="consecutive")
  assert len(pairs) == 27
  for pair in pairs:
    tree = cKDTree(pair.scene_points)
    d, _ = tree.query(pair.model_in_scene()[::4], workers=-1)  # every 4th point is plenty
    inside = d < 1.0
    assert inside.mean() >= 0.5, (pair.name, inside.mean())
    assert np.median(d[inside]) < 0.6 * pair.mr, (pair.name, np.median(d[inside]))
    raw, _ = tree.query(pair.model_points[::4], distance_upper_bound=1.0, workers=-1)
    assert np.isfinite(raw).mean() < 0.5 * inside.mean()  # the views do need the pose
  to_model = ds.load_uwa3m(uwa3m_root, kind="view_to_model", objects=("parasaurolophus",))
  assert len(to_model) == 10 and "stand-in" in to_model[0].meta["model_stand_in"]
  for pair in to_model:  # each view lies on the model under inv(T_v)
    assert _overlap(pair.scene_points, pair.model_in_scene(), 1.0) > 0.8


def _on_parallelograms(points, quads, tol):
  """Whether each point lies within `tol` of one of the parallelograms (origin, u, v)."""
  hit = np.zeros(len(points), bool)
  for o, u, v in quads:
    n = np.cross(u, v)
    rel = points - o
    gram = np.array([[u @ u, u @ v], [u @ v, v @ v]])
    ab = np.linalg.solve(gram, np.stack([rel @ u, rel @ v]))
    slack = tol / np.array([np.linalg.norm(u), np.linalg.norm(v)])[:, None]  # noise at an edge
    inside = np.all((ab >= -slack) & (ab <= 1 + slack), axis=0)
    hit |= inside & (np.abs(rel @ n) / np.linalg.norm(n) <= tol)
  return hit


def test_street_pair_is_seeded_and_its_truth_puts_both_sweeps_on_the_street():
  from lrf_jax.datasets.synthetic import street_quads
  kw = dict(n_points=5000)
  a, b = ds.make_street_pair(4.0, 6.0, seed=3, **kw), ds.make_street_pair(4.0, 6.0, seed=3, **kw)
  assert np.array_equal(a.model_points, b.model_points) and len(a.model_points) == 5000
  assert not np.array_equal(a.model_points,
                            ds.make_street_pair(4.0, 6.0, seed=4, **kw).model_points)
  assert np.array_equal(a.transform[:3, 3], [-6.0, 0.0, 0.0])
  assert np.array_equal(a.model_viewpoint, np.zeros(3))
  quads = street_quads(4.0)
  sensor = np.array([0.0, 0.0, 1.7])  # the model's; the truth moves the scene's there
  world_model = a.model_points + sensor
  world_scene = ds.transform_points(np.linalg.inv(a.transform), a.scene_points) + sensor
  for pts in (world_model, world_scene):  # 1 cm noise a axis: within 6 cm of the surfaces
    assert _on_parallelograms(pts, quads, 0.06).all()
  assert not _on_parallelograms(a.scene_points + sensor, quads, 0.06).all()  # untransformed
  assert np.linalg.norm(a.model_points, axis=1).max() < 40.0 + 0.1  # the sensor's range
