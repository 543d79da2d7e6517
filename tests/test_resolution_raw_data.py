"""Raw, uneven clouds: the working resolution, thinning at the door, one resolution per pair,
units, scale invariance, KITTI sweeps, full-density clouds (register's resolution relative to
the extent)."""

from __future__ import annotations

import numpy as np
import pytest

from lrf_jax import datasets
from lrf_jax.geometry import resolution
from lrf_jax.geometry.sampling import voxel_downsample, voxel_groups
from lrf_jax.registration import register, rotation_error_deg
import lrf_jax


def sweep(sensor=(0.0, 0.0, 0.0), n_az=720, n_el=32, seed=0) -> np.ndarray:
  """A synthetic raw LiDAR sweep of a street seen from `sensor` (metres, in the world frame):
  rays on an azimuth x elevation grid hit the ground (z = -1.7), two walls (y = +-8) and boxes,
  so the points are dense near the sensor and sparse far away, as a spinning LiDAR's are."""
  rng = np.random.default_rng(seed)
  az = np.linspace(-np.pi, np.pi, n_az, endpoint=False)
  el = np.deg2rad(np.linspace(-24.0, 2.0, n_el))
  a, e = np.meshgrid(az, el)
  d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
  o = np.asarray(sensor, float)
  t = np.full(len(d), np.inf)
  with np.errstate(divide="ignore", invalid="ignore"):
    tg = (-1.7 - o[2]) / d[:, 2]
    t = np.where((tg > 0) & (tg < 60), np.minimum(t, tg), t)
    for wall in (8.0, -8.0):
      tw = (wall - o[1]) / d[:, 1]
      hit = o[2] + tw * d[:, 2]
      t = np.where((tw > 0) & (hit < 4) & (tw < t), tw, t)
    for cx, cy, h in ((6.0, 4.0, 1.5), (-9.0, -5.0, 2.5), (15.0, -3.0, 1.0), (-4.0, 3.5, 2.0),
                      (25.0, 5.0, 3.0)):  # boxes of 2 x 2 m: hit their x faces
      for fx in (cx - 1.0, cx + 1.0):
        tb = (fx - o[0]) / d[:, 0]
        p = o + tb[:, None] * d
        inside = (np.abs(p[:, 1] - cy) < 1.0) & (p[:, 2] < -1.7 + h) & (tb > 0) & (tb < t)
        t = np.where(inside, tb, t)
  hit = np.isfinite(t) & (t < 60.0)  # the sensor's range
  pts = o + t[hit, None] * d[hit]
  return pts + rng.normal(scale=0.01, size=pts.shape)


def dense_room(n: int, seed: int = 0) -> np.ndarray:
  """A room corner (floor 4 x 3 m, two walls 2.5 m high, three boxes) sampled uniformly at
  random with `n` points: at 120,000 points sampled more finely than register works
  (extent / mean spacing about 410, above `MAX_EXTENT_MR`), at 20,000 not (about 170)."""
  rng = np.random.default_rng(seed)
  quads = [((0, 0, 0), (4, 0, 0), (0, 3, 0)), ((0, 0, 0), (4, 0, 0), (0, 0, 2.5)),
           ((0, 0, 0), (0, 3, 0), (0, 0, 2.5))]  # origin, edge u, edge v
  for x, y, w, d, h in ((1.0, 1.0, 0.6, 0.4, 0.8), (2.5, 0.3, 0.8, 0.8, 0.5),
                        (0.3, 2.0, 0.5, 0.7, 1.2)):
    quads += [((x, y, h), (w, 0, 0), (0, d, 0)), ((x, y, 0), (w, 0, 0), (0, 0, h)),
              ((x, y + d, 0), (w, 0, 0), (0, 0, h)), ((x, y, 0), (0, d, 0), (0, 0, h)),
              ((x + w, y, 0), (0, d, 0), (0, 0, h))]
  q = np.array(quads, float)
  area = np.linalg.norm(np.cross(q[:, 1], q[:, 2]), axis=1)
  k = rng.choice(len(q), n, p=area / area.sum())
  uv = rng.random((n, 2))
  return q[k, 0] + uv[:, :1] * q[k, 1] + uv[:, 1:] * q[k, 2]


