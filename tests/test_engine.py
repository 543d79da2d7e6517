"""The compiled neighborhood engine against cKDTree references, on real and adversarial clouds."""

import threading
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lrf_jax.search import balls, engine
from lrf_jax.search.neighborhoods import SearchIndex, build_patches, hash_priority

# Float64 statistics are summed in another order than the reference's: they agree to this
# relative tolerance (of the ball's squared radius for covariances, its radius for centroids).
STATS_RTOL = 1e-9


def reference_patches(points, keypoints, radius, k, seed=0, z_ratio=1.0 / 3.0):
  """The engine's contract written with cKDTree: the K in-ball points of smallest
  hash_priority (ties by index), in that order; float64 inner-ball statistics."""
  pts = np.asarray(points, np.float64)
  tree = cKDTree(pts)
  prio = hash_priority(seed, np.arange(len(pts)))
  order = np.lexsort((np.arange(len(pts)), prio))
  rank = np.empty(len(pts), np.int64)
  rank[order] = np.arange(len(pts))
  m = len(keypoints)
  idx = np.full((m, k), -1, np.int64)
  count = np.zeros(m, np.int64)
  z_count = np.zeros(m, np.int64)
  z_mean = np.zeros((m, 3))
  z_cov = np.zeros((m, 3, 3))
  for i, p in enumerate(keypoints):
    ball = np.asarray(tree.query_ball_point(pts[p], radius), np.int64)
    count[i] = len(ball)
    keep = ball[np.argsort(rank[ball])][:k]
    idx[i, :len(keep)] = keep
    inner = np.asarray(tree.query_ball_point(pts[p], z_ratio * radius), np.int64)
    z_count[i] = len(inner)
    if len(inner):
      off = pts[inner] - pts[p]
      z_mean[i] = off.mean(0)
      z_cov[i] = (off.T @ off) / len(inner) - np.outer(z_mean[i], z_mean[i])
  return idx, count, z_count, z_mean, z_cov


def assert_matches_reference(points, keypoints, radius, k, seed=0, z_ratio=1.0 / 3.0):
  got = engine.patches(SearchIndex(points, seed).grid(radius), np.asarray(points)[keypoints],
                       radius, k, z_ratio * radius)
  idx, count, z_count, z_mean, z_cov = reference_patches(points, keypoints, radius, k, seed,
                                                         z_ratio)
  np.testing.assert_array_equal(got["indices"], idx)
  np.testing.assert_array_equal(got["mask"], idx >= 0)
  np.testing.assert_array_equal(got["count"], count)
  np.testing.assert_array_equal(got["z_count"], z_count)
  np.testing.assert_allclose(got["z_mean"], z_mean, rtol=0, atol=STATS_RTOL * radius)
  np.testing.assert_allclose(got["z_cov"], z_cov, rtol=0, atol=STATS_RTOL * radius**2)
  pts = np.asarray(points, np.float64)
  off = np.where((idx >= 0)[..., None], pts[np.maximum(idx, 0)] - pts[keypoints][:, None], 0)
  np.testing.assert_array_equal(got["offsets"], off.astype(np.float32))


def _adversarial():
  rng = np.random.default_rng(3)
  plane = np.c_[rng.uniform(size=(3000, 2)), np.zeros(3000)]
  strip = np.c_[rng.uniform(0.4, 0.45, size=(3000, 1)), rng.uniform(size=(3000, 1)),
                np.zeros((3000, 1))]  # 20x denser than the plane around it
  lattice = np.stack(np.meshgrid(*[np.arange(12) * 0.05] * 3), -1).reshape(-1, 3)
  return {
      "duplicates": (np.repeat(rng.normal(size=(400, 3)), 5, axis=0), 0.5),
      "dense_strip": (np.r_[plane, strip], 0.08),
      # Lattice spacing 0.05 with r = 0.15: many points exactly on cell boundaries of r / 3 and
      # exactly at distance r (along the axes) from every keypoint.
      "lattice_boundaries": (lattice, 0.15),
      "single_cell": (rng.uniform(size=(300, 3)) * 1e-3, 1.0),
      "far_from_origin": (rng.normal(size=(3000, 3)) * 0.01 + [1e6, -2e6, 5e5], 0.01),
      "tiny_radius": (rng.uniform(size=(2000, 3)), 1e-9),
  }


