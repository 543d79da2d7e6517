"""LRF-based descriptors (snapshots, SHOT, RoPS, TOLDI), matching and the RPC protocol."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets
from lrf_jax.descriptors import (DESCRIPTORS, compute_descriptors, describe_patches,
                                 descriptors_from_patches, match_descriptors, pad_patches,
                                 top_correspondences)
from lrf_jax.descriptors import shot as shot_mod
from lrf_jax.descriptors.rops import rotation_matrices
from lrf_jax.evaluation.description import (DescriptionRun, evaluate_description_pair,
                                            recall_at, rpc_counts, rpc_curve)
from lrf_jax.evaluation.repeatability import MethodRun
from lrf_jax.search.neighborhoods import Patches, build_patches
from tests.lrf_testing import random_rotation

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "pcl_desc_demo.npz"
NAMES = ("snapshots", "shot", "rops", "toldi")


@pytest.fixture(scope="module")
def demo_crop():
  """A 36 mr crop of the procedural demo blob: (points, normals, keypoints, radius)."""
  pts, faces = datasets.make_demo_mesh("blob", 0)
  mr, _ = datasets.mesh_resolution(pts, faces)
  keep = np.linalg.norm(pts - pts[0], axis=1) <= 36 * mr
  crop = pts[keep]
  inner = np.flatnonzero(np.linalg.norm(crop - pts[0], axis=1) <= 20 * mr)
  kp = np.sort(np.random.default_rng(0).choice(inner, 48, replace=False))
  return crop, kp, 15 * mr


def test_registry_dimensions(demo_crop):
  pts, kp, r = demo_crop
  frames, valid = lrf_jax.compute_frames(pts, kp, r, "toldi")
  assert np.all(np.asarray(valid))
  expected = {"snapshots": 225, "shot": 352, "rops": 135, "toldi": 1200}
  for name in NAMES:
    d, ok = compute_descriptors(pts, kp, r, frames, valid, name)
    d = np.asarray(d)
    assert d.shape == (len(kp), expected[name]) == (len(kp), DESCRIPTORS[name].dim)
    assert np.all(np.asarray(ok)) and np.isfinite(d).all()
    if name == "shot":
      np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-5)
    elif name == "rops":
      np.testing.assert_allclose(np.abs(d).sum(axis=1), 1.0, rtol=1e-5)
    elif name == "toldi":  # depths in [0, 1] or the empty marker 100
      assert np.all(((d >= 0) & (d <= 1)) | (d == 100.0))
      assert np.any(d == 100.0) and np.any(d < 1)
    else:
      assert np.all((d >= 0) & (d <= 1)) and d.max() > 0.5


@pytest.mark.parametrize("name", NAMES)
def test_rotation_invariant_with_equivariant_lrf(demo_crop, name):
  """Descriptors on an equivariant LRF (TOLDI) do not change when the cloud is moved; with a fixed
  (non-equivariant) frame they do: the test can fail."""
  pts, kp, r = demo_crop
  rot, t = random_rotation(11), np.array([0.4, -2.0, 1.5])
  moved = pts @ rot.T + t
  f1, v1 = lrf_jax.compute_frames(pts, kp, r, "toldi")
  f2, v2 = lrf_jax.compute_frames(moved, kp, r, "toldi")
  d1, _ = compute_descriptors(pts, kp, r, f1, v1, name)
  d2, _ = compute_descriptors(moved, kp, r, f2, v2, name)
  d1, d2 = np.asarray(d1, np.float64), np.asarray(d2, np.float64)
  rel = np.linalg.norm(d1 - d2, axis=1) / np.linalg.norm(d1, axis=1)
  # Float rounding of the frames (~1e-6) may move a point across a bin border (RoPS: a 1/n count
  # in one of 27 distribution matrices, ~1e-3 of the vector); everything else agrees to ~1e-6.
  assert np.median(rel) < 1e-5 and rel.max() < 1e-2, (np.median(rel), rel.max())
  m = match_descriptors(d2, d1)
  np.testing.assert_array_equal(m.nearest, np.arange(len(kp)))
  # Negative control: identity frames are not equivariant, the descriptors change.
  eye = np.broadcast_to(np.eye(3), (len(kp), 3, 3))
  e1, _ = compute_descriptors(pts, kp, r, eye, None, name)
  e2, _ = compute_descriptors(moved, kp, r, eye, None, name)
  e1, e2 = np.asarray(e1), np.asarray(e2)
  assert np.median(np.linalg.norm(e1 - e2, axis=1) / np.linalg.norm(e1, axis=1)) > 0.1


def test_padding_and_slot_order_do_not_change_descriptors(demo_crop):
  pts, kp, r = demo_crop
  frames, valid = lrf_jax.compute_frames(pts, kp[:16], r, "lrf_net")
  patches = build_patches(pts, kp[:16], r, None)
  padded = pad_patches(patches, patches.k + 40)
  perm = np.random.default_rng(1).permutation(padded.k)
  shuffled = padded._replace(offsets=padded.offsets[:, perm], mask=padded.mask[:, perm],
                             indices=padded.indices[:, perm])
  for name in NAMES:
    a, _ = describe_patches(patches, frames, valid, name, points=pts, keypoints=kp[:16], radius=r)
    b, _ = describe_patches(shuffled, frames, valid, name, points=pts, keypoints=kp[:16],
                            radius=r)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-6, err_msg=name)


def _one_point_patch(local: np.ndarray, cos: float, radius: float = 1.0):
  """A keypoint plus 4 copies of one neighbor at `local` (identity frame), its normal making
  `cos` with z: (patches, frames, valid, normals)."""
  offsets = np.zeros((1, 8, 3), np.float32)
  offsets[0, 1:5] = local
  mask = np.zeros((1, 8), bool)
  mask[0, :5] = True
  normal = np.array([math.sqrt(1 - cos * cos), 0.0, cos], np.float32)
  normals = np.zeros((1, 8, 3), np.float32)
  normals[0, :5] = normal
  p = Patches(offsets=offsets, mask=mask, indices=np.where(mask, 0, -1).astype(np.int32),
              count=np.array([5], np.int32), radius=np.array([radius], np.float32),
              z_cov=np.zeros((1, 3, 3), np.float32), z_mean=np.zeros((1, 3), np.float32),
              z_count=np.array([5], np.int32))
  return p, np.eye(3, dtype=np.float32)[None], np.array([True]), normals


@pytest.mark.parametrize("sector", range(8))
@pytest.mark.parametrize("shell,upper", [(0, 1), (1, 0), (1, 1), (0, 0)])
def test_shot_bin_layout(sector, shell, upper):
  """A neighbor at the centre of a volume's azimuth, at an elevation and distance where no
  interpolation spills, votes into exactly bin (4 sector + 2 shell + upper) * 11 + cosine bin."""
  az = -7 * math.pi / 8 + sector * math.pi / 4
  inc = math.pi / 4 if upper else 3 * math.pi / 4
  d = 0.75 if shell else 0.25
  local = d * np.array([math.sin(inc) * math.cos(az), math.sin(inc) * math.sin(az),
                        math.cos(inc)])
  p, f, v, n = _one_point_patch(local, cos=0.0)  # b = 5: cosine bin 5, no spill
  desc, ok = shot_mod.shot_descriptors(p, f, v, n, align_normals=False)
  desc = np.asarray(desc)[0]
  assert bool(ok[0])
  expected = (4 * sector + 2 * shell + upper) * shot_mod.STRIDE + 5
  assert int(np.argmax(desc)) == expected
  assert desc[expected] > 0.9999


def test_shot_cosine_interpolation_wraps_like_pcl():
  """b = (1 + cos) * 5 = 9.2 votes 0.8 to cosine bin 9 and 0.2 to bin (9 + 1) mod 10 = 0 (PCL's
  circular wrap), never to the 11th slot; the three spatial directions add 1 each to the own bin."""
  inc, az, d = math.pi / 4, -7 * math.pi / 8, 0.25
  local = d * np.array([[math.sin(inc) * math.cos(az), math.sin(inc) * math.sin(az),
                         math.cos(inc)]], np.float32)
  h = np.asarray(shot_mod._shot_one(local, np.array([d], np.float32),
                                    np.array([0.84], np.float32), np.array([True]),
                                    np.float32(1.0)))
  base = 1 * shot_mod.STRIDE  # sector 0, inner shell, upper half
  np.testing.assert_allclose(h[base + 9], 3.8, rtol=1e-4)
  np.testing.assert_allclose(h[base + 0], 0.2, rtol=1e-3)
  np.testing.assert_allclose(h.sum(), 4.0, rtol=1e-5)
  assert h[base + 10] == 0


def test_invalid_frames_and_small_balls_give_invalid_zero_descriptors(demo_crop):
  pts, kp, r = demo_crop
  frames, valid = lrf_jax.compute_frames(pts, kp[:8], r, "toldi")
  valid = np.asarray(valid).copy()
  valid[[1, 5]] = False
  frames = np.asarray(frames).copy()
  frames[5] = np.nan  # non-finite frames must not leak NaN
  for name in NAMES:
    d, ok = compute_descriptors(pts, kp[:8], r, frames, valid, name)
    d, ok = np.asarray(d), np.asarray(ok)
    assert not ok[1] and not ok[5] and ok[[0, 2, 3, 4, 6, 7]].all()
    assert np.isfinite(d).all() and not d[[1, 5]].any()
  tiny = compute_descriptors(pts, kp[:2], 1e-9, frames[:2], None, "shot")
  assert not np.asarray(tiny[1]).any()


def test_pcl_agreement_shot_and_rops():
  """SHOT352 and RoPS on external (LRF-Net) frames agree with PCL 1.13's (stored fixture made by
  tools/pcl_descriptors/run_pcl_desc.py --fixtures; PCL is not needed here)."""
  if not FIXTURE.exists():
    pytest.skip(f"{FIXTURE} missing: run tools/pcl_descriptors/run_pcl_desc.py --fixtures")
  fx = dict(np.load(FIXTURE))
  pts = fx["points"].astype(np.float64)
  kp, frames, r = fx["keypoints"].astype(np.int64), fx["frames"], float(fx["radius"])
  shot, ok_s = compute_descriptors(pts, kp, r, frames, None, "shot", normals=fx["normals"],
                                   align_normals=False)
  rops, ok_r = compute_descriptors(pts, kp, r, frames, None, "rops")
  assert np.all(np.asarray(ok_s)) and np.all(np.asarray(ok_r))
  rel = {name: np.linalg.norm(np.asarray(ours) - fx[name], axis=1) / np.linalg.norm(fx[name], axis=1)
         for name, ours in (("shot", shot), ("rops", rops))}
  # SHOT interpolates (continuous in the coordinates): float32 rounding only (measured 4e-7).
  assert rel["shot"].max() < 1e-5, rel["shot"].max()
  # RoPS bins by truncation: a coordinate within rounding of a bin border may land in the other
  # bin on another CPU (measured on 1000 BR bunny keypoints: 3 with rel 2e-4..4.5e-4, the rest
  # < 1e-6; on this fixture all < 6e-7).
  assert np.mean(rel["rops"] < 1e-5) >= 0.95 and rel["rops"].max() < 1e-2, rel["rops"].max()


def test_bad_inputs_name_the_problem(demo_crop):
  pts, kp, r = demo_crop
  with pytest.raises(ValueError, match="descriptor: unknown"):
    compute_descriptors(pts, kp, r, np.eye(3)[None].repeat(len(kp), 0), None, "fpfh")
  with pytest.raises(ValueError, match=r"frames: expected .*\(48, 3, 3\)"):
    compute_descriptors(pts, kp, r, np.eye(3)[None].repeat(3, 0), None, "toldi")
  with pytest.raises(ValueError, match="valid: expected shape"):
    compute_descriptors(pts, kp, r, np.eye(3)[None].repeat(len(kp), 0), np.ones(3, bool),
                        "toldi")
  with pytest.raises(ValueError, match="radius"):
    compute_descriptors(pts, kp, -1.0, np.eye(3)[None].repeat(len(kp), 0), None, "toldi")
  with pytest.raises(ValueError, match="needs `extra`"):
    descriptors_from_patches(build_patches(pts, kp[:2], r, 32), np.eye(3)[None].repeat(2, 0),
                             np.ones(2, bool), "shot")
  with pytest.raises(ValueError, match="same D"):
    match_descriptors(np.zeros((3, 4)), np.zeros((3, 5)))


def test_rops_rotations_match_pcl_angles():
  rots = rotation_matrices()
  assert rots.shape == (9, 3, 3)
  angles = np.degrees(np.arccos((np.trace(rots, axis1=1, axis2=2) - 1) / 2))
  np.testing.assert_allclose(angles, np.tile([22.5, 45.0, 67.5], 3), atol=1e-4)
  np.testing.assert_allclose(rots[:3, :, 0], np.tile([1.0, 0, 0], (3, 1)), atol=1e-6)  # about x


def test_matching_ratio_and_top_correspondences():
  ref = np.array([[0.0, 0], [1, 0], [0, 3]], np.float32)
  query = np.array([[0.1, 0], [0.85, 0], [0, 2.9], [5, 5]], np.float32)
  m = match_descriptors(query, ref, np.array([True, True, True, False]),
                        np.array([True, True, True]))
  np.testing.assert_array_equal(m.nearest, [0, 1, 2, -1])
  np.testing.assert_allclose(m.ratio[:3], [0.1 / 0.9, 0.15 / 0.85, 0.1 / 2.9], rtol=1e-4)
  np.testing.assert_allclose(m.distance[:3], [0.1, 0.15, 0.1], rtol=1e-4)
  assert np.isinf(m.ratio[3])
  qi, ri = top_correspondences(m, 2)
  np.testing.assert_array_equal(qi, [2, 0])  # smallest ratio first; invalid queries never
  np.testing.assert_array_equal(ri, [2, 0])


def test_rpc_counts_and_curve():
  ratio = np.array([0.2, 0.5, 0.6, 0.9, np.inf])
  correct = np.array([True, False, True, True, False])
  n_match, n_true = rpc_counts(ratio, correct, np.array([0.1, 0.5, 1.0]))
  np.testing.assert_array_equal(n_match, [0, 2, 4])
  np.testing.assert_array_equal(n_true, [0, 1, 3])
  recall, omp = rpc_curve(n_match, n_true, n_corr=5)
  np.testing.assert_allclose(recall, [0, 0.2, 0.6])
  assert np.isnan(omp[0])
  np.testing.assert_allclose(omp[1:], [0.5, 0.25])
  assert recall_at(recall, omp, 0.3) == 0.6 and recall_at(recall, omp, 0.1) == 0.0


def test_description_protocol_on_a_rigidly_moved_cloud():
  """Scene = model under a rigid motion: with an equivariant LRF every descriptor finds its own
  keypoint (recall 1 at tau = 1); the records carry the documented fields."""
  pts, faces = datasets.make_demo_mesh("blob", 0)
  mr, _ = datasets.mesh_resolution(pts, faces)
  tr = np.eye(4)
  tr[:3, :3], tr[:3, 3] = random_rotation(5), [1.0, 2.0, -0.5]
  pair = datasets.Pair("moved", "demo", pts, datasets.transform_points(tr, pts), faces, faces,
                       tr, mr, "mean_edge_length", "index")
  runs = [DescriptionRun("toldi", MethodRun("toldi", "toldi")),
          DescriptionRun("shot", MethodRun("lrf_net", "lrf_net"))]
  recs = evaluate_description_pair(pair, runs, n_keypoints=60, seed=3)
  assert [r["method"] for r in recs] == ["toldi+toldi", "shot+lrf_net"]
  json.dumps(recs)  # records go to results.json as they are
  for r in recs:
    assert r["experiment"] == "description" and r["n_corr"] == 60
    assert r["recall_max"] == 1.0 and r["recall_at_0.1"] == 1.0
    assert len(r["n_match"]) == len(r["thresholds"]) == 101


def test_toldi_host_fast_path_equals_the_jitted_descriptor(br_bunny):
  """compute_descriptors(kernel="host"): the same images as the jitted descriptor (float64
  coordinates: a point on a pixel border may land in its neighbor)."""
  points, faces, mr, _ = br_bunny
  r = 15.0 * mr
  kp = np.random.default_rng(5).choice(len(points), 300, replace=False)
  frames, valid = lrf_jax.compute_frames(points, kp, r, "toldi")
  valid = np.asarray(valid).copy()
  valid[:5] = False  # invalid frames give invalid, zero descriptors on both paths
  out = [compute_descriptors(points, kp, r, frames, valid, "toldi", kernel=kernel)
         for kernel in ("host", "jit")]
  (dh, vh), (dj, vj) = [(np.asarray(d), np.asarray(v)) for d, v in out]
  np.testing.assert_array_equal(vh, vj)
  assert not vh[:5].any() and not dh[:5].any()
  same = np.isclose(dh, dj, atol=1e-5)
  assert same.mean() > 0.999, same.mean()
  assert same[vh].all(axis=1).mean() > 0.9
  with pytest.raises(ValueError, match="no host fast path"):
    compute_descriptors(points, kp, r, frames, valid, "shot", kernel="host")