@pytest.fixture(scope="module")
def sweeps():
  a = sweep((0.0, 0.0, 0.0), seed=0)
  b_world = sweep((1.5, 0.3, 0.0), seed=1)
  c, s = np.cos(0.05), np.sin(0.05)
  r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
  gt = np.eye(4)  # maps b (in its own frame) onto a
  gt[:3, :3], gt[:3, 3] = r, [1.5, 0.3, 0.0]
  b = (b_world - gt[:3, 3]) @ r  # b in its own (rotated, moved) frame: gt maps it back
  return a, b, gt


def test_a_raw_sweep_is_uneven_and_clean_clouds_keep_their_resolution(sweeps):
  res = resolution.working_resolution(sweeps[0])
  assert res.uneven and res.mr == res.area_spacing > resolution.UNEVEN_RATIO * res.mean_spacing
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  for pts in (pair.model_points, pair.scene_points):
    clean = resolution.working_resolution(pts)
    assert not clean.uneven
    assert clean.mr == resolution.mesh_resolution(pts)[0]  # exactly today's mr


def test_area_median_weights_points_by_their_area():
  d = np.array([1.0] * 90 + [10.0] * 10)  # 90 dense points, 10 sparse ones holding most area
  assert resolution.area_median(d) == 10.0 and np.median(d) == 1.0
  assert resolution.area_median(np.full(7, 0.5)) == 0.5
  assert resolution.area_median(np.zeros(3)) == 0.0


def test_pair_resolution_rules():
  even = resolution.Resolution(1.0, 1.0, 1.1, "mean_nn_distance")
  coarse = resolution.Resolution(3.0, 3.0, 3.2, "mean_nn_distance")
  uneven = resolution.Resolution(0.5, 0.1, 0.5, "area_median_nn_distance")
  assert resolution.pair_resolution(even, even) == 1.0
  assert resolution.pair_resolution(even, dataclasses_replace(even, mr=1.9)) == 1.0
  assert resolution.pair_resolution(even, coarse) == 3.0  # a raw fragment vs a coarser one
  assert resolution.pair_resolution(coarse, even) == 3.0
  assert resolution.pair_resolution(uneven, dataclasses_replace(uneven, mr=0.3)) == 0.5
  mm = resolution.Resolution(500.0, 500.0, 510.0, "mean_nn_distance")
  with pytest.raises(ValueError, match=r"differ 500-fold.*same units.*0.001"):
    resolution.pair_resolution(even, mm)
  assert resolution.thinning_voxel(uneven, 0.5) == 0.5
  assert resolution.thinning_voxel(even, 1.0) is None
  capped = resolution.Resolution(1.5, 1.0, 1.05, "extent_fraction")  # spacing 1, worked at 1.5
  assert capped.capped and not capped.uneven and not even.capped
  assert resolution.pair_resolution(even, capped) == 1.5  # the coarser, though under 2x
  assert resolution.pair_resolution(capped, even) == 1.5
  assert resolution.thinning_voxel(capped, 1.5) == 1.5  # thinned, though not 2x denser
  near = resolution.Resolution(1.2, 1.0, 1.05, "extent_fraction")  # spacing above 0.8 mr
  assert resolution.thinning_voxel(near, 1.2) is None  # would remove few points
  assert resolution.thinning_voxel(capped, 1.0) is None  # a given mr at its spacing


def dataclasses_replace(res, **kw):
  import dataclasses
  return dataclasses.replace(res, **kw)


