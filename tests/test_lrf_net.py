"""LRF-Net frames: conventions, equivariance, invariances, formulas, degenerate cases, bad input."""

import functools
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lrf_jax
from lrf_jax.frames.lrf_net import (attributes, lrf_net_frames, lrf_net_weights, softmax_weights,
                                    uniform_frames)
from lrf_jax.frames.lrf_net import lrf_net_frames as _lrf_net_frames
from lrf_jax.search.neighborhoods import Patches, build_patches
from tests.reference_numpy import reference_frames
from tests.lrf_testing import (assert_frames_orthonormal, equivariance_deficit,
                               random_rotation)

PARAMS = lrf_jax.init_params(3)


@pytest.fixture(scope="module")
def bunny(br_bunny):
  pts, faces, mr, xf = br_bunny
  kp = np.random.default_rng(0).choice(len(pts), 300, replace=False)
  return pts, kp, 15 * mr, xf


def _frames(pts, kp, r, method="lrf_net", **kw):
  """Frames of `method`; lrf_net runs its exact network (lut=0) unless `lut` is given."""
  f, v = lrf_jax.compute_frames(pts, kp, r, method, **({"params": PARAMS, "lut": 0} | kw)
                                if method == "lrf_net" else kw)
  return np.asarray(f), np.asarray(v)


@pytest.mark.parametrize("method", ["lrf_net", "uniform", "toldi"])
def test_frames_orthonormal_right_handed(bunny, method):
  pts, kp, r, _ = bunny
  f, v = _frames(pts, kp, r, method)
  assert v.mean() > 0.99
  assert_frames_orthonormal(f, v)
  np.testing.assert_allclose(np.cross(f[:, 2], f[:, 0]), f[:, 1], atol=1e-5)  # y = z × x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rotation_translation_equivariance_on_real_patches(bunny, seed):
  pts, kp, r, _ = bunny
  rot = random_rotation(seed)
  t = np.random.default_rng(seed).normal(size=3)
  f, v = _frames(pts, kp, r)
  g, w = _frames(pts @ rot.T + t, kp, r)
  deficit = equivariance_deficit(f, g, rot, v, w)
  assert deficit.mean() < 1e-4, deficit.max()
  np.testing.assert_array_equal(v, w)


def test_meancos_under_ground_truth_is_one(bunny):
  """Noise-free model vs the model under its .xf: catches direction and transpose errors."""
  pts, kp, r, xf = bunny
  scene = pts @ xf[:3, :3].T + xf[:3, 3]
  f, v = _frames(pts, kp, r)
  g, w = _frames(scene, kp, r)
  mc = np.asarray(lrf_jax.meancos(f, g, xf, v, w))
  assert mc.mean() > 0.9999
  # ... and the transposed rotation must NOT give 1: the check has teeth.
  assert np.asarray(lrf_jax.meancos(f, g, xf[:3, :3].T, v, w)).mean() < 0.9


@pytest.mark.parametrize("weights,method", [("lrf_net", "lrf_net"), ("uniform", "uniform"),
                                            ("toldi", "toldi")])
def test_matches_numpy_reference(bunny, weights, method):
  pts, kp, r, _ = bunny
  kp = kp[:60]
  k = None if method == "toldi" else 256
  f, v = _frames(pts, kp, r, method)
  fr, vr = reference_frames(pts, kp, r, weights=weights, params=PARAMS, k=k)
  np.testing.assert_array_equal(v, vr)
  np.testing.assert_allclose(f[v], fr[v], atol=2e-4)


def test_z_sign_rule(bunny):
  """Σ (p - q_i)·z >= 0 over the neighbors within r/3."""
  pts, kp, r, _ = bunny
  f, v = _frames(pts, kp, r)
  for i, frame in zip(kp[v], f[v]):
    d = pts - pts[i]
    inner = d[np.linalg.norm(d, axis=1) <= r / 3]
    assert np.sum(-inner @ frame[2]) >= 0


def test_uniform_weights_give_normalised_sum_of_tangent_projections(bunny):
  pts, kp, r, _ = bunny
  patches = build_patches(pts, kp[:20], r, 256)
  f, v = uniform_frames(jax.tree.map(jnp.asarray, patches))
  for n in range(20):
    z = np.asarray(f[n, 2], np.float64)
    off = patches.offsets[n][patches.mask[n]].astype(np.float64)
    s = (off - np.outer(off @ z, z)).sum(0)
    np.testing.assert_allclose(np.asarray(f[n, 0]), s / np.linalg.norm(s), atol=1e-5)


