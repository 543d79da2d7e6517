"""ICP refinement: point-to-plane (lrf_jax.registration.icp_host) against numpy references, and the
point-to-point mode held to the original algorithm bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lrf_jax import datasets
from lrf_jax.search import engine
from lrf_jax.registration import icp_host, icp_normals
from lrf_jax.registration import icp, pose_errors, to_transform


def _height_field(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
  """A bumpy, irregularly sampled height field and its exact unit normals."""
  rng = np.random.default_rng(seed)
  x, y = rng.uniform(-1, 1, (2, n))
  z = 0.3 * np.sin(3 * x) * np.cos(2 * y) + 0.2 * x ** 2
  dzdx = 0.9 * np.cos(3 * x) * np.cos(2 * y) + 0.4 * x
  dzdy = -0.6 * np.sin(3 * x) * np.sin(2 * y)
  nrm = np.stack([-dzdx, -dzdy, np.ones(n)], axis=1)
  return np.stack([x, y, z], axis=1), nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def _corner(n: int, seed: int, noise: float) -> np.ndarray:
  """A room corner: the floor z = 0 and the walls y = 0, x = 0, each 1 x 1, n // 3 random
  points per plane with Gaussian noise of `noise`."""
  rng = np.random.default_rng(seed)
  k = n // 3
  u = rng.uniform(0, 1, (3, k, 2))
  zero = np.zeros(k)
  pts = np.concatenate([np.c_[u[0], zero], np.c_[u[1][:, 0], zero, u[1][:, 1]],
                        np.c_[zero, u[2]]])
  return pts + rng.normal(0, noise, pts.shape)


def _pose(axis, deg: float, t) -> np.ndarray:
  return to_transform(datasets.rotation_matrix(np.asarray(axis, np.float64), deg), t)


# ------------------------------------------------------------------------------------------------
# point_to_point: the original algorithm


def _old_icp_numpy(source, target, init, max_distance, iterations=30, tolerance=1e-7):
  """The point-to-point ICP `icp` had before the point-to-plane mode, in numpy: cKDTree pairs,
  the engine's per-block sums (same arithmetic in the same order), Kabsch on the sums."""
  target = np.asarray(target, np.float64)
  source = np.asarray(source, np.float64)
  tree = cKDTree(target)
  center = target.mean(axis=0)
  r2 = max_distance * max_distance
  nblock = max(1, -(-len(source) // icp_host._SUMS_BLOCK))

  def step(tr):
    rot, trans = tr[:3, :3], tr[:3, 3]
    sx, sy, sz = source[:, 0], source[:, 1], source[:, 2]
    q = np.stack([rot[k, 0] * sx + rot[k, 1] * sy + rot[k, 2] * sz + trans[k] for k in range(3)],
                 axis=1)
    _, j = tree.query(q, distance_upper_bound=max_distance * (1 + 1e-6))
    ok = j < len(target)
    tj = target[np.where(ok, j, 0)]
    dx, dy, dz = (tj[:, k] - q[:, k] for k in range(3))
    d2 = dx * dx + dy * dy + dz * dz
    ok &= d2 <= r2
    a, b = q - center, tj - center
    terms = np.concatenate([np.ones((len(q), 1)), d2[:, None], a, b,
                            (a[:, :, None] * b[:, None, :]).reshape(-1, 9)], axis=1)
    terms[~ok] = 0.0
    padded = np.zeros((nblock * icp_host._SUMS_BLOCK, 17))
    padded[:len(q)] = terms
    padded = padded.reshape(nblock, icp_host._SUMS_BLOCK, 17)
    partial = np.zeros((nblock, 17))
    for k in range(icp_host._SUMS_BLOCK):  # each block's sums in point order, as the kernel adds them
      partial += padded[:, k]
    acc = partial.sum(axis=0)
    n = int(acc[0])
    return n, (np.sqrt(acc[1] / n) if n else float("inf")), acc[2:5], acc[5:8], \
        acc[8:17].reshape(3, 3)

  tr = np.array(init, np.float64)
  for _ in range(int(iterations)):
    n, _, sa, sb, sab = step(tr)
    if n < 3:
      break
    ca, cb = sa / n, sb / n
    u, _, vt = np.linalg.svd(sab - n * np.outer(ca, cb))
    dd = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, dd]) @ u.T
    move = to_transform(r, (cb + center) - r @ (ca + center))
    tr = move @ tr
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))
    if angle + np.linalg.norm(move[:3, 3]) / max_distance < tolerance:
      break
  n, rmse, *_ = step(tr)
  return tr, (n / len(source) if len(source) else 0.0), float(rmse)