def test_a_raw_sweep_pair_registers_with_the_defaults(sweeps):
  a, b, gt = sweeps
  reg = register(b, a)
  assert reg.voxel_size > reg.mr > 0  # thinned: voxel centroids about mr apart
  assert rotation_error_deg(reg.transform[:3, :3], gt[:3, :3]) < 1.0
  assert np.linalg.norm(reg.transform[:3, 3] - gt[:3, 3]) < 0.1
  assert reg.success
  c = reg.correspondences  # indices into the input clouds
  assert c[:, 0].max() < len(b) and c[:, 1].max() < len(a)
  moved = b[c[reg.inliers, 0]] @ gt[:3, :3].T + gt[:3, 3]
  assert np.median(np.linalg.norm(moved - a[c[reg.inliers, 1]], axis=1)) < 5 * reg.mr


@pytest.mark.parametrize("k", [1e-3, 1e3])
def test_scaling_both_clouds_scales_only_the_translation(sweeps, k):
  a, b, _ = sweeps
  base = register(b, a, n_keypoints=1000)
  scaled = register(k * b, k * a, n_keypoints=1000)
  assert scaled.success == base.success
  assert rotation_error_deg(scaled.transform[:3, :3], base.transform[:3, :3]) < 1e-3
  assert np.allclose(scaled.transform[:3, 3] / k, base.transform[:3, 3], atol=1e-4)
  assert scaled.mr / k == pytest.approx(base.mr, rel=1e-9)


def test_voxel_size_zero_keeps_every_point_and_a_bad_one_is_refused(sweeps):
  a, b, _ = sweeps
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  kept = register(pair.model_points, pair.scene_points, voxel_size=0, n_keypoints=500)
  default = register(pair.model_points, pair.scene_points, n_keypoints=500)
  assert kept.voxel_size == default.voxel_size == 0.0  # a clean pair is not thinned
  assert np.array_equal(kept.transform, default.transform)
  for bad in (-1.0, np.nan, "x", True):
    with pytest.raises(ValueError, match="voxel_size"):
      register(b, a, voxel_size=bad)


def test_clouds_in_different_units_are_refused_with_both_figures():
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.0, partial=True)
  with pytest.raises(ValueError, match="same units"):
    register(1000.0 * pair.model_points, pair.scene_points)


def test_cloud_extent_moves_and_scales_with_the_cloud():
  from scipy.spatial.transform import Rotation
  pts = dense_room(5000)
  ext = resolution.cloud_extent(pts)
  rot = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
  assert resolution.cloud_extent(pts @ rot.T + [100.0, -7.0, 3.0]) == pytest.approx(ext, rel=1e-9)
  assert resolution.cloud_extent(pts[::-1]) == pytest.approx(ext, rel=1e-12)
  assert resolution.cloud_extent(1e-3 * pts) == pytest.approx(1e-3 * ext, rel=1e-12)
  rms = np.sqrt(np.mean(np.sum((pts - pts.mean(0)) ** 2, axis=1)))  # brute force
  assert ext == pytest.approx(2 * rms, rel=1e-12)


def test_a_full_density_cloud_is_registered_at_a_fraction_of_its_extent():
  """register's resolution (`registration_resolution`) is the extent / `capped_extent_ratio`
  where the cloud is sampled more finely than extent / MAX_EXTENT_MR (its spacing measured on a
  sample, within 1 % of the whole cloud's); the working resolution of compute_frames stays its
  spacing; a cloud sampled no more finely keeps the working resolution exactly; scale-free."""
  dense, sparse = dense_room(120_000), dense_room(20_000)
  work, reg = resolution.working_resolution(dense), resolution.registration_resolution(dense)
  assert not work.capped and work.mr == resolution.mesh_resolution(dense)[0]
  assert reg.capped and reg.mean_spacing == pytest.approx(work.mr, rel=1e-2)
  extent = resolution.cloud_extent(dense)
  assert extent / work.mr > resolution.MAX_EXTENT_MR / resolution.SAMPLED_CAP_MARGIN  # sampled
  assert reg.mr == pytest.approx(
      extent / resolution.capped_extent_ratio(extent / reg.mean_spacing), rel=1e-12)
  # about 410 times finer than its extent: worked about 410 / 300 times coarser than the cap
  assert reg.mr == pytest.approx(extent / resolution.MAX_EXTENT_MR ** 2 * (extent / work.mr),
                                 rel=1e-2)
  assert reg.mr > 1.8 * work.mr
  assert resolution.registration_resolution(sparse) == resolution.working_resolution(sparse)
  from lrf_jax.frames.compute import _resolve_radius  # compute_frames' radius_mr: the spacing's, uncapped
  from lrf_jax.geometry.cloud import as_cloud
  assert _resolve_radius(as_cloud(dense), None, 15) == pytest.approx(15 * work.mr, rel=1e-12)
  for k in (1e-3, 1e3):
    assert resolution.registration_resolution(k * dense).mr == pytest.approx(k * reg.mr,
                                                                            rel=1e-9)


