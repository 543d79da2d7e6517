"""Hand-crafted LRFs (mian, shot, rops, board, flare, ps, gframes, toldi): what is theirs.

Rotation + translation equivariance on real BR bunny patches (exact, except Mian's x/y, which are
sign-ambiguous by definition); mesh methods refusing clouds; the default normals; TOLDI's signed
vs unsigned x weights, SHOT's batched tie rule, and the normal estimation's equivariance. The
properties every registered method shares (orthonormal, degenerate keypoints invalid, slot order
and padding invariance, NaN input) are in test_method_properties.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets
from lrf_jax.geometry import normals as nm
from lrf_jax.frames import shot as shot_mod
from tests.lrf_testing import (N_GOOD, assert_frames_orthonormal, equivariance_deficit,
                               random_rotation, synthetic_mesh)

METHODS = ("toldi", "mian", "shot", "rops", "board", "flare", "ps", "gframes")
EXACT = 1e-4  # largest allowed 1 - MeanCos for "exact" equivariance (float32 round-off: ~1e-7)


SYN = synthetic_mesh()


@pytest.fixture(scope="module")
def synthetic_normals():
  points, faces, _, radius = SYN
  return nm.estimate_normals(points, nm.NORMAL_RADIUS_RATIO * radius, faces)


def test_mesh_methods_need_faces():
  points, _, keypoints, radius = SYN
  for m in ("rops", "gframes"):
    with pytest.raises(ValueError, match="needs a triangle mesh"):
      lrf_jax.compute_frames(points, keypoints, radius, m)


def test_default_normals_are_estimated():
  """Without `normals=`, the normal methods use normals.estimate_normals at 0.2 r (cached)."""
  points, faces, keypoints, radius = SYN
  for faces_arg in (faces, None):
    own = nm.estimate_normals(points, nm.NORMAL_RADIUS_RATIO * radius, faces_arg)
    f0, v0 = lrf_jax.compute_frames(points, keypoints, radius, "board", faces=faces_arg)
    f1, v1 = lrf_jax.compute_frames(points, keypoints, radius, "board", faces=faces_arg,
                                    normals=own)
    assert np.asarray(v0)[:N_GOOD].all()
    np.testing.assert_array_equal(np.asarray(f0), np.asarray(f1))


def test_nan_keypoint_normal_is_invalid(synthetic_normals):
  points, faces, keypoints, radius = SYN
  bad_normals = synthetic_normals.copy()
  bad_normals[keypoints[0]] = np.nan
  for m in ("mian", "ps", "gframes"):
    _, v = lrf_jax.compute_frames(points, keypoints[:2], radius, m, faces=faces,
                                  normals=bad_normals)
    assert not bool(v[0]) and bool(v[1]), m


# ----------------------------------------------------------------------------------------------
# Real data: equivariance on BR bunny patches.
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bunny_setup(br_bunny):
  points, faces, mr, _ = br_bunny
  radius = 15.0 * mr
  normals = nm.estimate_normals(points, nm.NORMAL_RADIUS_RATIO * radius, faces)
  keypoints = np.random.default_rng(11).choice(points.shape[0], 48, replace=False)
  rot = random_rotation(5)
  shift = np.array([0.4, -1.3, 2.2])
  return points, faces, radius, normals, keypoints, rot, shift


@pytest.mark.data
@pytest.mark.parametrize("method", METHODS)
def test_bunny_equivariance(method, bunny_setup):
  points, faces, radius, normals, keypoints, rot, shift = bunny_setup
  f0, v0 = lrf_jax.compute_frames(points, keypoints, radius, method, faces=faces,
                                  normals=normals)
  f1, v1 = lrf_jax.compute_frames(points @ rot.T + shift, keypoints, radius, method, faces=faces,
                                  normals=normals @ rot.T)
  f0, v0, f1, v1 = map(np.asarray, (f0, v0, f1, v1))
  assert_frames_orthonormal(f0, v0)
  assert_frames_orthonormal(f1, v1)
  assert v0.mean() > 0.95, f"{method}: only {v0.mean():.2f} valid on the bunny"
  np.testing.assert_array_equal(v0, v1)
  if method == "mian":
    # z is fixed by the normal: exact; x (and y) only up to sign, by construction.
    cz = np.sum((f0[:, 2] @ rot.T) * f1[:, 2], -1)
    assert cz[v0].min() > 1 - EXACT
    deficit = equivariance_deficit(f0, f1, rot, v0, v1, up_to_sign=True)
    # ... and the ambiguity is real: some x axes come back flipped (about half on the bunny).
    assert (equivariance_deficit(f0, f1, rot, v0, v1) > 0.5).any()
  else:
    deficit = equivariance_deficit(f0, f1, rot, v0, v1)
  assert deficit[v0].max() < EXACT, f"{method}: max 1 - MeanCos = {deficit[v0].max():.2e}"


@pytest.mark.data
def test_normals_equivariant_and_consistent(br_bunny):
  points, faces, mr, _ = br_bunny
  rn = 3.0 * mr
  rot, shift = random_rotation(8), np.array([1.0, 2.0, -3.0])
  moved = points @ rot.T + shift
  mesh = nm.estimate_normals(points, rn, faces)
  prop = nm.estimate_normals(points, rn)  # MST propagation
  assert np.isfinite(mesh).all()
  # Propagation orients (almost) every normal as the mesh's winding does.
  agree = np.einsum("ij,ij->i", mesh, prop) > 0
  assert agree.mean() > 0.99, agree.mean()
  for faces_arg, ref in ((faces, mesh), (None, prop)):
    got = nm.estimate_normals(moved, rn, faces_arg)
    cos = np.einsum("ij,ij->i", ref @ rot.T, got)
    assert (cos > 1 - 1e-6).mean() > 0.999, (faces_arg is None, np.sort(cos)[:5])


def _scipy_orientation(points, normals, k=nm.PROPAGATION_K):
  """Reference: Hoppe propagation with scipy's Kruskal MST walked breadth first."""
  from scipy.sparse import coo_matrix
  from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
  from scipy.spatial import cKDTree
  good = np.all(np.isfinite(normals), 1)
  idx = np.flatnonzero(good)
  sub, sub_n = points[idx], normals[idx]
  _, nbr = cKDTree(sub).query(sub, k + 1)
  r, c = np.repeat(np.arange(len(idx)), k + 1), nbr.reshape(-1)
  r, c = r[r != c], c[r != c]
  w = 1.0 - np.abs(np.einsum("ij,ij->i", sub_n[r], sub_n[c])) + 1e-9
  graph = coo_matrix((w, (r, c)), shape=(len(idx),) * 2).tocsr()
  mst = minimum_spanning_tree(graph.maximum(graph.T))
  mst = mst + mst.T
  n_comp, labels = connected_components(mst, directed=False)
  sign = np.ones(len(idx))
  for comp in range(n_comp):
    members = np.flatnonzero(labels == comp)
    cen = sub[members].mean(0)
    seed = members[np.argmax(np.linalg.norm(sub[members] - cen, axis=1))]
    sign[seed] = 1.0 if np.dot(sub_n[seed], sub[seed] - cen) >= 0 else -1.0
    order, pred = breadth_first_order(mst, seed, directed=False, return_predecessors=True)
    for node in order[1:]:
      sign[node] = sign[pred[node]] * (1.0 if sub_n[node] @ sub_n[pred[node]] >= 0 else -1.0)
  out = normals.copy()
  out[idx] = sub_n * sign[:, None]
  return out