def test_point_to_point_mode_is_bit_identical_to_the_original_algorithm():
  pts, _ = _height_field(3000, 0)
  gt = _pose([0.3, 1.0, 0.2], 3.0, [0.01, -0.02, 0.005])
  target = datasets.transform_points(gt, pts)
  for iterations in (1, 4, 12):
    want = _old_icp_numpy(pts[::3], target, np.eye(4), 0.1, iterations)
    got = icp(pts[::3], target, np.eye(4), max_distance=0.1, iterations=iterations,
              mode="point_to_point")
    assert np.array_equal(got[0], want[0])
    assert got[1] == want[1] and got[2] == want[2]
  assert pose_errors(got[0], gt, mr=0.01)[0] < 0.5  # it did move towards gt


# ------------------------------------------------------------------------------------------------
# point_to_plane: one step against numpy


def _reference_step(source, target, normals, init, max_distance):
  """One point-to-plane Gauss-Newton step in numpy: cKDTree pairs, rows a = [(p - c) x n, n],
  b = (q - p) . n (pairs with unusable normals left out), the rescaled damped solve of
  icp_host's docstring, the exact rotation from scipy. Returns (new pose, A^T A, A^T b, pairs,
  plane pairs)."""
  c = target.mean(axis=0)
  p = source @ init[:3, :3].T + init[:3, 3]
  d, j = cKDTree(target).query(p, distance_upper_bound=max_distance)
  paired = j < len(target)
  lengths = np.linalg.norm(normals, axis=1)
  usable = np.isfinite(lengths) & (lengths > 0)
  keep = paired.copy()
  keep[paired] = usable[j[paired]]
  n = normals[j[keep]] / lengths[j[keep], None]
  pk, qk = p[keep], target[j[keep]]
  a = np.concatenate([np.cross(pk - c, n), n], axis=1)
  b = np.einsum("ij,ij->i", qk - pk, n)
  h, g = a.T @ a, a.T @ b
  lever = np.sqrt(np.trace(h[:3, :3]) / np.trace(h[3:, 3:]))
  s = np.r_[np.full(3, 1 / lever), np.ones(3)]
  hs = h * np.outer(s, s)
  x = np.linalg.solve(hs + icp_host.DAMPING * np.trace(hs) / 6 * np.eye(6), g * s) * s
  r = Rotation.from_rotvec(x[:3]).as_matrix()
  move = to_transform(r, c + x[3:] - r @ c)
  return move @ init, h, g, int(paired.sum()), int(keep.sum())


def test_one_step_matches_a_numpy_reference():
  pts, nrm = _height_field(4000, 1)
  gt = _pose([1.0, -0.4, 0.5], 4.0, [0.03, 0.01, -0.02])
  source = datasets.transform_points(np.linalg.inv(gt), pts[::2] + 0.002)  # a bit off the surface
  nrm = nrm * np.random.default_rng(2).uniform(0.5, 2.0, (len(nrm), 1))   # any length, any sign
  nrm[::7] *= -1.0
  nrm[3::11] = 0.0  # unusable normals: their pairs are skipped
  nrm[5::13] = np.nan
  init = _pose([0.2, 0.3, 1.0], 1.0, [0.01, 0.0, 0.0])
  want, h, g, pairs, plane_pairs = _reference_step(source, pts, nrm, init, 0.08)
  grid = engine.Grid(pts, 0.08)
  sums = icp_host.plane_sums(grid, icp_normals.unit_normals(nrm), source, init[:3, :3], init[:3, 3],
                             0.08, pts.mean(axis=0))
  assert (sums.pairs, sums.plane_pairs) == (pairs, plane_pairs) and plane_pairs < pairs
  np.testing.assert_allclose(sums.hessian, h, rtol=1e-10, atol=1e-10 * np.abs(h).max())
  np.testing.assert_allclose(sums.gradient, g, rtol=1e-10, atol=1e-10 * np.abs(g).max())
  got, fitness, rmse = icp(source, pts, init, max_distance=0.08, iterations=1, target_normals=nrm)
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
  assert not np.allclose(got, init, atol=1e-4)  # the step is not trivially zero
  # fitness and rmse are point-to-point statistics at the returned pose, as in point_to_point.
  n, d2, *_ = icp_host.icp_sums(grid, source, got[:3, :3], got[:3, 3], 0.08, pts.mean(axis=0))
  assert fitness == n / len(source)
  assert rmse == pytest.approx(np.sqrt(d2 / n), rel=1e-12)