def test_a_cloud_just_over_the_cap_is_measured_on_all_its_points():
  """Between the cap and the sample's margin the whole cloud is measured (as below the cap):
  its spacings are `working_resolution`'s exactly, and its working resolution is just coarser
  than its spacing (the capped ratio is continuous at the cap)."""
  cloud = dense_room(70_000, seed=3)  # extent / spacing about 311
  work, reg = resolution.working_resolution(cloud), resolution.registration_resolution(cloud)
  ratio = resolution.cloud_extent(cloud) / work.mr
  assert resolution.MAX_EXTENT_MR < ratio < resolution.MAX_EXTENT_MR / resolution.SAMPLED_CAP_MARGIN
  assert reg.capped and reg.mean_spacing == work.mean_spacing
  assert reg.area_spacing == work.area_spacing
  assert reg.mr == pytest.approx(work.mr * (ratio / resolution.MAX_EXTENT_MR) ** 2, rel=1e-12)


def test_sampled_spacings_are_nearest_neighbor_distances():
  """`sampled_spacings`: every point's distance to its nearest other point in a small cloud; in
  a large one, SPACING_SAMPLE distinct points' (seeded: the same on every call), each against
  the whole cloud (a brute-force reference)."""
  from scipy.spatial import cKDTree
  small = dense_room(2000, seed=5)
  d = resolution.sampled_spacings(small)
  np.testing.assert_allclose(d, cKDTree(small).query(small, 2)[0][:, 1], rtol=0, atol=1e-12)
  big = dense_room(30_000, seed=6)
  d = resolution.sampled_spacings(big)
  assert d.shape == (resolution.SPACING_SAMPLE,)
  np.testing.assert_array_equal(d, resolution.sampled_spacings(big))
  every = cKDTree(big).query(big, 2)[0][:, 1]
  rows = np.sort(np.random.default_rng(0).choice(len(big), resolution.SPACING_SAMPLE,
                                                 replace=False))
  np.testing.assert_allclose(d, every[rows], rtol=0, atol=1e-12)
  assert d.mean() == pytest.approx(every.mean(), rel=2e-2)


@pytest.mark.parametrize("ratio", [300.0, 300.5, 350.0, 450.0, 600.0, 601.0, 1000.0, 1e6])
def test_capped_extent_ratio_is_continuous_at_the_cap_and_floored(ratio):
  """A cloud k <= 2 times finer than the cap is worked k times coarser than it; from twice the
  cap on, at CAPPED_MIN_RATIO; never finer than the cap."""
  cap, low = resolution.MAX_EXTENT_MR, resolution.CAPPED_MIN_RATIO
  got = resolution.capped_extent_ratio(ratio)
  assert low <= got <= cap
  assert got == pytest.approx(max(cap / (ratio / cap), low), rel=1e-12)
  assert resolution.capped_extent_ratio(ratio * (1 + 1e-9)) <= got  # non-increasing
  assert resolution.capped_extent_ratio(cap * (1 + 1e-9)) == pytest.approx(cap, rel=1e-8)