def test_propagation_matches_scipy_mst_reference():
  # Two noisy spheres far apart (two components) and some NaN normals: Prim's tree from each
  # component's seed gives the same signs as scipy's Kruskal tree walked breadth first (the
  # weights are distinct, so the minimum spanning tree is unique). The normals are noisy enough
  # that the tree matters: a maximum spanning tree flips about 1,400 of the 3,000.
  rng = np.random.default_rng(3)
  d = rng.normal(size=(3000, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  pts = np.concatenate([d[:2000] * 1.0, d[2000:] * 0.5 + [10.0, 0.0, 0.0]])
  pts += rng.normal(scale=0.01, size=pts.shape)
  nrm = d + rng.normal(scale=0.4, size=d.shape)
  nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
  nrm *= rng.choice([-1.0, 1.0], size=(len(nrm), 1))
  nrm[rng.choice(len(nrm), 30, replace=False)] = np.nan
  got = nm.orient_by_propagation(pts, nrm)
  ref = _scipy_orientation(pts, nrm)
  np.testing.assert_array_equal(np.isnan(got), np.isnan(nrm))
  ok = np.isfinite(nrm[:, 0])
  np.testing.assert_array_equal(got[ok], ref[ok])
  # Both spheres come out outward (the seeds' rule), up to the noisy normals near 90 degrees.
  outward = np.einsum("ij,ij->i", got[ok], d[ok]) > 0
  assert outward.mean() > 0.99, outward.mean()


def test_pca_normals_plane_and_viewpoint():
  rng = np.random.default_rng(0)
  pts = np.c_[rng.uniform(-1, 1, (400, 2)), np.zeros(400)]
  n = nm.pca_normals(pts, 0.3, viewpoint=np.array([0.0, 0.0, -5.0]))
  np.testing.assert_allclose(n, np.tile([0.0, 0.0, -1.0], (400, 1)), atol=1e-9)
  line = np.c_[np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)]
  assert np.isnan(nm.pca_normals(line, 0.2)).all()


def test_mean_curvature_sphere():
  # Icosphere-like UV sphere of radius 2: H ~ 1/2 with outward winding.
  th, ph = np.meshgrid(np.linspace(0.2, np.pi - 0.2, 40), np.linspace(0, 2 * np.pi, 80,
                                                                       endpoint=False),
                       indexing="ij")
  pts = 2.0 * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)],
                       -1).reshape(-1, 3)
  ids = np.arange(40 * 80).reshape(40, 80)
  a, b = ids[:-1], ids[1:]
  c, d = np.roll(b, -1, 1), np.roll(a, -1, 1)
  faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                          np.stack([a, c, d], -1).reshape(-1, 3)])
  h = nm.cotangent_laplacian_curvature(pts, faces)
  interior = ids[5:-5].reshape(-1)
  np.testing.assert_allclose(h[interior], 0.5, rtol=0.05)