def test_attributes_formula():
  off = jnp.array([[1.0, 0, 0], [0, 0, 2.0], [0, 0, 0], [1.0, 0, 1.0]])
  a = attributes(off, jnp.array([0, 0, 1.0]), jnp.asarray(2.0))
  np.testing.assert_allclose(a, [[0.5, 0], [1.0, 1.0], [0, 0], [np.sqrt(2) / 2, np.sqrt(0.5)]],
                             atol=1e-6)


def _jnp(p: Patches) -> Patches:
  return jax.tree.map(jnp.asarray, p)


@pytest.mark.parametrize("x_mode", ["sum", "softmax"])
def test_neighbor_order_and_padding_invariance(bunny, x_mode):
  pts, kp, r, _ = bunny
  p = build_patches(pts, kp[:50], r, 256)
  lrf_net_frames = functools.partial(_lrf_net_frames, x_mode=x_mode)
  f, v = lrf_net_frames(PARAMS, _jnp(p))
  perm = np.random.default_rng(0).permutation(p.k)
  shuffled = p._replace(offsets=p.offsets[:, perm], mask=p.mask[:, perm],
                        indices=p.indices[:, perm])
  f2, v2 = lrf_net_frames(PARAMS, _jnp(shuffled))
  np.testing.assert_allclose(f, f2, atol=2e-6)
  pad = 77
  padded = p._replace(
      offsets=np.concatenate([p.offsets, np.full((50, pad, 3), 123.0, np.float32)], 1),
      mask=np.concatenate([p.mask, np.zeros((50, pad), bool)], 1),
      indices=np.concatenate([p.indices, -np.ones((50, pad), np.int32)], 1))
  f3, v3 = lrf_net_frames(PARAMS, _jnp(padded))
  np.testing.assert_allclose(f, f3, atol=2e-6)
  np.testing.assert_array_equal(v, v3)
  np.testing.assert_array_equal(v, v2)


def test_subsample_independent_of_coordinates_and_search_order(bunny):
  pts, kp, r, _ = bunny
  rot = random_rotation(5)
  a = build_patches(pts, kp[:40], r, 64, seed=7)
  b = build_patches(pts @ rot.T + 3.0, kp[:40], r, 64, seed=7)
  assert (a.count > 64).all()
  for i in range(40):
    assert set(a.indices[i]) == set(b.indices[i])
  c = build_patches(pts, kp[:40], r, 64, seed=8)
  assert any(set(a.indices[i]) != set(c.indices[i]) for i in range(40))
  # permuting the order of the cloud (and the keypoint ids with it) permutes nothing else
  perm = np.random.default_rng(1).permutation(len(pts))
  inv = np.argsort(perm)
  d = build_patches(pts[perm], inv[kp[:40]], r, None)
  e = build_patches(pts, kp[:40], r, None)
  for i in range(40):
    assert set(perm[d.indices[i][d.mask[i]]]) == set(e.indices[i][e.mask[i]])