def test_the_normals_sign_and_length_do_not_change_the_result():
  pts, nrm = _height_field(3000, 3)
  gt = _pose([0.0, 1.0, 0.3], 5.0, [0.02, 0.02, 0.0])
  source = datasets.transform_points(np.linalg.inv(gt), pts[::3])
  flipped = nrm * np.where(np.arange(len(nrm)) % 2, -1.0, 1.0)[:, None]
  a = icp(source, pts, np.eye(4), max_distance=0.1, target_normals=nrm)
  b = icp(source, pts, np.eye(4), max_distance=0.1, target_normals=flipped)
  assert np.array_equal(a[0], b[0]) and a[1:] == b[1:]
  assert pose_errors(a[0], gt, mr=0.01)[0] < 1e-4  # noise-free with exact normals: exact


# ------------------------------------------------------------------------------------------------
# point_to_plane: convergence, determinism, degenerate scenes


def test_point_to_plane_converges_on_a_room_corner_in_fewer_iterations():
  """Independent samples of the same noisy room corner, 7 deg and 5 cm apart: point-to-plane
  (estimated normals) is within 0.05 deg after 5 iterations, point-to-point is not after 10."""
  source, target = _corner(3000, 0, 0.001), _corner(3000, 1, 0.001)
  init = _pose([1.0, -0.5, 0.3], 7.0, [0.04, -0.03, 0.02])
  plane, fit, _ = icp(source, target, init, max_distance=0.2, iterations=5)
  point, *_ = icp(source, target, init, max_distance=0.2, iterations=10, mode="point_to_point")
  err_plane, err_t = pose_errors(plane, np.eye(4), mr=1.0)
  err_point, _ = pose_errors(point, np.eye(4), mr=1.0)
  assert err_plane < 0.05 and err_t < 0.002 and fit == 1.0
  assert err_point > 0.05


def test_point_to_plane_does_not_depend_on_the_thread_count():
  source, target = _corner(3000, 2, 0.002), _corner(3000, 3, 0.002)
  init = _pose([0.3, 1.0, -0.2], 6.0, [0.02, 0.05, -0.03])
  before = engine.num_threads()
  try:
    results = []
    for n in (1, engine.set_num_threads(None)):
      engine.set_num_threads(n)
      results.append(icp(source, target, init, max_distance=0.2, iterations=6))
  finally:
    engine.set_num_threads(before)
  (a, fa, ra), (b, fb, rb) = results
  assert np.array_equal(a, b) and fa == fb and ra == rb


def test_a_single_plane_neither_blows_up_nor_slides():
  """z = 0 constrains t_z and the two tilts only: the 6 x 6 system is singular. The damped step
  levels the source onto the plane and leaves the unconstrained in-plane motion alone."""
  rng = np.random.default_rng(4)
  plane = np.c_[rng.uniform(0, 1, (3000, 2)), np.zeros(3000)]
  source = np.c_[rng.uniform(0.2, 0.8, (1000, 2)), np.zeros(1000)]
  init = _pose([1.0, 0.0, 0.0], 3.0, [0.0, 0.0, 0.02])
  with np.errstate(all="raise"):
    est, fit, rmse = icp(source, plane, init, max_distance=0.1,
                         target_normals=np.tile([0.0, 0.0, 1.0], (3000, 1)))
  assert np.all(np.isfinite(est)) and np.isfinite(rmse) and fit == 1.0
  moved = datasets.transform_points(est, source)
  assert np.abs(moved[:, 2]).max() < 1e-9  # levelled onto the plane
  # The tilt about x is undone, and nothing moves along the null directions: no rotation about
  # z, no shift along x (y shifts by the lever of the tilt about the rotation centre, < 5 mm).
  assert np.abs(est[:3, :3] - np.eye(3)).max() < 1e-9
  start = datasets.transform_points(init, source)
  assert np.abs(moved[:, 0] - start[:, 0]).max() < 1e-9
  assert np.abs(moved[:, 1] - start[:, 1]).max() < 5e-3
  # Noisy, with estimated normals: still finite and on the plane.
  noisy = plane + rng.normal(0, 0.001, plane.shape)
  est, fit, rmse = icp(source, noisy, init, max_distance=0.1)
  moved = datasets.transform_points(est, source)
  assert np.all(np.isfinite(est)) and fit == 1.0 and np.abs(moved[:, 2]).mean() < 1e-3