def _numpy_mesh_reference(pts, faces):
  """Vertex normals, cotangent curvature and GFrames' per-face A ∇f and vertex shares, written
  with whole-array numpy ops (the formulas the numba kernels implement)."""
  f = faces
  n = len(pts)
  rows = f.T.reshape(-1)
  cross = np.cross(pts[f[:, 1]] - pts[f[:, 0]], pts[f[:, 2]] - pts[f[:, 0]])
  acc = np.stack([np.bincount(rows, weights=np.tile(cross[:, a], 3), minlength=n)
                  for a in range(3)], 1)
  norm = np.linalg.norm(acc, axis=1, keepdims=True)
  with np.errstate(invalid="ignore", divide="ignore"):
    vn = acc / norm
  vn[norm[:, 0] == 0] = np.nan
  area = np.bincount(f.reshape(-1), weights=np.repeat(0.5 * np.linalg.norm(cross, axis=1) / 3, 3),
                     minlength=n)
  lap = np.zeros((n, 3))
  for c in range(3):
    i, j, o = f[:, (c + 1) % 3], f[:, (c + 2) % 3], f[:, c]
    u, v = pts[i] - pts[o], pts[j] - pts[o]
    with np.errstate(invalid="ignore", divide="ignore"):
      cot = (u * v).sum(1) / np.linalg.norm(np.cross(u, v), axis=1)
    cot = np.clip(np.nan_to_num(cot, nan=0.0, posinf=1e3, neginf=-1e3), -1e3, 1e3)
    np.add.at(lap, i, cot[:, None] * (pts[j] - pts[i]))
    np.add.at(lap, j, -cot[:, None] * (pts[j] - pts[i]))
  with np.errstate(invalid="ignore", divide="ignore"):
    lap = lap / (2 * area[:, None])
  h = np.where(area > 0, -0.5 * (np.nan_to_num(lap) * np.nan_to_num(vn)).sum(1), 0.0)
  hf = h[f] - h[f].mean(1, keepdims=True)
  length = np.linalg.norm(cross, axis=1, keepdims=True)
  nrm = np.where(length > 0, cross / np.where(length > 0, length, 1.0), 0.0)
  tri = pts[f]
  g = 0.5 * sum(hf[:, i:i + 1] * np.cross(nrm, tri[:, (i + 2) % 3] - tri[:, (i + 1) % 3])
                for i in range(3))
  share = np.stack([np.bincount(rows, weights=np.tile(g[:, a], 3), minlength=n)
                    for a in range(3)], 1) / 3
  edge = np.zeros(n)
  for a, b in ((0, 1), (1, 2), (2, 0)):
    length = np.linalg.norm(pts[f[:, a]] - pts[f[:, b]], axis=1)
    np.maximum.at(edge, f[:, a], length)
    np.maximum.at(edge, f[:, b], length)
  return vn, h, g, share, edge