@pytest.mark.parametrize("name", sorted(_adversarial()))
@pytest.mark.parametrize("k", [1, 16, 256])
def test_patches_equal_ckdtree_on_adversarial_clouds(name, k):
  points, radius = _adversarial()[name]
  kp = np.random.default_rng(0).choice(len(points), min(200, len(points)), replace=False)
  assert_matches_reference(points, kp, radius, k)


@pytest.mark.parametrize("z_ratio", [1.0, 1.7])
def test_inner_statistics_of_a_support_as_large_as_or_larger_than_the_ball(z_ratio):
  """The normal support may reach beyond r (more cells than the patch's ball scans)."""
  points, radius = _adversarial()["dense_strip"]
  kp = np.random.default_rng(2).choice(len(points), 300, replace=False)
  assert_matches_reference(points, kp, radius, 64, z_ratio=z_ratio)


@pytest.mark.parametrize("z_ratio", [0.0, -0.5, float("nan")])
def test_build_patches_rejects_a_bad_support_ratio(z_ratio):
  pts = np.random.default_rng(0).normal(size=(100, 3))
  with pytest.raises(ValueError, match="z_ratio"):
    build_patches(pts, np.arange(10), 0.5, 16, z_ratio=z_ratio)


@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_cells_counted_whole_lie_inside_the_ball(offset):
  """The patch count takes cells whose box lies inside the ball without testing their points
  (`balls._column_runs`): every point of such a cell is within r by cKDTree's rule, also far
  from the origin, and the shortcut covers a good part of a dense ball."""
  import numba as nb
  rng = np.random.default_rng(4)
  pts = rng.uniform(size=(20000, 3)) + offset
  r = 0.1
  grid = engine.Grid(pts, r / 3)
  centers = pts[rng.choice(len(pts), 300, replace=False)]
  reach = balls.cell_reach(grid, r)

  @nb.njit
  def check(xyz, starts, origin, h, dims, centers, r, reach):
    n = (2 * reach + 1) ** 2
    js, je = np.empty(n, np.int64), np.empty(n, np.int64)
    ji, jk = np.empty(n, np.int64), np.empty(n, np.int64)
    whole = 0
    bad = 0
    for i in range(centers.shape[0]):
      cx, cy, cz = centers[i, 0], centers[i, 1], centers[i, 2]
      nr = balls._column_runs(cx, cy, cz, origin, h, dims, starts, r, reach, js, je, True, ji,
                               jk)
      for q in range(nr):
        bad += not (js[q] <= ji[q] <= jk[q] <= je[q])
        for j in range(starts[ji[q]], starts[jk[q]]):
          dx, dy, dz = xyz[0, j] - cx, xyz[1, j] - cy, xyz[2, j] - cz
          whole += 1
          bad += (dx * dx + dy * dy + dz * dz) > r * r
    return whole, bad

  whole, bad = check(grid.xyz, grid.starts, grid.origin, grid.h, grid.dims, centers, r, reach)
  counts = engine.ball_counts(grid, centers, r)
  assert bad == 0 and whole > 0.1 * counts.sum()


def test_in_ball_rule_is_ckdtree_squared_distance():
  """Points at distance exactly r are in; one ulp beyond is out; (0.1, 0.2, 0.2), at distance
  0.3 in exact arithmetic, is out because its float64 squared distance rounds above 0.3 * 0.3."""
  r = 0.3
  beyond = np.nextafter(r, 1.0)
  pts = np.array([[0, 0, 0], [r, 0, 0], [0, -r, 0], [0, 0, beyond], [0.1, 0.2, 0.2]], float)
  ptr, idx = engine.ball_lists(engine.Grid(pts, r / 3), pts[:1], r)
  ref = cKDTree(pts).query_ball_point(pts[0], r)
  assert sorted(idx.tolist()) == sorted(ref) == [0, 1, 2]