def test_a_full_density_pair_is_thinned_and_registered_right():
  from scipy.spatial.transform import Rotation
  from lrf_jax.registration import stages
  from lrf_jax.registration.options import RegisterOptions
  target, source = dense_room(120_000, seed=0), dense_room(120_000, seed=1)
  gt = np.eye(4)
  gt[:3, :3] = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
  gt[:3, 3] = [0.5, -1.0, 0.3]
  source = (source - gt[:3, 3]) @ gt[:3, :3]  # gt maps it back onto the target
  reg = register(source, target)
  caps = [resolution.registration_resolution(c) for c in (source, target)]
  assert all(r.capped for r in caps)
  assert reg.mr == max(r.mr for r in caps)  # the coarser side's
  assert reg.voxel_size > reg.mr  # thinned: voxel centroids about mr apart
  assert rotation_error_deg(reg.transform[:3, :3], gt[:3, :3]) < 1.0
  assert np.linalg.norm(reg.transform[:3, 3] - gt[:3, 3]) < 0.02
  # thinned because oversampled: the voxel centroids are the working points, no last pass
  prepared = stages.prepare(source, target, RegisterOptions())
  assert all(side.input_index is not None and side.raw is None for side in prepared.sides)
  spacing = resolution.mesh_resolution(source)[0]  # a given mr at the spacing: every point kept
  given = register(source, target, mr=spacing, n_keypoints=100, icp_iterations=0)
  assert given.voxel_size == 0.0 and given.mr == spacing


def test_voxel_groups_matches_unique_rows():
  rng = np.random.default_rng(0)
  cells = rng.integers(0, 5, size=(500, 3))
  inverse, first = voxel_groups(cells)
  u, f, inv = np.unique(cells, axis=0, return_index=True, return_inverse=True)
  assert np.array_equal(inverse, inv.ravel()) and np.array_equal(first, f)
  big = cells * (2**39)  # past one integer key: the row-wise fallback
  inverse2, first2 = voxel_groups(big)
  assert np.array_equal(inverse2, inverse) and np.array_equal(first2, first)


@pytest.mark.parametrize("scale", [1, 2**15, 2**39])
def test_voxel_groups_every_key_path_matches_unique_rows(scale):
  """One sort of key * n + index (spans times points under 2**62), a stable argsort of the
  key (spans under 2**62) and unique rows (beyond): the same groups, each first point the
  smallest index of its cell."""
  rng = np.random.default_rng(1)
  cells = rng.integers(0, 7, size=(5000, 3)) * scale
  inverse, first = voxel_groups(cells)
  _, f, inv = np.unique(cells, axis=0, return_index=True, return_inverse=True)
  assert np.array_equal(inverse, inv.ravel()) and np.array_equal(first, f)


def test_voxel_downsample_index_is_each_voxels_first_point():
  pts = np.array([[0.1, 0.1, 0.1], [2.5, 0.1, 0.1], [0.2, 0.3, 0.1], [2.6, 0.2, 0.4]])
  out, idx = voxel_downsample(pts, 1.0, return_index=True)
  assert idx.tolist() == [0, 1]
  assert np.allclose(out, [pts[[0, 2]].mean(0), pts[[1, 3]].mean(0)])


def test_kitti_bin_reader_checks_the_record_size(tmp_path):
  from lrf_jax.io import read_cloud
  pts = np.array([[1, 2, 3, 0.5], [4, 5, 6, 0.1]], "<f4")
  pts.tofile(tmp_path / "s.bin")
  assert np.array_equal(read_cloud(tmp_path / "s.bin").points, pts[:, :3].astype(float))
  (tmp_path / "bad.bin").write_bytes(b"\0" * 20)
  with pytest.raises(ValueError, match=r"bad.bin: size: expected a whole number of 16-byte"):
    read_cloud(tmp_path / "bad.bin")