def test_mesh_kernels_match_the_numpy_formulas(br_bunny):
  """The numba mesh quantities (vertex normals, cotangent curvature, GFrames' face gradients and
  vertex shares) equal whole-array numpy formulas on a real mesh with a zero-area face, a face
  that repeats a vertex and an isolated vertex added."""
  from lrf_jax.frames import gframes as gf
  pts, faces = br_bunny[0][:3000], np.asarray(br_bunny[1], np.int64)
  faces = faces[(faces < 3000).all(1)]
  pts = np.vstack([pts, pts[:2].mean(0), [[1e3, 1e3, 1e3]]])  # a collinear and an isolated vertex
  n = len(pts)
  faces = np.vstack([faces, [[0, 1, n - 2], [5, 5, 6]]])
  vn, h, g, share, edge = _numpy_mesh_reference(pts, faces)
  np.testing.assert_array_equal(nm.vertex_normals(pts, faces), vn)
  got_h = nm.cotangent_laplacian_curvature(pts, faces)
  np.testing.assert_allclose(got_h, h, rtol=1e-12, atol=1e-12 * np.abs(h).max())
  assert got_h[n - 1] == 0.0 and np.isnan(nm.vertex_normals(pts, faces)[n - 1]).all()
  nm.CLOUD_CACHE.clear()
  g2, gn2, share2, share_n2, ok2, edge2 = gf.vertex_shares(pts, faces)
  scale = np.abs(g).max()
  np.testing.assert_allclose(g2, g, atol=1e-9 * scale)
  np.testing.assert_allclose(gn2, np.linalg.norm(g2, axis=1), rtol=1e-15)
  np.testing.assert_allclose(share2, share, atol=1e-9 * scale)
  np.testing.assert_array_equal(edge2, edge)
  assert ok2.all()


# ----------------------------------------------------------------------------------------------
# TOLDI: the original signed weight vs the paper's unsigned one.
# ----------------------------------------------------------------------------------------------


def test_toldi_signed_vs_unsigned_weight():
  """A bowl with a bump (+x) and a shallower dip (-x): the two weightings pick opposite x.

  z: the bowl's centroid lies above p, so z = -e_z (TOLDI's rule Σ (p - q_i)·z >= 0). Heights
  h = pq·z: bump -a, dip +a/2. Unsigned (paper) weights h² favour the bump: x -> +e_x. Signed
  (original C++) weights sign(h) h²: both terms push towards -e_x.
  """
  g = np.arange(-1.0, 1.0001, 0.05)
  x, y = np.meshgrid(g, g, indexing="ij")
  keep = x ** 2 + y ** 2 <= 1.0
  x, y = x[keep], y[keep]
  z = (0.05 * (x ** 2 + y ** 2) + 0.1 * np.exp(-((x - 0.7) ** 2 + y ** 2) / 0.01)
       - 0.05 * np.exp(-((x + 0.7) ** 2 + y ** 2) / 0.01))
  pts = np.c_[x, y, z]
  kp = np.array([int(np.argmin(x ** 2 + y ** 2))])
  f_signed, v_s = lrf_jax.compute_frames(pts, kp, 1.0, "toldi")
  f_paper, v_p = lrf_jax.compute_frames(pts, kp, 1.0, "toldi", signed=False)
  assert bool(v_s[0]) and bool(v_p[0])
  np.testing.assert_allclose(np.asarray(f_signed)[0, 2], [0, 0, -1], atol=1e-3)
  assert float(f_signed[0, 0, 0]) < -0.99
  assert float(f_paper[0, 0, 0]) > 0.99