def test_patches_match_brute_force_ball(bunny):
  pts, kp, r, _ = bunny
  p = build_patches(pts, kp[:30], r, None)
  for i, c in enumerate(kp[:30]):
    ball = np.flatnonzero(np.linalg.norm(pts - pts[c], axis=1) <= r)
    assert set(p.indices[i][p.mask[i]]) == set(ball)
    assert p.count[i] == len(ball)
    inner = pts[np.linalg.norm(pts - pts[c], axis=1) <= r / 3] - pts[c]
    assert p.z_count[i] == len(inner)
    np.testing.assert_allclose(p.z_mean[i], inner.mean(0), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(p.z_cov[i], np.cov(inner.T, bias=True), rtol=1e-4, atol=1e-11)


def test_all_neighbor_k_ladder_and_cap(bunny):
  pts, kp, r, _ = bunny
  full = build_patches(pts, kp[:40], r, None)
  biggest = int(full.count.max())
  assert full.k >= biggest and full.k <= 1.5 * biggest  # next ladder size: at most 1.5x padding
  assert full.k in {s << j for s in (32, 48) for j in range(12)}
  cap = 64
  capped = build_patches(pts, kp[:40], r, None, max_k=cap)
  assert capped.k == cap and biggest > cap
  # A capped ball keeps the same seeded subsample as the integer K: its first `cap` priorities.
  fixed = build_patches(pts, kp[:40], r, cap)
  np.testing.assert_array_equal(capped.indices, fixed.indices)
  np.testing.assert_array_equal(capped.count, full.count)


# ----------------------------------------------------------------------------- degenerate cases


def _single(points, r=1.0, k=64, method="lrf_net"):
  f, v = lrf_jax.compute_frames(points, np.array([0]), r, method,
                                **({"params": PARAMS} if method == "lrf_net" else {}), k=k)
  f = np.asarray(f)
  assert np.isfinite(f).all()
  return f[0], bool(v[0])


@pytest.mark.parametrize("method", ["lrf_net", "uniform", "toldi"])
def test_too_few_neighbors_is_invalid(method):
  pts = np.array([[0, 0, 0], [0.1, 0, 0], [5, 5, 5.0]])
  f, v = _single(pts, method=method)
  assert not v and np.array_equal(f, np.eye(3))


@pytest.mark.parametrize("method", ["lrf_net", "uniform", "toldi"])
def test_duplicates_are_invalid(method):
  f, v = _single(np.zeros((20, 3)), method=method)
  assert not v and np.array_equal(f, np.eye(3))


@pytest.mark.parametrize("method", ["lrf_net", "uniform", "toldi"])
def test_collinear_is_invalid(method):
  t = np.linspace(-0.2, 0.2, 41)
  f, v = _single(np.stack([t, 2 * t, -t], 1)[np.argsort(np.abs(t))], method=method)
  assert not v and np.array_equal(f, np.eye(3))


def test_symmetric_planar_patch_with_uniform_weights_is_invalid():
  g = np.linspace(-0.3, 0.3, 13)
  xx, yy = np.meshgrid(g, g)
  grid = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
  grid = grid[np.argsort(np.linalg.norm(grid, axis=1), kind="stable")]  # keypoint first
  f, v = _single(grid, r=0.9, k=None, method="uniform")
  assert not v


def test_nan_in_patch_is_invalid_not_nan():
  pts = np.random.default_rng(0).normal(size=(200, 3)) * [1, 1, 0.05]
  p = build_patches(pts, np.arange(5), 1.5, 64)
  off = p.offsets.copy()
  off[2, 0] = np.nan
  cov = p.z_cov.copy()
  cov[3, 0, 0] = np.inf
  with jax.debug_nans(False):  # the NaN is in the input on purpose; none may come out
    f, v = jax.jit(lrf_net_frames)(PARAMS, _jnp(p._replace(offsets=off, z_cov=cov)))
  assert np.isfinite(np.asarray(f)).all()
  assert not v[2] and not v[3] and v[0]


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("points,match", [
    (np.zeros((0, 3)), "empty"),
    (np.zeros((10, 2)), r"shape \(n, 3\)"),
    (np.array([[0, 0, np.nan]] * 5), "non-finite"),
    (np.array([["a", "b", "c"]]), "dtype"),
])
def test_bad_cloud_raises(points, match):
  with pytest.raises(ValueError, match=match):
    lrf_jax.compute_frames(points, np.array([0]), 1.0)


def test_bad_keypoints_and_radius_raise():
  pts = np.random.default_rng(0).normal(size=(50, 3))
  with pytest.raises(ValueError, match=r"out of range.*\[0, 50\)"):
    lrf_jax.compute_frames(pts, np.array([3, 50]), 1.0)
  with pytest.raises(ValueError, match="integer"):
    lrf_jax.compute_frames(pts, np.array([0.5]), 1.0)
  for r in (0.0, -1.0, float("nan")):
    with pytest.raises(ValueError, match="radius"):
      lrf_jax.compute_frames(pts, np.array([0]), r)
  with pytest.raises(ValueError, match="unknown LRF method"):
    lrf_jax.compute_frames(pts, np.array([0]), 1.0, method="nope")


def test_chunked_equals_single_call(bunny):
  pts, kp, r, _ = bunny
  f1, v1 = _frames(pts, kp[:100], r)
  f2, v2 = _frames(pts, kp[:100], r, chunk_size=32)
  np.testing.assert_allclose(f1, f2, atol=1e-6)
  np.testing.assert_array_equal(v1, v2)


def test_methods_registry_lists_lrf_net():
  assert "lrf_net" in lrf_jax.METHODS and lrf_jax.METHODS["lrf_net"].needs_params
  assert "toldi" in lrf_jax.METHODS
  f = lrf_jax.geometry.ops.frame_from_zx(jnp.array([0, 0, 1.0]), jnp.array([1.0, 1.0, 5.0]))[0]
  np.testing.assert_allclose(f, [[np.sqrt(.5), np.sqrt(.5), 0], [-np.sqrt(.5), np.sqrt(.5), 0],
                                 [0, 0, 1]], atol=1e-6)


def test_lrf_net_plus_viewpoint_sign():
  """With a sensor viewpoint lrf_net_plus's z faces the sensor, equivariantly; without one the
  ball sign decides (here it points away from a sensor above this bump on one side)."""
  rng = np.random.default_rng(5)
  xy = rng.uniform(-3, 3, (6000, 2))
  pts = np.c_[xy, np.exp(-np.sum(xy**2, 1))]  # a bump seen from +z
  vp = np.array([0.0, 0.0, 30.0])
  kp = np.arange(0, 6000, 53)
  f, v = map(np.asarray, lrf_jax.compute_frames(pts, kp, 1.0, "lrf_net_plus", params=PARAMS,
                                                viewpoint=vp))
  assert v.mean() > 0.9
  assert (np.einsum("nc,nc->n", f[v, 2], vp - pts[kp][v]) > 0).all()
  rot, t = random_rotation(4), np.array([1.0, -2.0, 0.5])
  g, w = map(np.asarray, lrf_jax.compute_frames(pts @ rot.T + t, kp, 1.0, "lrf_net_plus",
                                                params=PARAMS, viewpoint=rot @ vp + t))
  assert equivariance_deficit(f, g, rot, v, w).mean() < 1e-4
  h, _ = map(np.asarray, lrf_jax.compute_frames(pts, kp, 1.0, "lrf_net_plus", params=PARAMS))
  flipped = np.einsum("nc,nc->n", h[:, 2], f[:, 2]) < 0
  assert flipped[v].any()  # the viewpoint changes the sign where the ball rule disagrees


def test_lrf_net_plus_equivariant_and_ball_sign_rule(bunny):
  """lrf_net_plus: rotation equivariant (z from the points alone by default on a cloud); with
  oriented_sign=False z is oriented so that Σ (p - q_i)·z >= 0 over the patch."""
  pts, kp, r, _ = bunny
  rot = random_rotation(11)
  for opts in ({}, {"oriented_sign": False}):
    f, v = lrf_jax.compute_frames(pts, kp, r, "lrf_net_plus", params=PARAMS, **opts)
    g, w = lrf_jax.compute_frames(pts @ rot.T - 2.0, kp, r, "lrf_net_plus", params=PARAMS,
                                  **opts)
    f, v, g, w = map(np.asarray, (f, v, g, w))
    assert equivariance_deficit(f, g, rot, v, w).mean() < 1e-4
    assert_frames_orthonormal(f, v)
  p = build_patches(pts, kp, r, lrf_jax.METHODS["lrf_net_plus"].default_k)
  for n in np.flatnonzero(v):
    off = p.offsets[n][p.mask[n]]
    assert np.sum(-off @ f[n, 2]) >= 0
  # it is a different rule from TOLDI's r/3 one: on some keypoints the two disagree
  t, _ = lrf_jax.compute_frames(pts, kp, r, "lrf_net", params=PARAMS)
  assert np.any(np.sum(np.asarray(t)[:, 2] * f[:, 2], axis=-1) < 0)


def test_lut_weights_match_exact_network(bunny):
  """`lut=257`: the tabulated weight map gives the exact frames up to interpolation error."""
  pts, kp, r, _ = bunny
  exact, v = _frames(pts, kp, r)
  fast, w = _frames(pts, kp, r, lut=257)
  np.testing.assert_array_equal(v, w)
  cos_x = np.sum(exact[:, 0] * fast[:, 0], axis=-1)
  assert (1 - cos_x[v]).max() < 1e-3 and (1 - cos_x[v]).mean() < 1e-5
  rot = random_rotation(4)
  moved, wm = _frames(pts @ rot.T, kp, r, lut=257)
  assert equivariance_deficit(fast, moved, rot, w, wm).mean() < 1e-4
  # The default call is the table (the fast path); lut=0 is one keyword away.
  default, _ = lrf_jax.compute_frames(pts, kp, r, "lrf_net", params=PARAMS)
  np.testing.assert_array_equal(np.asarray(default), fast)


def test_weight_table_is_cached_and_equals_the_parameters_path(bunny):
  """`compute_frames(lut=)` builds the table once per parameter set; a prebuilt WeightTable
  gives exactly the frames of the parameters."""
  from lrf_jax.frames import patch_frames
  from lrf_jax.frames.lrf_net import WeightTable, weight_table

  pts, kp, r, _ = bunny
  p = _jnp(build_patches(pts, kp[:40], r, 256))
  table = weight_table(PARAMS, 65)
  assert isinstance(table, WeightTable) and table.values.shape == (65, 65)
  a = _lrf_net_frames(PARAMS, p, lut=65)
  b = _lrf_net_frames(table, p, lut=65)
  np.testing.assert_array_equal(np.asarray(a[0]), np.asarray(b[0]))
  with pytest.raises(ValueError, match="WeightTable of shape"):
    _lrf_net_frames(table, p, lut=33)
  patch_frames.WEIGHT_TABLES.clear()
  f1, _ = _frames(pts, kp[:40], r, lut=65)
  cached = patch_frames.WEIGHT_TABLES[-1][-1]
  f2, _ = _frames(pts, kp[:40], r, lut=65)
  assert len(patch_frames.WEIGHT_TABLES) == 1 and patch_frames.WEIGHT_TABLES[-1][-1] is cached
  np.testing.assert_array_equal(f1, f2)


def test_prepare_view_precedence(br_bunny):
  """lrf_net_plus's sign reference: viewpoint, else given normals, else winding-oriented normals."""
  from lrf_jax.frames.lrf_net_plus import prepare_view
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals

  points, faces, mr, _ = br_bunny
  kp = np.arange(0, len(points), 997)
  r = 15 * mr
  patches = build_patches(points, kp, r, 256)
  vp = np.array([0.0, 1.0, 0.0])
  got = prepare_view(points, kp, patches, faces=faces, radius=r, viewpoint=vp).view
  np.testing.assert_allclose(got, vp - points[kp], atol=1e-6)
  nrm = np.tile([0.0, 0.0, 1.0], (len(points), 1))
  got = prepare_view(points, kp, patches, faces=faces, normals=nrm, radius=r).view
  near = patches.mask & (np.linalg.norm(patches.offsets, axis=-1) <= r / 3)
  np.testing.assert_allclose(got, nrm[kp] * near.sum(1)[:, None])  # summed over the z support
  assert (near.sum(1) < patches.mask.sum(1)).all()
  est = estimate_normals(points, NORMAL_RADIUS_RATIO * r, faces)
  want = np.stack([np.nansum(est[i[m]], 0) for i, m in zip(patches.indices, near)])
  np.testing.assert_allclose(prepare_view(points, kp, patches, faces=faces, radius=r).view,
                             want, rtol=1e-5, atol=1e-4)
  # Nothing but the points: normals oriented from the cloud (`voted_normals`), summed over the z
  # support where the vote is trusted, else zero (the ball sign).
  from lrf_jax.frames.lrf_net_plus import MIN_VOTE_TRUST
  from lrf_jax.geometry.normals import voted_normals
  alone = prepare_view(points, kp, patches, radius=r)
  voted, trust = voted_normals(points, NORMAL_RADIUS_RATIO * r, r)
  want = np.stack([np.nansum(voted[i[m]], 0) for i, m in zip(patches.indices, near)])
  ok = alone.trust >= MIN_VOTE_TRUST
  assert ok.mean() > 0.9 and (alone.trust <= 1).all()
  np.testing.assert_allclose(alone.view[ok], want[ok], rtol=1e-5, atol=1e-4)
  assert not alone.view[~ok].any() and not alone.trust[~ok].any()
  assert not prepare_view(points, kp, None).view.any()  # no patches: the ball sign
  f, v = lrf_jax.compute_frames(points, kp, r, "lrf_net_plus", params=PARAMS, faces=faces)
  assert (np.einsum("nc,nc->n", np.asarray(f)[:, 2], want) >= 0).all()


def test_patch_areas_follow_sampling_density():
  from lrf_jax.frames.lrf_net_plus import patch_areas

  rng = np.random.default_rng(2)
  sparse = rng.uniform([-2, -2], [0, 2], (2000, 2))
  dense = rng.uniform([0, -2], [2, 2], (8000, 2))  # 4x the density on the right half
  pts = np.c_[np.concatenate([sparse, dense]), np.zeros(10000)]
  kp = np.flatnonzero(np.abs(pts[:, 0]) < 0.05)[:20]  # on the seam: both densities in each patch
  patches = build_patches(pts, kp, 0.8, 256)
  a = patch_areas(pts, patches)
  valid = patches.mask
  np.testing.assert_allclose(a.sum(1) / valid.sum(1), 1.0, rtol=1e-5)
  assert (a[~valid] == 0).all()
  left = valid & (patches.offsets[..., 0] + pts[kp, 0][:, None] < -0.1)
  right = valid & (patches.offsets[..., 0] + pts[kp, 0][:, None] > 0.1)
  ratio = a[left].mean() / a[right].mean()
  assert 3.0 < ratio < 5.5, ratio  # a sparse point stands for ~4x the area
  rot = random_rotation(6)
  moved = build_patches(pts @ rot.T + 1.0, kp, 0.8, 256)
  np.testing.assert_allclose(patch_areas(pts @ rot.T + 1.0, moved), a, rtol=1e-4)


def test_patch_areas_are_the_numpy_expression_bit_for_bit(br_bunny):
  # The compiled pass (`lrf_net_plus_sums.relative_areas`) against the numpy lines it replaced,
  # on a cloud and a mesh, with padding (k=None: uneven rows) and numpy's pairwise row sums.
  from lrf_jax.frames.lrf_net_plus import patch_areas
  from lrf_jax.geometry.cloud_cache import cache_last

  points, faces, mr, _ = br_bunny
  kp = np.arange(0, len(points), 397)
  for k, f in ((512, None), (None, None), (100, faces)):
    patches = build_patches(points, kp, 15 * mr, k)
    got = patch_areas(points, patches, f)
    per_point = cache_last("point_area", (np.asarray(points, np.float64),) + (
        () if f is None else (np.asarray(f),)), lambda: None)
    a = np.append(per_point, 0.0).take(np.asarray(patches.indices))
    count = np.count_nonzero(np.asarray(patches.mask), axis=1)[:, None]
    mean = a.sum(1, keepdims=True) / np.maximum(count, 1)
    want = np.divide(a, np.where(mean > 0, mean, 1.0), out=np.empty(a.shape, np.float32),
                     casting="same_kind")
    np.testing.assert_array_equal(got, want)


def test_patch_areas_of_a_mesh_are_barycentric():
  """With faces, a vertex stands for a third of its triangles' area (they sum to the mesh's)."""
  from lrf_jax.frames.lrf_net_plus import patch_areas, vertex_areas

  # a 2 x 1 strip: left square cut into 2 triangles, right square into 8 (finer on the right)
  g = np.array([[x, y, 0.0] for y in (0, 1) for x in (0, 1, 2)])  # 0..5
  mid = np.array([[1.5, 0.5, 0.0], [1.5, 0.0, 0.0], [2.0, 0.5, 0.0], [1.5, 1.0, 0.0],
                  [1.0, 0.5, 0.0]])  # 6..10
  pts = np.concatenate([g, mid, [[9.0, 9.0, 9.0]]])  # 11: a vertex on no triangle
  faces = np.array([[0, 1, 4], [0, 4, 3], [1, 7, 6], [7, 2, 6], [2, 8, 6], [8, 5, 6],
                    [5, 9, 6], [9, 4, 6], [4, 10, 6], [10, 1, 6]])
  va = vertex_areas(pts, faces)
  np.testing.assert_allclose(va.sum(), 2.0)
  np.testing.assert_allclose(va[0], 1.0 / 3.0)  # two triangles of 1/2
  assert va[11] == 0
  p = Patches(offsets=(pts - pts[6]).astype(np.float32)[None], mask=np.ones((1, 12), bool),
              indices=np.arange(12, dtype=np.int32)[None], z_cov=np.eye(3, dtype=np.float32)[None],
              z_mean=np.zeros((1, 3), np.float32), z_count=np.array([12], np.int32),
              count=np.array([12], np.int32), radius=np.array([20.0], np.float32))
  a = patch_areas(pts, p, faces)[0]
  np.testing.assert_allclose(a.mean(), 1.0, rtol=1e-6)
  np.testing.assert_allclose(a[:11] / a[0], va[:11] / va[0], rtol=1e-6)
  assert a[11] > 0  # the isolated vertex falls back to the nearest-neighbor estimate


def test_softmax_weights_properties():
  """exp(s - max s) over real neighbors: in (0, 1], 1 at the best, 0 in padding, shift-free."""
  rng = np.random.default_rng(0)
  s = jnp.asarray(rng.normal(scale=5.0, size=(4, 9)), jnp.float32)
  mask = jnp.asarray(rng.random((4, 9)) < 0.7).at[:, 0].set(True)
  w = np.asarray(softmax_weights(s, mask))
  assert np.all(w[~np.asarray(mask)] == 0) and np.all(w[np.asarray(mask)] > 0)
  np.testing.assert_allclose(w.max(1), 1.0)
  np.testing.assert_allclose(np.asarray(softmax_weights(s + 30.0, mask)), w, rtol=1e-4, atol=1e-7)
  big = s.at[:, -1].set(1e4)  # a huge score in padding changes nothing
  np.testing.assert_allclose(np.asarray(softmax_weights(big, mask.at[:, -1].set(False))),
                             np.asarray(softmax_weights(s, mask.at[:, -1].set(False))))
  assert np.all(np.asarray(softmax_weights(s, jnp.zeros_like(mask))) == 0)  # no NaN


def test_softmax_x_matches_numpy(bunny):
  """x_mode="softmax": x = normalised Σ exp(s_i) v_i in float64 numpy, with s the network."""
  pts, kp, r, _ = bunny
  p = build_patches(pts, kp[:20], r, 256)
  f, v = _lrf_net_frames(PARAMS, _jnp(p), x_mode="softmax")
  s = np.asarray(lrf_net_weights(PARAMS)(jnp.asarray(p.offsets), f[:, 2], jnp.asarray(p.radius)),
                 np.float64)
  for n in np.flatnonzero(np.asarray(v)):
    z = np.asarray(f[n, 2], np.float64)
    off = p.offsets[n][p.mask[n]].astype(np.float64)
    e = np.exp(s[n][p.mask[n]] - s[n][p.mask[n]].max())
    x = (e[:, None] * (off - np.outer(off @ z, z))).sum(0)
    np.testing.assert_allclose(np.asarray(f[n, 0]), x / np.linalg.norm(x), atol=1e-4)


def test_lrf_net_plus_default_lut_is_close_to_the_exact_network(bunny):
  """lrf_net_plus reads its weights from a 257 x 257 table by default; lut=0 is exact."""
  pts, kp, r, _ = bunny
  assert dict(lrf_jax.METHODS["lrf_net_plus"].default_options)["lut"] == 257
  fast, v = _frames(pts, kp, r, "lrf_net_plus")
  exact, w = _frames(pts, kp, r, "lrf_net_plus", lut=0)
  np.testing.assert_array_equal(v, w)
  cos_x = np.sum(exact[:, 0] * fast[:, 0], axis=-1)[v]
  assert (1 - cos_x).max() < 1e-3 and (1 - cos_x).mean() < 1e-5
  assert (1 - cos_x).max() > 0  # the two paths really differ


def _noisy_height_field():
  from tests.lrf_testing import synthetic_mesh
  points, faces, keypoints, radius = synthetic_mesh()
  rng = np.random.default_rng(11)
  noisy = points.copy()
  noisy[:41 * 41] += rng.normal(scale=0.05, size=(41 * 41, 3))  # the degenerate parts stay so
  grid_kp = rng.choice(41 * 41, 400, replace=False)
  return noisy, np.r_[grid_kp, keypoints[-2:]], radius  # with the two degenerate keypoints


def test_numpy_weight_table_equals_the_jitted_one():
  """The host kernels' table (numpy float32) is the jitted table up to float32 rounding."""
  from lrf_jax.frames.lrf_net import weight_table, weight_table_numpy
  a = np.asarray(weight_table(PARAMS, 129).values)
  b = weight_table_numpy(PARAMS, 129).values
  assert isinstance(b, np.ndarray) and b.dtype == np.float32 and b.shape == (129, 129)
  np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5 * np.abs(a).max())
  assert np.abs(a).max() > 0.1  # a table that could differ