@pytest.mark.data
@pytest.mark.parametrize("cloud", ["br_bunny", "bunny_scan", "uwaor_rs1"])
def test_patches_equal_ckdtree_on_real_clouds(cloud, data_root):
  from lrf_jax.geometry.resolution import mesh_resolution
  from lrf_jax.io import read_cloud
  if cloud == "br_bunny":
    c = read_cloud(data_root / "bologna_retrieval" / "models" / "bunny" / "bun_zipper_0.ply")
  elif cloud == "bunny_scan":
    c = read_cloud(data_root / "stanford_bunny_scans" / "bun045.ply")
  else:
    c = read_cloud(data_root / "uwa_object_recognition" / "scenes" / "rs1_normals2.ply")
  pts = c.points
  mr, _ = mesh_resolution(pts, c.faces)
  kp = np.random.default_rng(1).choice(len(pts), 150, replace=False)
  assert_matches_reference(pts, kp, 15 * mr, 256)


def test_same_patches_with_one_and_two_threads():
  rng = np.random.default_rng(5)
  pts = rng.normal(size=(20000, 3)) * [1, 1, 0.05]
  kp = rng.choice(len(pts), 2000, replace=False)
  before = engine.num_threads()
  try:
    engine.set_num_threads(1)
    one = build_patches(pts, kp, 0.3, 64)
    engine.set_num_threads(2)
    two = build_patches(pts, kp, 0.3, 64)
  finally:
    engine.set_num_threads(before)
  for a, b in zip(one, two):
    np.testing.assert_array_equal(a, b)


def test_patches_written_into_given_rows_equal_fresh_ones():
  rng = np.random.default_rng(6)
  pts = rng.normal(size=(5000, 3))
  kp = rng.choice(len(pts), 300, replace=False)
  fresh = build_patches(pts, kp, 0.4, 32)
  assert not fresh.mask.all()  # some padding to write
  # Whatever the arrays hold, every element of the given rows is written (padding included).
  big = (np.full((500, 32, 3), np.nan, np.float32), np.ones((500, 32), bool),
         np.full((500, 32), 7, np.int32))
  rows = slice(100, 400)
  got = build_patches(pts, kp, 0.4, 32, into=tuple(a[rows] for a in big))
  for a, b in zip(fresh, got):
    np.testing.assert_array_equal(a, b)
  np.testing.assert_array_equal(big[0][rows], fresh.offsets)  # written in place
  np.testing.assert_array_equal(big[2][rows], fresh.indices)
  assert big[1][:100].all() and (big[2][400:] == 7).all()  # other rows untouched
  with pytest.raises(ValueError, match="into"):
    build_patches(pts, kp, 0.4, 32, into=(big[0][:300], big[1][:300], big[2][:300, :16]))


def test_balls_missed_by_the_rank_limit_are_collected_again():
  """The kernel guesses a rank limit from the ball's count; when fewer than K candidates lie
  under it, it collects again without one. A rank range of 1 makes every guess miss."""
  rng = np.random.default_rng(8)
  pts = rng.normal(size=(4000, 3))
  centers = pts[rng.choice(len(pts), 200, replace=False)]
  grid = SearchIndex(pts, 0).grid(0.5)
  want = engine.patches(grid, centers, 0.5, 16, 0.5 / 3)
  m, k = len(centers), 16
  got = dict(offsets=np.empty((m, k, 3), np.float32), mask=np.empty((m, k), bool),
             indices=np.empty((m, k), np.int32), count=np.zeros(m, np.int64),
             z_count=np.zeros(m, np.int64), z_mean=np.zeros((m, 3)), z_cov=np.zeros((m, 3, 3)))
  r, rz = 0.5, 0.5 / 3
  balls._patch_kernel(grid.xyz, grid.slot_index, grid.slot_rank, grid.starts, grid.origin,
                       grid.h, grid.dims, centers, engine.query_order(grid, centers), r, rz, k,
                       1, balls.cell_reach(grid, r), balls.cell_reach(grid, rz),
                       *balls.kept_shells(r, None), False, *got.values())
  assert (want["count"] > 2 * k).mean() > 0.5  # balls the limit would have cut
  for name in got:
    np.testing.assert_array_equal(got[name], want[name])