def test_the_damped_solve_of_a_singular_system_is_finite_and_zero_off_the_data():
  rng = np.random.default_rng(5)
  p = np.c_[rng.uniform(-1, 1, (50, 2)), np.zeros(50)]
  n = np.tile([0.0, 0.0, 1.0], (50, 1))
  a = np.concatenate([np.cross(p, n), n], axis=1)   # columns of ω_z, t_x, t_y are zero
  b = rng.normal(size=50)
  x = icp_host.solve_step(a.T @ a, a.T @ b)
  assert np.linalg.matrix_rank(a.T @ a) == 3 and np.all(np.isfinite(x))
  assert np.array_equal(x[[2, 3, 4]], np.zeros(3))
  np.testing.assert_allclose(a @ x, a @ np.linalg.lstsq(a, b, rcond=None)[0], atol=1e-5)
  assert np.array_equal(icp_host.solve_step(np.zeros((6, 6)), np.zeros(6)), np.zeros(6))


def test_no_pairs_leaves_the_pose_alone():
  target = _corner(600, 6, 0.0)
  init = _pose([0.0, 0.0, 1.0], 10.0, [5.0, 0.0, 0.0])  # far away from the target
  est, fit, rmse = icp(target, target, init, max_distance=0.05)
  assert np.array_equal(est, init) and fit == 0.0 and rmse == float("inf")


def test_bad_arguments_name_the_argument():
  pts = _corner(300, 7, 0.0)
  with pytest.raises(ValueError, match="mode"):
    icp(pts, pts, np.eye(4), max_distance=0.1, mode="plane")
  with pytest.raises(ValueError, match=r"target_normals: expected shape \(300, 3\)"):
    icp(pts, pts, np.eye(4), max_distance=0.1, target_normals=np.zeros((300, 2)))
  with pytest.raises(ValueError, match="target_normals"):
    icp(pts, pts, np.eye(4), max_distance=0.1, target_normals=np.zeros((299, 3)))
  with pytest.raises(ValueError, match="target_normals"):
    icp(pts, pts, np.eye(4), max_distance=0.1, target_normals=[["a", "b", "c"]] * 300)
  for bad in (0.0, -1.0, float("nan"), "5cm"):
    with pytest.raises(ValueError, match="max_distance"):
      icp(pts, pts, np.eye(4), max_distance=bad)
  with pytest.raises(ValueError, match="max_distance: expected a finite"):
    icp(pts, pts, np.eye(4), max_distance=float("inf"), target_grid=engine.Grid(pts, 0.1))


def test_the_fine_gate_is_the_clipped_median_residual():
  """`registration.refine.fine_distance` against cKDTree: 1.5 x the median nearest distance of
  the moved source over the pairs within the first gate, clipped to [1 mr, first gate]."""
  from lrf_jax.registration.refine import ICP_FINE_FACTOR, ICP_FINE_MIN_MR, fine_distance
  source, _ = _height_field(3000, 0)
  target, _ = _height_field(4000, 1)
  mr = float(cKDTree(source).query(source, 2)[0][:, 1].mean())
  grid = engine.Grid(target, 3 * mr)
  tree = cKDTree(target)
  for shift, noise in ((0.0, 0.0), (0.5, 0.3), (2.0, 1.0)):
    pose = _pose([0.2, 1.0, 0.1], 0.5, [0.0, 0.0, shift * mr])
    src = source + np.random.default_rng(2).normal(0, noise * mr, source.shape)
    d = tree.query(src @ pose[:3, :3].T + pose[:3, 3])[0]
    want = np.clip(ICP_FINE_FACTOR * np.median(d[d < 3 * mr]), ICP_FINE_MIN_MR * mr, 3 * mr)
    got = fine_distance(src, grid, pose, 3 * mr, mr)
    assert got == pytest.approx(want, rel=1e-9)
  far = _pose([0.0, 0.0, 1.0], 0.0, [10.0, 0.0, 0.0])   # no pair: the first gate stays
  assert fine_distance(source, grid, far, 3 * mr, mr) == 3 * mr