@pytest.mark.parametrize("method,options", [
    ("lrf_net", {}), ("lrf_net", {"x_mode": "softmax"}), ("lrf_net_plus", {}),
    ("lrf_net_plus", {"density": False, "oriented_sign": False}), ("uniform", {}),
    ("uniform", {"z_sign": "ball"}), ("lrf_net_plus", {"points_only": True})])
def test_host_patch_kernel_gives_the_jitted_frames(method, options):
  # The CPU default of the learned methods (numba, float64) against their jitted float32
  # function on the same patches: the same validity, axes equal to float32 rounding.
  # "points_only": lrf_net_plus without a viewpoint (z oriented from the points alone).
  pts, kp, r = _noisy_height_field()
  options = dict(options)
  alone = options.pop("points_only", False)
  view = ({"viewpoint": np.array([20.0, 20.0, 40.0])}
          if method == "lrf_net_plus" and not alone else {})
  fj, vj = lrf_jax.compute_frames(pts, kp, r, method, kernel="jit", **options, **view)
  fh, vh = lrf_jax.compute_frames(pts, kp, r, method, kernel="host", **options, **view)
  fj, vj, fh, vh = map(np.asarray, (fj, vj, fh, vh))
  np.testing.assert_array_equal(vj, vh)
  assert vj[:-2].all() and not vj[-2:].any()
  # float32 sums of K terms in the jitted function: about 1e-6 typically, 1e-4 at worst.
  np.testing.assert_allclose(fh, fj, atol=1e-4)
  assert np.median(np.abs(fh - fj)) < 1e-6
  assert_frames_orthonormal(fh, vh)