def test_query_order_is_a_cell_sorted_permutation_that_changes_nothing():
  rng = np.random.default_rng(7)
  pts = rng.normal(size=(6000, 3)) * [1, 1, 0.1]
  kp = rng.choice(len(pts), 700, replace=False)
  grid = SearchIndex(pts, 0).grid(0.3)
  centers = np.r_[pts[kp], [[50.0, -50.0, 0.0]]]  # one centre far outside the grid
  order = engine.query_order(grid, centers)
  np.testing.assert_array_equal(np.sort(order), np.arange(len(centers)))
  cell = np.clip(np.floor((centers - grid.origin) / grid.h), 0, grid.dims - 1).astype(np.int64)
  cid = (cell[:, 0] * grid.dims[1] + cell[:, 1]) * grid.dims[2] + cell[:, 2]
  assert (np.diff(cid[order]) >= 0).all()
  # Visiting the centres in cell order leaves each row its own: reversed keypoints, reversed rows.
  fwd = build_patches(pts, kp, 0.3, 48)
  rev = build_patches(pts, kp[::-1], 0.3, 48)
  for a, b in zip(fwd, rev):
    np.testing.assert_array_equal(a, b[::-1])
  ptr, idx = engine.ball_lists(grid, pts[kp], 0.3)
  ptr_r, idx_r = engine.ball_lists(grid, pts[kp[::-1]], 0.3)
  for i in range(len(kp)):
    j = len(kp) - 1 - i
    np.testing.assert_array_equal(idx[ptr[i]:ptr[i + 1]], idx_r[ptr_r[j]:ptr_r[j + 1]])


def test_patches_reusing_seed_independent_stats_equal_fresh_ones():
  rng = np.random.default_rng(8)
  pts = rng.normal(size=(8000, 3)) * [1, 1, 0.2]
  kp = rng.choice(len(pts), 500, replace=False)
  earlier = build_patches(pts, kp, 0.4, 16, seed=1)  # another seed and K
  fresh = build_patches(pts, kp, 0.4, 64, seed=2)
  reused = build_patches(pts, kp, 0.4, 64, seed=2, stats_from=earlier)
  assert (fresh.count > 64).any() and (fresh.count < 64).any()  # subsampled and padded rows
  for a, b in zip(fresh, reused):
    np.testing.assert_array_equal(a, b)
  with pytest.raises(ValueError, match="stats_from"):
    build_patches(pts, kp, 0.5, 64, stats_from=earlier)  # another radius
  with pytest.raises(ValueError, match="stats_from"):
    build_patches(pts, kp[:100], 0.4, 64, stats_from=earlier)
  with pytest.raises(ValueError, match="shells"):
    build_patches(pts, kp, 0.4, 64, shells=(0.3, 0.8), stats_from=earlier)


def test_set_num_threads_rejects_bad_values():
  for bad in (0, -1, 2.5, True):
    with pytest.raises(ValueError, match="num_threads"):
      engine.set_num_threads(bad)