def test_raw_kitti_sweeps_register_with_the_defaults(data_root):
  """The pair the default resolution used to lose (5 -> 0, 3.5 m apart; 124k points each)."""
  folder = data_root / "lidar_kitti00"
  poses = np.loadtxt(folder / "poses_DERIVED.txt").reshape(-1, 3, 4)
  pose = [np.vstack([p, [0, 0, 0, 1]]) for p in poses]
  gt = np.linalg.inv(pose[0]) @ pose[5]
  reg = register(str(folder / "000005.bin"), str(folder / "000000.bin"))
  assert reg.success and reg.voxel_size > 0
  assert rotation_error_deg(reg.transform[:3, :3], gt[:3, :3]) < 0.1
  # the last pass on the input points: 2.7 mm from the truth (7.8 mm without it)
  assert np.linalg.norm(reg.transform[:3, 3] - gt[:3, 3]) < 0.005


def test_the_last_pass_on_the_input_points_is_closer_to_the_truth(sweeps, monkeypatch):
  """A pair thinned by default ends with ICP on its input points (`refine.raw_pass`): closer to
  the truth than the thinned clouds' pose, the verdict the same; with a voxel given (the user
  chose the working cloud) no such pass runs."""
  from lrf_jax.registration import refine
  a, b, gt = sweeps
  with_raw = register(b, a)
  monkeypatch.setattr(refine, "RAW_GATES_MR", ())  # the pass without steps: the thinned pose
  thinned = register(b, a)
  assert with_raw.success == thinned.success and with_raw.reason == thinned.reason
  err = [np.linalg.norm(r.transform[:3, 3] - gt[:3, 3]) for r in (with_raw, thinned)]
  assert err[0] < 0.5 * err[1], err
  given_without = register(b, a, voxel_size=with_raw.voxel_size)
  monkeypatch.undo()
  given = register(b, a, voxel_size=with_raw.voxel_size)
  np.testing.assert_array_equal(given.transform, given_without.transform)


def test_the_last_pass_keeps_the_pose_when_it_moves_the_points_too_far():
  from lrf_jax.registration import refine
  from lrf_jax.registration.options import RegisterOptions
  rng = np.random.default_rng(0)
  target = np.concatenate([rng.uniform(-1, 1, (4000, 3)) * [1, 1, 0],  # a floor, two walls
                           rng.uniform(-1, 1, (4000, 3)) * [1, 0, 1] + [0, 1, 0],
                           rng.uniform(-1, 1, (4000, 3)) * [0, 1, 1] + [1, 0, 0]])
  source = target - [0.02, 0.01, 0.015]  # the pass moves every point by 0.027 back
  pose = np.eye(4)
  opts = RegisterOptions().icp
  moved = refine.raw_pass(source, target, pose, 0.05, opts, seed=0)
  np.testing.assert_allclose(moved[:3, 3], [0.02, 0.01, 0.015], atol=2e-3)
  kept = refine.raw_pass(source, target, pose, 0.02, opts, seed=0)  # 0.027 > 1 mr = 0.02
  np.testing.assert_array_equal(kept, pose)


def test_the_options_help_quotes_the_cap_it_documents():
  """`RegisterOptions.mr`'s help (the command lines show it) names the cap as a fraction; the
  options module does not import the resolution module (numba) to format it, so this binds them."""
  from lrf_jax.registration.options import option_fields
  help_text = {f.name: f.metadata["help"] for f in option_fields()}["mr"]
  assert f"1/{resolution.MAX_EXTENT_MR:g} of the cloud's extent" in help_text