# ----------------------------------------------------------------------------------------------
# SHOT: the batched tie rule equals the per-keypoint reference on an all-tied batch.
# ----------------------------------------------------------------------------------------------


def test_shot_tie_rule_batched_equals_reference():
  rng = np.random.default_rng(4)
  n, half = 200, 40
  q = rng.normal(size=(n, half, 3)) * np.array([3.0, 2.0, 1.0])
  offsets = np.concatenate([q, -q], 1).astype(np.float32)  # point-symmetric: every vote ties
  mask = np.ones((n, 2 * half), bool)
  mask[::3, -2:] = False  # keep the count even (symmetric pairs 38, 39 lose both halves)
  mask[::3, half - 2:half] = False
  indices = np.tile(np.arange(2 * half, dtype=np.int32), (n, 1))
  radius = np.full((n,), 20.0, np.float32)
  patches = lrf_jax.Patches(offsets, mask, indices, mask.sum(1).astype(np.int32), radius,
                            np.zeros((n, 3, 3), np.float32), np.zeros((n, 3), np.float32),
                            np.zeros((n,), np.int32))
  fb, vb = jax.jit(shot_mod.shot_frames)(jax.tree.map(jnp.asarray, patches))
  fr, vr = jax.jit(jax.vmap(shot_mod.shot_frame))(
      jnp.asarray(offsets), jnp.asarray(mask), jnp.asarray(indices), jnp.asarray(radius))
  assert np.asarray(vb).all()
  np.testing.assert_array_equal(np.asarray(vb), np.asarray(vr))
  np.testing.assert_allclose(np.asarray(fb), np.asarray(fr), atol=1e-6)
  # Independent check of PCL's rule: after it, >= 3 of the 5 neighbors around the median of the
  # (distance, index)-sorted list lie on the positive side of x and of z.
  fb = np.asarray(fb)
  for i in range(0, n, 7):
    use = np.flatnonzero(mask[i])
    d2 = np.sum(offsets[i, use] ** 2, -1)
    order = use[np.lexsort((indices[i, use], d2))]
    voters = offsets[i, order[len(use) // 2 - 2:len(use) // 2 + 3]]
    for axis in (0, 2):
      assert np.sum(voters @ fb[i, axis] > 0) >= 3, (i, axis)


def _open_scan():
  """A wavy open height field seen from +z (a stand-in for one range scan), its sensor at z = 20."""
  rng = np.random.default_rng(4)
  xy = rng.uniform(-6, 6, (3000, 2))
  z = 0.8 * np.sin(0.7 * xy[:, 0]) * np.cos(0.5 * xy[:, 1])
  return np.c_[xy, z], np.array([0.0, 0.0, 20.0])


def test_viewpoint_orients_scan_normals_equivariantly():
  points, vp = _open_scan()
  n = nm.estimate_normals(points, 1.0, viewpoint=vp)
  ok = np.isfinite(n).all(axis=1)
  assert ok.mean() > 0.99
  assert (n[ok, 2] > 0).all()  # every normal faces the sensor
  rot, shift = random_rotation(2), np.array([3.0, -1.0, 0.5])
  moved = nm.estimate_normals(points @ rot.T + shift, 1.0, viewpoint=rot @ vp + shift)
  cos = np.einsum("ij,ij->i", n[ok] @ rot.T, moved[ok])
  assert cos.min() > 1 - 1e-9
  with pytest.raises(ValueError, match="viewpoint"):
    nm.estimate_normals(points, 1.0, viewpoint=np.array([0.0, np.nan, 1.0]))


def test_compute_frames_viewpoint_feeds_the_normal_methods():
  points, vp = _open_scan()
  kp = np.arange(0, 3000, 97)
  want = nm.estimate_normals(points, nm.NORMAL_RADIUS_RATIO * 4.0, viewpoint=vp)
  f0, v0 = lrf_jax.compute_frames(points, kp, 4.0, "flare", normals=want)
  f1, v1 = lrf_jax.compute_frames(points, kp, 4.0, "flare", viewpoint=vp)
  np.testing.assert_array_equal(np.asarray(v0), np.asarray(v1))
  np.testing.assert_allclose(np.asarray(f0), np.asarray(f1), atol=1e-6)
  assert (np.asarray(f1)[np.asarray(v1), 2, 2] > 0).all()  # z follows the sensor-facing normal


@pytest.mark.data
def test_bunny_scan_normals_need_the_viewpoint(data_root):
  """Propagation orients scan bun000 inwards and bun045 outwards; the sensor viewpoint fixes it."""
  from lrf_jax.datasets import load_bunny_pairs
  from lrf_jax.evaluation import correspondences

  pair = load_bunny_pairs(data_root)[0]
  mi, si = correspondences(pair, 300, 0)
  r = nm.NORMAL_RADIUS_RATIO * 15 * pair.mr

  def agreement(vm, vs):
    a = nm.estimate_normals(pair.model_points, r, viewpoint=vm)[mi] @ pair.rotation.T
    b = nm.estimate_normals(pair.scene_points, r, viewpoint=vs)[si]
    return np.nanmean(np.sign(np.einsum("ij,ij->i", a, b)))

  assert agreement(None, None) < 0  # the failure this fixes: most normals disagree
  assert agreement(pair.model_viewpoint, pair.scene_viewpoint) > 0.95


# ---- bad arguments at the compute_frames boundary ------------------------------------------


@pytest.mark.parametrize("viewpoint", [(np.nan, 0, 0), (0, 0), (0, 0, 0, 1), "abc",
                                       (np.inf, 1, 2)])
def test_bad_viewpoint_is_rejected_by_name(viewpoint):
  pts = np.random.default_rng(0).normal(size=(300, 3))
  with pytest.raises(ValueError, match="viewpoint: expected a finite \\(3,\\) sensor position"):
    lrf_jax.compute_frames(pts, np.arange(5), 0.8, "lrf_net_plus", viewpoint=viewpoint)


@pytest.mark.parametrize("k", [0, -5, 2.5, True, "all"])
def test_bad_k_is_rejected_by_name(k):
  pts = np.random.default_rng(0).normal(size=(300, 3))
  with pytest.raises(ValueError, match="k: expected a positive integer"):
    lrf_jax.compute_frames(pts, np.arange(5), 0.8, "lrf_net", k=k)


def test_unknown_option_lists_the_valid_ones():
  pts = np.random.default_rng(0).normal(size=(300, 3))
  with pytest.raises(ValueError, match=r"unknown option\(s\) \['x_mod'\].*'x_mode'"):
    lrf_jax.compute_frames(pts, np.arange(5), 0.8, "lrf_net_plus", x_mod="softmax")
  with pytest.raises(ValueError, match="its options are none"):
    lrf_jax.compute_frames(pts, np.arange(5), 0.8, "shot", signed=True)


@pytest.mark.parametrize("method", ["toldi", "lrf_net", "shot", "flare"])
def test_frames_are_scale_invariant(method):
  """Frames of s P at radius s r equal those of P at r, s from 1e-6 to 1e8 (float64 input,
  float32 compute): TOLDI's fourth powers used to underflow (s <= 1e-2) and overflow (s >= 1e6)."""
  pair = datasets.make_demo_pair(1, seed=0, noise_mr=0.0, partial=False)
  pts, r = pair.model_points, 15 * pair.mr
  kp = np.random.default_rng(0).choice(len(pts), 150, replace=False)
  ref, v_ref = (np.asarray(a) for a in lrf_jax.compute_frames(pts, kp, r, method))
  assert v_ref.mean() > 0.9
  for s in (1e-6, 1e-2, 1e8):
    f, v = (np.asarray(a) for a in lrf_jax.compute_frames(pts * s, kp, r * s, method))
    assert (v == v_ref).mean() >= 0.99, (s, v.mean(), v_ref.mean())
    both = v & v_ref
    mc = (np.sum(f[both, 0] * ref[both, 0], -1) + np.sum(f[both, 2] * ref[both, 2], -1)) / 2
    assert mc.mean() >= 0.999, (s, mc.mean())