@pytest.mark.parametrize("name", sorted(_adversarial()))
@pytest.mark.parametrize("k", [1, 2, 9])
def test_knn_distances_equal_ckdtree(name, k):
  points, _ = _adversarial()[name]
  rng = np.random.default_rng(2)
  queries = np.r_[points[:100], points.mean(0) + rng.normal(size=(30, 3)) * points.std() * 3]
  d, i = engine.knn(engine.knn_grid(points, k), queries, k)
  kk = min(k + 1, len(points))
  rd, ri = cKDTree(points).query(queries, k=kk)
  rd, ri = rd.reshape(len(queries), kk), ri.reshape(len(queries), kk)
  scale = max(1.0, float(np.abs(points).max()))
  np.testing.assert_allclose(d, rd[:, :k], rtol=1e-12, atol=1e-12 * scale)
  # Indices agree wherever the distance is not tied with another point's (k + 1 reference
  # neighbors show ties with the first point left out).
  ext = np.c_[np.full(len(rd), -np.inf), rd, np.full(len(rd), np.inf)]
  untied = (np.diff(ext, axis=1)[:, :-1] > 1e-9 * scale) & (np.diff(ext, axis=1)[:, 1:] > 1e-9 * scale)
  untied, ri = untied[:, :k], ri[:, :k]
  np.testing.assert_array_equal(i[untied], ri[untied])


def test_bounded_knn_and_any_within_match_ckdtree():
  rng = np.random.default_rng(4)
  pts = rng.uniform(size=(5000, 3))
  q = rng.uniform(-0.2, 1.2, size=(2000, 3))
  bound = 0.03
  grid = engine.Grid(pts, bound)
  d, i = engine.knn(grid, q, 1, bound)
  rd, ri = cKDTree(pts).query(q, distance_upper_bound=bound)
  np.testing.assert_array_equal(np.isfinite(d[:, 0]), np.isfinite(rd))
  np.testing.assert_array_equal(i[:, 0], ri)
  np.testing.assert_array_equal(engine.any_within(grid, q, bound), np.isfinite(rd))


def test_ball_lists_and_stats_match_ckdtree():
  rng = np.random.default_rng(6)
  pts = rng.normal(size=(4000, 3))
  grid = engine.Grid(pts, 0.2)
  ptr, idx = engine.ball_lists(grid, pts[:300], 0.4)
  count, mean, cov = engine.ball_stats(grid, pts[:300], 0.4)
  tree = cKDTree(pts)
  for i in range(300):
    ref = np.sort(tree.query_ball_point(pts[i], 0.4))
    np.testing.assert_array_equal(np.sort(idx[ptr[i]:ptr[i + 1]]), ref)
    assert count[i] == len(ref)
    off = pts[ref] - pts[i]
    np.testing.assert_allclose(mean[i], off.mean(0), atol=1e-12)
    np.testing.assert_allclose(cov[i], np.cov(off.T, bias=True), atol=1e-12)
  # The shell lists count every in-ball point on the side (with_counts), in the same pass.
  ptr_s, idx_s, full = engine.ball_lists(grid, pts[:300], 0.4, (0.3, 0.8), with_counts=True)
  np.testing.assert_array_equal(full, count)
  assert (np.diff(ptr_s) <= count).all() and (np.diff(ptr_s) < count).any()
  np.testing.assert_array_equal(np.diff(ptr_s), engine.ball_counts(grid, pts[:300], 0.4,
                                                                   (0.3, 0.8)))


def test_shell_patches_hold_exactly_the_inner_and_outer_neighbors():
  rng = np.random.default_rng(7)
  pts = rng.normal(size=(6000, 3)) * [1, 1, 0.1]
  kp = rng.choice(len(pts), 300, replace=False)
  r = 0.4
  full = build_patches(pts, kp, r, None)
  shell = build_patches(pts, kp, r, None, shells=(1 / 3, 0.85))
  np.testing.assert_array_equal(shell.count, full.count)
  np.testing.assert_array_equal(shell.z_cov, full.z_cov)
  for i in range(len(kp)):
    d = np.linalg.norm(full.offsets[i][full.mask[i]], axis=1)
    want = full.indices[i][full.mask[i]][(d <= r / 3 * (1 + 1e-5)) | (d > 0.85 * r * (1 - 1e-5))]
    np.testing.assert_array_equal(shell.indices[i][shell.mask[i]], want)  # same priority order
  assert shell.k < full.k