def test_register_without_the_fine_pass_is_one_icp_pass():
  """`register(icp_fine=False)` refines the coarse pose by a single ICP pass at icp_mr mr; the
  default adds the second pass and reports fitness at icp_mr mr either way."""
  from lrf_jax import register
  from lrf_jax.registration.refine import ICP_POINTS
  cloud, _ = _height_field(4000, 3)
  gt = _pose([0.3, -1.0, 0.4], 20.0, [0.1, 0.2, -0.1])
  target = datasets.transform_points(gt, cloud[::-1])
  one = register(cloud, target, n_keypoints=500, n_correspondences=300, icp_fine=False)
  two = register(cloud, target, n_keypoints=500, n_correspondences=300)
  assert len(cloud) <= ICP_POINTS
  np.testing.assert_array_equal(one.coarse_transform, two.coarse_transform)
  ref, fit, _ = icp(cloud, target, one.coarse_transform, max_distance=3.0 * one.mr,
                    iterations=50)
  np.testing.assert_allclose(one.transform, ref, atol=1e-12)
  assert one.fitness == pytest.approx(fit)
  for reg in (one, two):
    err_r, err_t = pose_errors(reg.transform, gt, mr=reg.mr)
    assert err_r < 0.05 and err_t < 0.05
  with pytest.raises(ValueError, match="icp_fine"):
    register(cloud, target, icp_fine="yes")


def test_revisited_finds_a_pose_within_the_tolerance():
  rot = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
  pose = to_transform(rot, np.array([1.0, 2.0, 3.0]))
  near = to_transform(Rotation.from_rotvec([2e-8, 0.0, 0.0]).as_matrix() @ rot,
                      pose[:3, 3] + [0.0, 1e-9, 0.0])
  far = to_transform(Rotation.from_rotvec([2e-7, 0.0, 0.0]).as_matrix() @ rot, pose[:3, 3])
  other = np.eye(4)
  assert icp_host.revisited(near, [other, pose, pose], 0.1, 1e-7) == 1
  assert icp_host.revisited(far, [other, pose], 0.1, 1e-7) is None
  assert icp_host.revisited(pose, [], 0.1, 1e-7) is None


def _wavy(rng, n):
  uv = rng.uniform(-1, 1, size=(n, 2))
  z = 0.2 * np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])
  return np.c_[uv, z] + rng.normal(scale=0.01, size=(n, 3))


@pytest.mark.parametrize("seed", [1, 6, 7])
def test_a_cycle_of_pairings_stops_at_its_best_pose(seed, monkeypatch):
  """Two samplings of one surface whose pairing alternates near the optimum: the loop stops at
  the cycle instead of the iteration cap, at a pose no worse than where the cap leaves it."""
  rng = np.random.default_rng(seed)
  src, dst = _wavy(rng, 400), _wavy(rng, 400)
  init = to_transform(np.eye(3), np.array([0.03, -0.02, 0.01]))
  steps = [0]
  sums = icp_host.plane_sums

  def counted(*a, **k):
    steps[0] += 1
    return sums(*a, **k)

  monkeypatch.setattr(icp_host, "plane_sums", counted)
  kw = dict(max_distance=0.15, iterations=60, tolerance=1e-7)
  tr, _, rmse = icp_host.point_to_plane_icp(src, dst, init, **kw)
  stopped = steps[0]
  monkeypatch.setattr(icp_host, "revisited", lambda *a: None)
  steps[0] = 0
  _, _, rmse_cap = icp_host.point_to_plane_icp(src, dst, init, **kw)
  assert steps[0] == 61 and stopped < 30
  assert np.isfinite(tr).all() and rmse <= rmse_cap * (1 + 1e-9)


def test_overlap_points_are_the_source_within_the_distance():
  from lrf_jax.registration.refine import overlap_points
  rng = np.random.default_rng(0)
  target = rng.uniform(0, 1, size=(2000, 3)) * [1.0, 1.0, 0.0]   # the unit square, z = 0
  source = rng.uniform(-1, 2, size=(3000, 3)) * [1.0, 1.0, 0.0]
  source[:, 2] = rng.choice([0.0, 0.5], size=3000)                  # half of them lifted
  grid = engine.Grid(target, 0.05)
  pose = np.eye(4)
  got = overlap_points(source, grid, pose, 0.05, 10_000, np.random.default_rng(1),
                       fallback=source[:3])
  d = cKDTree(target).query(source)[0]
  np.testing.assert_array_equal(got, source[d <= 0.05])
  few = overlap_points(source, grid, pose, 0.05, 50, np.random.default_rng(1), fallback=source)
  assert len(few) == 50 and np.all(cKDTree(target).query(few)[0] <= 0.05)
  moved = to_transform(np.eye(3), np.array([0.0, 0.0, 10.0]))     # no overlap: the fallback
  np.testing.assert_array_equal(overlap_points(source, grid, moved, 0.05, 50,
                                               np.random.default_rng(1), fallback=source[:3]),
                                source[:3])