def test_compute_frames_picks_the_host_patch_kernel_on_the_cpu(monkeypatch):
  from lrf_jax.frames import compute, lrf_net_host
  monkeypatch.setattr(compute, "backend_is_cpu", lambda: True)  # the CPU's choice, on any machine
  calls = []
  real = lrf_net_host.lrf_net_frames_host
  monkeypatch.setattr(lrf_net_host, "lrf_net_frames_host",
                      lambda *a, **kw: calls.append(kw.get("x_mode")) or real(*a, **kw))
  pts, kp, r = _noisy_height_field()
  lrf_jax.compute_frames(pts, kp, r, "lrf_net")  # default lut=257 on the CPU: host
  lrf_jax.compute_frames(pts, kp, r, "lrf_net", lut=0)  # the exact network: jitted
  lrf_jax.compute_frames(pts, kp, r, "lrf_net", x_mode="max")  # the ablation's max: jitted
  lrf_jax.compute_frames(pts, kp, r, "lrf_net", kernel="jit")
  assert calls == ["sum"]
  with pytest.raises(ValueError, match="no host kernel for the options"):
    lrf_jax.compute_frames(pts, kp, r, "lrf_net", lut=0, kernel="host")


@pytest.mark.parametrize("numpy_form", [False, True])
def test_default_params_hand_out_no_shared_dict(numpy_form):
  """Replacing a leaf of `default_params()`'s result changed every later call (the cached dict
  was handed out); the numpy form's arrays are read-only."""
  from lrf_jax.frames.weights import default_params, default_params_numpy
  get = default_params_numpy if numpy_form else default_params
  p = get("lrf_net")
  kernel = np.array(p["out"]["kernel"])
  p["out"]["kernel"] = np.zeros_like(kernel)
  np.testing.assert_array_equal(get("lrf_net")["out"]["kernel"], kernel)
  if numpy_form:
    with pytest.raises(ValueError, match="read-only"):
      get("lrf_net")["out"]["bias"][...] = 0