def test_flare_frames_from_shell_patches_equal_full_patches():
  from lrf_jax.frames.patch_frames import frames_from_patches
  from lrf_jax.frames import METHODS
  from lrf_jax.frames.normal_based import prepare_normals
  rng = np.random.default_rng(8)
  u, v = rng.uniform(-1, 1, size=(2, 8000))
  pts = np.c_[u, v, 0.2 * np.sin(2 * u) * np.cos(3 * v)]
  kp = rng.choice(len(pts), 200, replace=False)
  spec = METHODS["flare"]
  out = []
  for shells in (None, spec.shells):
    p = build_patches(pts, kp, 0.3, None, z_ratio=spec.z_ratio, shells=shells)
    extra = prepare_normals(pts, kp, p, radius=0.3)
    out.append([np.asarray(a) for a in frames_from_patches(p, "flare", extra=extra)])
  np.testing.assert_array_equal(out[0][1], out[1][1])
  np.testing.assert_array_equal(out[0][0], out[1][0])


def test_rops_triangles_from_a_subsampled_patch_equal_the_complete_ones():
  """gather_triangles searches the ball again when the patch is a subsample (the evaluation's
  neighbor cap): both paths give the same triangles."""
  from lrf_jax.frames.rops import gather_triangles
  rng = np.random.default_rng(9)
  n = 40
  u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
  pts = np.c_[u.ravel(), v.ravel(), 0.05 * np.sin(6 * u.ravel())]
  quads = np.array([[i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1]
                    for i in range(n - 1) for j in range(n - 1)])
  faces = np.r_[quads[:, [0, 1, 2]], quads[:, [1, 3, 2]]]
  kp = rng.choice(len(pts), 50, replace=False)
  full = build_patches(pts, kp, 0.12, None)
  sub = build_patches(pts, kp, 0.12, 16)
  assert np.all(full.count <= full.mask.sum(1)) and np.any(sub.count > sub.mask.sum(1))
  a = gather_triangles(pts, kp, faces, 0.12, patches=full)
  b = gather_triangles(pts, kp, faces, 0.12, patches=sub)
  for x, y in zip(a, b):
    np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("m, block", [(0, 32), (1, 32), (32, 32), (33, 32), (1000, 32),
                                      (5000, 256)])
def test_run_blocks_calls_every_query_once_in_whole_blocks(threads, m, block):
  seen = np.zeros(m, np.int64)
  calls = []
  lock = threading.Lock()

  def task(lo, hi):
    with lock:
      calls.append((lo, hi))
      seen[lo:hi] += 1

  before = engine.num_threads()
  try:
    engine.set_num_threads(threads)
    engine.run_blocks(task, m, block)
  finally:
    engine.set_num_threads(before)
  assert (seen == 1).all()
  assert all(lo % block == 0 and lo < hi <= m for lo, hi in calls)
  assert len(calls) <= max(1, -(-m // block))


def test_run_blocks_raises_a_tasks_error_after_the_others_end():
  done = []

  def task(lo, hi):
    if lo == 0:
      raise RuntimeError("span 0 failed")
    done.append(hi)

  with pytest.raises(RuntimeError, match="span 0 failed"):
    engine.run_blocks(task, 10_000)
  before = len(done)
  time.sleep(0.05)
  assert done and len(done) == before  # no span still running after the error came back


def test_run_blocks_from_several_threads_at_once():
  from concurrent.futures import ThreadPoolExecutor
  rng = np.random.default_rng(9)
  pts = rng.normal(size=(20000, 3))
  grid = engine.knn_grid(pts, 4)
  want = engine.knn(grid, pts[:5000], 4)

  def query(_):
    return engine.knn(grid, pts[:5000], 4)

  with ThreadPoolExecutor(4) as callers:
    for d, i in callers.map(query, range(8)):
      np.testing.assert_array_equal(d, want[0])
      np.testing.assert_array_equal(i, want[1])