# ------------------------------------------------------------------------------------------------
# Target normals computed where ICP pairs (TargetNormals)


def test_pca_normals_at_a_subset_equal_the_rows_of_every_normal():
  pts, _ = _height_field(3000, 7)
  grid = engine.knn_grid(pts)
  at = np.random.default_rng(0).choice(len(pts), 400, replace=False)
  every = icp_normals.pca_normals(pts, 0.09, grid=grid)
  assert np.array_equal(icp_normals.pca_normals(pts, 0.09, grid=grid, at=at), every[at],
                        equal_nan=True)


def test_target_normals_are_the_estimated_ones_where_required_and_nan_elsewhere():
  pts, _ = _height_field(3000, 8)
  grid = engine.knn_grid(pts)
  lazy = icp_normals.TargetNormals(pts, 0.1, grid)
  want = icp_normals.unit_normals(icp_normals.estimate_target_normals(pts, 0.1, grid))
  idx = np.array([5, -1, 17, 5, 2999, 400])
  assert lazy.require(idx) and not lazy.require(idx[::-1])  # computed once
  done = np.unique(idx[idx >= 0])
  assert np.array_equal(lazy.unit[done], want[done]) and np.isfinite(want[done]).all()
  assert np.array_equal(lazy.pca[done], icp_normals.estimate_target_normals(pts, 0.1, grid)[done])
  rest = np.setdiff1d(np.arange(len(pts)), done)
  assert np.isnan(lazy.unit[rest]).all() and lazy.done.sum() == len(done)
  # a spacing the caller measured, as working_resolution measures it: the same radius
  spacing = float(engine.knn(engine.knn_grid(pts, 2), pts, 2)[0][:, 1].mean())
  assert icp_normals.TargetNormals(pts, 0.1, grid, spacing=spacing).radius == lazy.radius


@pytest.mark.parametrize("subset", [7, 1])
def test_icp_with_normals_computed_where_it_pairs_equals_icp_with_every_normal(subset):
  """Bit for bit: the same pose, fitness and rmse whether the target's normals are all given
  (`estimate_target_normals`) or computed on demand; on a dense target with a sparse source only
  part of the target's normals are computed."""
  target = _corner(30000, 4, 0.002)
  source = datasets.transform_points(_pose([0.3, 1.0, -0.2], 3.0, [0.02, -0.01, 0.01]),
                                     _corner(30000, 5, 0.002)[::subset])
  grid = engine.knn_grid(target)
  every = icp_normals.estimate_target_normals(target, 0.05, grid)
  want = icp(source, target, np.eye(4), max_distance=0.05, target_grid=grid,
             target_normals=every)
  lazy = icp_normals.TargetNormals(target, 0.05, grid)
  got = icp(source, target, np.eye(4), max_distance=0.05, target_grid=grid, target_normals=lazy)
  assert np.array_equal(got[0], want[0]) and got[1:] == want[1:]
  assert np.array_equal(icp(source, target, np.eye(4), max_distance=0.05, target_grid=grid)[0],
                        want[0])  # no normals given: computed on demand too
  if subset > 1:
    assert lazy.done.sum() < 0.5 * len(target)


def test_a_target_normals_of_another_cloud_is_refused():
  pts = _corner(300, 6, 0.0)
  for other in (pts[:200], pts + [0.0, 0.0, 0.01]):  # fewer points; as many, elsewhere
    with pytest.raises(ValueError, match="TargetNormals of another cloud"):
      icp(pts, other, np.eye(4), max_distance=0.1,
          target_normals=icp_normals.TargetNormals(pts, 0.1))
  same = icp_normals.TargetNormals(pts.copy(), 0.1)  # equal points in another array: accepted
  assert np.isfinite(icp(pts, pts, np.eye(4), max_distance=0.1, target_normals=same)[0]).all()