def test_prepare_keeps_each_input_clouds_measured_spacing():
  """`Side.input_spacing` (what the ICP passes' normals radius reads instead of measuring the
  target again) is the input cloud's mean nearest-neighbor spacing, thinned or not."""
  from lrf_jax.geometry.cloud import CheckedCloud
  from lrf_jax.registration.options import RegisterOptions
  from lrf_jax.registration.stages import prepare
  dense, clean = dense_room(60_000, seed=2), dense_room(6_000, seed=3)
  sides = prepare(dense, clean, RegisterOptions(n_keypoints=50)).sides
  assert sides[0].input_index is not None and sides[1].input_index is None
  for side, cloud in zip(sides, (dense, clean)):
    assert side.input_spacing == resolution.mesh_resolution(cloud)[0]
  points, faces = datasets.make_demo_mesh("torus")
  side = prepare(CheckedCloud(points, faces), points[::3], RegisterOptions(n_keypoints=50)).sides[0]
  assert side.input_spacing is None  # a mesh's resolution is its edge length


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


def test_a_capped_target_is_paired_as_thinned_by_the_last_pass(monkeypatch):
  """An uneven source (a dense patch in a room: thinned, its input points kept for the last pass)
  against an oversampled target (thinned, no input points kept): the last pass pairs the
  source's input points with the target's working points, and gives it no input spacing (the
  target's input spacing is not its centroids')."""
  from types import SimpleNamespace
  from lrf_jax.registration import refine, stages
  from lrf_jax.registration.options import RegisterOptions
  from lrf_jax.search import engine
  rng = np.random.default_rng(7)
  patch = rng.uniform([1.0, 1.0, 0.0], [1.3, 1.3, 0.0], size=(150_000, 3))
  source = np.concatenate([dense_room(20_000, seed=2), patch])
  target = dense_room(120_000, seed=0)
  res = [resolution.registration_resolution(c) for c in (source, target)]
  assert res[0].uneven and res[1].capped
  opts = RegisterOptions()
  prepared = stages.prepare(source, target, opts)
  src, dst = prepared.sides
  assert src.input_index is not None and src.raw is not None  # thinned, input points kept
  assert dst.input_index is not None and dst.raw is None  # thinned, oversampled
  seen = {}

  def fake(source_in, target_in, pose, mr, icp_opts, seed, target_spacing=None):
    seen.update(source=source_in, target=target_in, spacing=target_spacing)
    return pose
  monkeypatch.setattr(refine, "raw_pass", fake)
  distance = 3 * prepared.mr
  verified = stages.Verified(SimpleNamespace(transform=np.eye(4)), np.zeros(0), np.zeros(0, bool),
                             0, engine.Grid(dst.points, distance), distance)
  refine.refine(prepared, verified, opts.icp, stages.StageTimer())
  assert seen["source"] is src.raw and seen["target"] is dst.points
  assert seen["spacing"] is None


def test_a_large_cloud_of_duplicates_is_refused_as_before():
  """Every point duplicated (more points than the spacing sample): the sample's spacing is 0,
  so the whole cloud is measured, and refused with `mesh_resolution`'s message."""
  pts = np.repeat(dense_room(6000, seed=4), 2, axis=0)
  assert len(pts) > resolution.SPACING_SAMPLE
  with pytest.raises(ValueError, match=r"source: the cloud has no spacing .*every point is duplicated"):
    resolution.registration_resolution(pts, name="source")


def test_the_sampled_and_the_whole_measure_agree_on_capping():
  """On clouds clearly on either side of the cap (a full-density room, a raw-like uneven cloud,
  a clean one), the sampled decision is the whole cloud's (`working_resolution` against the
  cap)."""
  rng = np.random.default_rng(8)
  patch = rng.uniform([1.0, 1.0, 0.0], [1.3, 1.3, 0.0], size=(150_000, 3))
  for cloud in (dense_room(120_000, seed=5), dense_room(20_000, seed=5),
                np.concatenate([dense_room(20_000, seed=2), patch])):
    work = resolution.working_resolution(cloud)
    exact = work.mr < resolution.cloud_extent(cloud) / resolution.MAX_EXTENT_MR
    assert resolution.registration_resolution(cloud).capped == exact