@pytest.mark.parametrize("host", [False, True])
def test_weight_table_follows_the_parameters_content(host):
  """The LRF-Net weight table was cached by the identity of `params`: a leaf replaced (or
  written in place) kept the old table. It is keyed by content now."""
  from lrf_jax.frames import patch_frames
  from lrf_jax.frames.weights import default_params_numpy
  p = jax.tree.map(np.array, default_params_numpy("lrf_net"))  # writable copies
  first = np.array(patch_frames.cached_weight_table(p, 17, host=host).values)
  same = jax.tree.map(np.array, p)
  assert patch_frames.cached_weight_table(same, 17, host=host).values is not None
  np.testing.assert_array_equal(np.asarray(patch_frames.cached_weight_table(same, 17, host=host).values), first)
  p["out"]["bias"] = p["out"]["bias"] + 3.0  # a leaf replaced in the same dict
  replaced = np.asarray(patch_frames.cached_weight_table(p, 17, host=host).values)
  assert not np.array_equal(replaced, first)
  p["enc0"]["kernel"][...] *= -1.0  # a leaf written in place
  written = np.asarray(patch_frames.cached_weight_table(p, 17, host=host).values)
  assert not np.array_equal(written, replaced)
  fresh = jax.tree.map(np.array, p)
  np.testing.assert_array_equal(np.asarray(patch_frames.cached_weight_table(fresh, 17, host=host).values),
                                written)


def test_weight_table_under_jit_is_not_cached():
  from lrf_jax.frames import patch_frames
  from lrf_jax.frames.weights import default_params
  before = len(patch_frames.WEIGHT_TABLES)
  values = jax.jit(lambda p: patch_frames.cached_weight_table(p, 9).values)(default_params("lrf_net"))
  assert values.shape[:2] == (9, 9) and len(patch_frames.WEIGHT_TABLES) == before
