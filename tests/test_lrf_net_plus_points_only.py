"""lrf_net_plus from the points alone: the z sign oriented over the whole cloud
(`normals.orient_by_vote`), its per-keypoint confidence, and the points_only experiment."""

from pathlib import Path

import jax
import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets, evaluation
from lrf_jax.evaluation import PatchCache
from lrf_jax.frames import METHODS
from lrf_jax.frames.lrf_net_plus import MIN_VOTE_TRUST, prepare_view, sign_confidence
from lrf_jax.search.neighborhoods import build_patches
from lrf_jax.geometry.normals import orient_by_vote, pca_normals
from tests.lrf_testing import (assert_frames_orthonormal, equivariance_deficit,
                               random_rotation)

FIXTURE = Path(__file__).parent / "fixtures" / "lrf_net_plus_oriented_frames.npz"


@pytest.fixture(scope="module")
def scan():
  """A bumpy hemisphere seen from +z (an open scan, 3000 points, unit radius), r = 0.3."""
  z = np.load(FIXTURE)
  return z["points"].astype(np.float64), z["keypoints"], float(z["radius"])


def _sphere(n, center, rng):
  d = rng.normal(size=(n, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  return d + center, d


# Frame entries of the stored golden frames agree with a fresh computation to this much on
# another CPU: float32 rounding follows the machine's code (BLAS kernels, numba's and XLA's
# vector width and FMA use), so the stored values are not reproduced bit for bit. Measured: the
# host kernel's entries 2.7e-6 apart (AMD EPYC, and an Intel Xeon), the jitted kernel's 3.6e-5
# (the network's float32 sums). A frame that changed (an axis flipped or turned) moves entries
# by about 1, so these bounds still catch every real change; validity is compared exactly.
GOLDEN_ATOL = {"host": 1e-5, "jit": 1e-4}


def _close_to_golden(frames, valid, golden_frames, golden_valid, kernel):
  np.testing.assert_array_equal(np.asarray(valid), golden_valid)
  np.testing.assert_allclose(np.asarray(frames), golden_frames, rtol=0,
                             atol=GOLDEN_ATOL[kernel])


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="golden frames of a CPU: an "
                    "accelerator's float32 sums round otherwise (the host-vs-jit tests bound it)")
def test_viewpoint_and_normals_modes_are_bit_identical_to_before():
  # Frames written by the commit before points-only orientation existed: with a viewpoint
  # (host kernel and jitted) and with the caller's normals nothing may change, up to the
  # rounding of another CPU (GOLDEN_ATOL). Frames computed in this process are compared bit
  # for bit: the same inputs in another form (a list viewpoint, float64 normals) or with
  # return_confidence give the same bits.
  z = np.load(FIXTURE)
  pts, kp, r, vp = z["points"], z["keypoints"], float(z["radius"]), z["viewpoint"]
  f, v = lrf_jax.compute_frames(pts, kp, r, viewpoint=vp)
  _close_to_golden(f, v, z["f_view"], z["v_view"], "host")
  g, w, _ = lrf_jax.compute_frames(pts, kp, r, viewpoint=list(vp), return_confidence=True)
  np.testing.assert_array_equal(np.asarray(g), np.asarray(f))
  np.testing.assert_array_equal(np.asarray(w), np.asarray(v))
  f, v = lrf_jax.compute_frames(pts, kp, r, viewpoint=vp, kernel="jit")
  _close_to_golden(f, v, z["f_view_jit"], z["v_view_jit"], "jit")
  g, w, _ = lrf_jax.compute_frames(pts, kp, r, viewpoint=list(vp), kernel="jit",
                                   return_confidence=True)
  np.testing.assert_array_equal(np.asarray(g), np.asarray(f))
  np.testing.assert_array_equal(np.asarray(w), np.asarray(v))
  nrm = (pts / np.linalg.norm(pts, axis=1, keepdims=True)).astype(np.float32)
  f, v = lrf_jax.compute_frames(pts, kp, r, normals=nrm)
  _close_to_golden(f, v, z["f_normals"], z["v_normals"], "host")
  g, w = lrf_jax.compute_frames(pts, kp, r, normals=nrm.astype(np.float64))
  np.testing.assert_array_equal(np.asarray(g), np.asarray(f))
  np.testing.assert_array_equal(np.asarray(w), np.asarray(v))


def test_vote_orients_every_component_outwards():
  # Two spheres far apart (two components), PCA normals of arbitrary sign: each component's
  # vote turns its normals out of the sphere, unanimously.
  rng = np.random.default_rng(0)
  a, da = _sphere(3000, np.zeros(3), rng)
  b, db = _sphere(2000, np.array([10.0, 0, 0]), rng)
  pts = np.r_[a, b]
  nrm = pca_normals(pts, 0.2)
  nrm *= np.where(rng.random(len(pts)) < 0.5, -1.0, 1.0)[:, None]
  oriented, trust = orient_by_vote(pts, nrm, 0.5)
  assert (np.einsum("nc,nc->n", oriented, np.r_[da, db]) > 0).all()
  assert trust.min() > 0.9 and trust.max() <= 1.0


def test_points_only_frames_are_equivariant_with_the_same_sign(scan):
  pts, kp, r = scan
  f, v, c = map(np.asarray, lrf_jax.compute_frames(pts, kp, r, return_confidence=True))
  assert v.mean() > 0.9
  assert_frames_orthonormal(f, v)
  for seed in (1, 2):
    rot = random_rotation(seed)
    t = np.random.default_rng(seed).normal(size=3) * 5
    g, w, d = map(np.asarray, lrf_jax.compute_frames(pts @ rot.T + t, kp, r,
                                                     return_confidence=True))
    np.testing.assert_array_equal(v, w)
    assert equivariance_deficit(f, g, rot, v, w).max() < 1e-3
    z_back = np.einsum("nc,cd->nd", g[:, 2], rot)  # the moved cloud's z mapped back
    assert (np.einsum("nc,nc->n", f[:, 2], z_back)[v] > 0.99).all()  # the same sign everywhere
    np.testing.assert_allclose(c, d, atol=1e-4)


def test_points_only_z_points_out_of_a_convex_scan(scan):
  # The cloud's vote orients every z out of the cap, with a confidence above the vote threshold.
  pts, kp, r = scan
  f, v, c = map(np.asarray, lrf_jax.compute_frames(pts, kp, r, return_confidence=True))
  radial = pts[kp] / np.linalg.norm(pts[kp], axis=1, keepdims=True)
  assert (np.einsum("nc,nc->n", f[:, 2], radial)[v] > 0).all()
  assert np.median(c[v]) > MIN_VOTE_TRUST and (c >= 0).all() and (c <= 1).all()
  assert (c[~v] == 0).all()


def test_flat_patch_has_zero_confidence_and_a_valid_or_flagged_frame():
  # A plane has no side: the vote margin is 0, z falls back to the ball sign, and the
  # confidence is 0; frames stay orthonormal (identity where flagged).
  g = np.linspace(-1, 1, 61)
  pts = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
  pts = np.c_[pts, np.zeros(len(pts))]
  kp = np.arange(0, len(pts), 37)
  f, v, c = map(np.asarray, lrf_jax.compute_frames(pts, kp, 0.3, return_confidence=True))
  assert_frames_orthonormal(f, v)
  assert c.max() < 0.01
  assert np.allclose(np.abs(f[v][:, 2, 2]), 1.0, atol=1e-5)
  extra = prepare_view(pts, kp, build_patches(pts, kp, 0.3, 512), radius=0.3)
  assert not extra.view.any() and not extra.trust.any()


def support_view_reference(normals, per_point, patches, radius):
  """`lrf_net_plus.support_view` in numpy, as it was written before its compiled pass: the
  definition its kernel reproduces bit for bit."""
  idx = np.asarray(patches.indices)
  off = np.asarray(patches.offsets, np.float64)
  near = (idx >= 0) & (np.einsum("nkc,nkc->nk", off, off) <= (float(radius) / 3.0) ** 2)
  near &= np.all(np.isfinite(normals[np.maximum(idx, 0)]), axis=-1)
  view = np.where(near[..., None], normals[np.maximum(idx, 0)], 0.0).sum(1)
  trust = None
  if per_point is not None:
    trust = (np.where(near, per_point[np.maximum(idx, 0)], 0.0).sum(1)
             / np.maximum(near.sum(1), 1))
    view = np.where((trust >= MIN_VOTE_TRUST)[:, None], view, 0.0)
  return view, trust


@pytest.mark.parametrize("k", [512, 100, None])
def test_support_view_is_the_numpy_sums_bit_for_bit(scan, k):
  # Trust values of every magnitude (the order of the sums shows), NaN normals, padding, and
  # patch sizes below and above numpy's pairwise block (128) and uneven ones (k=None).
  from lrf_jax.frames.lrf_net_plus import support_view
  pts, kp, r = scan
  patches = build_patches(pts, kp, r, k)
  rng = np.random.default_rng(k or 0)
  nrm = rng.normal(size=(len(pts), 3))
  nrm[rng.random(len(pts)) < 0.05] = np.nan
  per_point = rng.random(len(pts)) * 10.0 ** rng.integers(-6, 3, len(pts))
  for trust in (per_point, np.full(len(pts), 0.3), None):
    view, got = support_view(nrm, trust, patches, r)
    want_view, want = support_view_reference(nrm, trust, patches, r)
    np.testing.assert_array_equal(view, want_view)
    assert (got is None and want is None) or np.array_equal(got, want)
    if trust is per_point:  # both sides of MIN_VOTE_TRUST: some views zeroed, some kept
      assert 0 < (want >= MIN_VOTE_TRUST).mean() < 1


def test_propagation_graph_is_the_knn_lists_each_edge_once_in_first_mention_order():
  # The graph Prim walks: every node's neighbours in the order the k-NN lists first mention
  # them (the list of i at i's turn, i in j's list at j's turn), each once. A repeated entry
  # would come later in both nodes' lists, where neither the walk nor Prim's strict key test
  # (an equal weight never replaces a key) reads it: the same trees, signs and components.
  from lrf_jax.geometry import orientation
  from lrf_jax.geometry.cloud_cache import cloud_knn
  rng = np.random.default_rng(5)
  pts = np.r_[_sphere(600, np.zeros(3), rng)[0], _sphere(300, np.zeros(3), rng)[0][:50]]
  nrm = pca_normals(pts, 0.3)
  nbr = cloud_knn(pts, 9)[1]
  starts, adj, wts = orientation._knn_graph(nrm, nbr)
  want = [[] for _ in pts]
  for i in range(len(pts)):
    for j in nbr[i]:
      if j != i:
        want[i].append(j)
        want[j].append(i)
  for i in range(len(pts)):
    first = list(dict.fromkeys(want[i]))
    np.testing.assert_array_equal(adj[starts[i]:starts[i + 1]], first)
    a, b = nrm[i], nrm[first]
    dot = a[0] * b[:, 0] + a[1] * b[:, 1] + a[2] * b[:, 2]
    np.testing.assert_array_equal(wts[starts[i]:starts[i + 1]], 1.0 - np.abs(dot))


def test_propagation_walks_the_knn_components_and_reads_the_cached_knn():
  # The component labels the vote uses come from the propagation's own walk: those of
  # `knn_components`, also with NaN normals (the finite ones' graph) and several components.
  from lrf_jax.geometry import orientation
  from lrf_jax.geometry.cloud_cache import cloud_knn
  from lrf_jax.search import engine
  rng = np.random.default_rng(3)
  pts = np.concatenate([_sphere(800, np.array([3.0 * i, 0, 0]), rng)[0] for i in range(3)])
  pts = pts[rng.permutation(len(pts))]
  nrm = pca_normals(pts, 0.3)
  for normals in (nrm, np.where(rng.random((len(pts), 1)) < 0.1, np.nan, nrm)):
    out, good, labels = orientation._propagated(pts, normals, 8)
    np.testing.assert_array_equal(labels, orientation.knn_components(pts[good], 8))
    assert labels.max() == 2
    np.testing.assert_array_equal(out, orientation.orient_by_propagation(pts, normals))
  d, i = engine.knn(engine.knn_grid(pts, 9), pts, 9)
  last, nbr = cloud_knn(pts, 9)
  np.testing.assert_array_equal(last, d[:, -1])
  np.testing.assert_array_equal(nbr, i)
  nbr[:] = 0  # the caller's copy
  np.testing.assert_array_equal(cloud_knn(pts, 9)[1], i)


def _patches_and_extra(scan, n=24):
  pts, kp, r = scan
  kp = kp[:n]
  patches = build_patches(pts, kp, r, 512)
  return patches, prepare_view(pts, kp, patches, radius=r)


def _plus(patches, extra):
  return jax.jit(lambda p, e: METHODS["lrf_net_plus"].fn(
      p, e, params=lrf_jax.default_params("lrf_net_plus")))(patches, extra)


def test_confidence_ignores_padding_and_nan_gives_zero(scan):
  patches, extra = _patches_and_extra(scan)
  f, v = _plus(patches, extra)
  c = np.asarray(sign_confidence(f, v, patches, extra))
  assert (c[np.asarray(v)] > 0).all()
  pad = 64  # more slots, filled with garbage that the mask hides
  n, k = patches.mask.shape
  junk = np.full((n, pad, 3), 1e3, np.float32)
  junk[:, ::2] = np.nan
  padded = patches._replace(
      offsets=np.concatenate([patches.offsets, junk], 1),
      mask=np.concatenate([patches.mask, np.zeros((n, pad), bool)], 1),
      indices=np.concatenate([patches.indices, -np.ones((n, pad), np.int32)], 1))
  extra_p = extra._replace(area=np.concatenate([extra.area, np.zeros((n, pad), np.float32)], 1))
  fp, vp = _plus(padded, extra_p)
  np.testing.assert_array_equal(np.asarray(vp), np.asarray(v))
  np.testing.assert_allclose(np.asarray(fp), np.asarray(f), atol=1e-6)
  np.testing.assert_allclose(np.asarray(sign_confidence(fp, vp, padded, extra_p)), c,
                             atol=1e-6)
  broken = patches.offsets.copy()
  broken[0, 3] = np.nan  # a real neighbor: the frame is flagged, its confidence is 0
  bad = patches._replace(offsets=broken)
  fb, vb = _plus(bad, extra)
  cb = np.asarray(sign_confidence(fb, vb, bad, extra))
  assert not bool(vb[0]) and cb[0] == 0.0 and np.isfinite(cb).all()
  np.testing.assert_allclose(cb[1:], c[1:], atol=1e-6)


def test_confidence_of_a_viewpoint_is_the_cosine_and_other_methods_have_none(scan):
  pts, kp, r = scan
  vp = np.array([0.0, 0.0, 3.0])
  f, v, c = map(np.asarray, lrf_jax.compute_frames(pts, kp, r, viewpoint=vp,
                                                   return_confidence=True))
  view = vp - pts[kp]
  cos = np.abs(np.einsum("nc,nc->n", f[:, 2], view)) / np.linalg.norm(view, axis=1)
  np.testing.assert_allclose(c[v], cos[v], atol=1e-5)
  f0, v0 = lrf_jax.compute_frames(pts, kp, r, viewpoint=vp)
  np.testing.assert_array_equal(np.asarray(f0), f)  # asking for it changes no frame
  with pytest.raises(ValueError, match="return_confidence"):
    lrf_jax.compute_frames(pts, kp, r, "toldi", return_confidence=True)
  f, v, c = lrf_jax.compute_frames(pts, kp[:0], r, return_confidence=True)
  assert f.shape == (0, 3, 3) and c.shape == (0,)


def test_random_motion_keeps_the_ground_truth():
  pair = datasets.make_demo_pair(0, seed=0, partial=True)
  moved = datasets.with_random_motion(pair, 3)
  ts = np.array(moved.meta["motion"]["scene"])
  np.testing.assert_allclose(moved.model_in_scene(),
                             datasets.transform_points(ts, pair.model_in_scene()), atol=1e-9)
  vp = datasets.transform_points(ts, pair.scene_viewpoint[None])[0]
  np.testing.assert_allclose(moved.scene_viewpoint, vp)
  bare = datasets.points_only(moved)
  assert bare.model_faces is None and bare.scene_viewpoint is None
  r = datasets.random_rigid_motion(5)[:3, :3]
  np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
  assert np.linalg.det(r) == pytest.approx(1.0)


def test_points_only_experiment_records_table_and_figure(tmp_path):
  opts = evaluation.EvalOptions(n_keypoints=60, max_pairs=1)
  recs = list(evaluation.run_experiment("points_only", ["demo"], [], opts, PatchCache()))
  labels = [r["method"] for r in recs]
  assert labels[:3] == ["lrf_net_plus (viewpoint)", "lrf_net_plus (points only)",
                        "lrf_net_plus (points only, ball sign)"]
  assert all(r["experiment"] == "points_only" and 0 <= r["z_flip"] <= 1 for r in recs)
  evaluation.write_results(recs, tmp_path)
  text = (tmp_path / "report.md").read_text()
  assert "## points_only" in text and "%)" in text
  assert (tmp_path / "points_only.png").stat().st_size > 5000


def test_evaluate_points_only_defaults(tmp_path):
  # evaluate.py --experiments points_only: at most POINTS_ONLY_PAIRS pairs a dataset without
  # --max-pairs, the hand-crafted methods --methods names (the defaults when it names none:
  # `test_points_only_experiment_records_table_and_figure`), no LRF-Net weight figures.
  import json

  import evaluate
  from lrf_jax.evaluation.experiments import POINTS_ONLY_HANDCRAFTED, POINTS_ONLY_PAIRS
  assert evaluate.main(["--experiments", "points_only", "--datasets", "demo", "--keypoints",
                        "30", "--methods", "lrf_net_plus", "toldi", "--out",
                        str(tmp_path)]) == 0
  recs = json.loads((tmp_path / "results.json").read_text())["records"]
  assert len({r["pair"] for r in recs}) == POINTS_ONLY_PAIRS
  assert {r["method"] for r in recs} == {"lrf_net_plus (viewpoint)", "lrf_net_plus (points only)",
                                         "lrf_net_plus (points only, ball sign)",
                                         "toldi (points only)"}
  assert (tmp_path / "points_only.png").exists() and not (tmp_path / "weights.png").exists()
  assert "shot" in POINTS_ONLY_HANDCRAFTED


def test_register_keeps_the_patch_sign_on_a_bare_cloud(scan, monkeypatch):
  # register() passes oriented_sign=False for a cloud without viewpoint or mesh: the frames are
  # those of the patch sign, and prepare_view orients no normals for them.
  from lrf_jax.geometry import normals as normals_module
  pts, kp, r = scan
  calls = []
  real = normals_module.voted_normals
  monkeypatch.setattr(normals_module, "voted_normals",
                      lambda *a, **k: calls.append(1) or real(*a, **k))
  f0, v0 = map(np.asarray, lrf_jax.compute_frames(pts, kp, r, oriented_sign=False))
  assert not calls
  extra = prepare_view(pts, kp, build_patches(pts, kp, r, 512), radius=r, oriented=False)
  assert not calls and not np.asarray(extra.view).any()
  f1, v1 = map(np.asarray, lrf_jax.compute_frames(pts, kp, r))
  assert calls  # the default does orient them
