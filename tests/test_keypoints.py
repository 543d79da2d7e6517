"""ISS keypoints (`lrf_jax.geometry.keypoints`) against a brute-force cKDTree reference, and their
invariances."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import lrf_jax
from lrf_jax import datasets
from lrf_jax.geometry.keypoints import iss_keypoints
from tests.lrf_testing import random_rotation


def reference_iss(pts, salient_radius, non_max_radius, gamma_21=0.975, gamma_32=0.975,
                  min_neighbors=5, max_keypoints=None):
  """The definition, brute force: cKDTree balls, two-pass covariance, eigvalsh, a Python loop."""
  pts = np.asarray(pts, np.float64)
  tree = cKDTree(pts)
  balls = tree.query_ball_point(pts, salient_radius)
  lens = np.array([len(b) for b in balls])
  rows = np.repeat(np.arange(len(pts)), lens)
  cols = np.concatenate([np.asarray(b, np.int64) for b in balls])
  mean = np.stack([np.bincount(rows, pts[cols, a], len(pts)) for a in range(3)], 1) / lens[:, None]
  off = pts[cols] - mean[rows]
  cov = np.empty((len(pts), 3, 3))
  for a in range(3):
    for b in range(3):
      cov[:, a, b] = np.bincount(rows, off[:, a] * off[:, b], len(pts)) / lens
  lam = np.linalg.eigvalsh(cov)
  l3, l2, l1 = lam[:, 0], lam[:, 1], lam[:, 2]
  with np.errstate(divide="ignore", invalid="ignore"):
    candidate = (lens >= min_neighbors) & (l1 > 0) & (l3 > 1e-12 * l1) & (l2 / l1 < gamma_21) \
        & (l3 / l2 < gamma_32)
  saliency = np.where(candidate, l3, 0.0)
  cand = np.flatnonzero(saliency > 0)
  keep = []
  for i, ball in zip(cand, tree.query_ball_point(pts[cand], non_max_radius)):
    if len(ball) >= min_neighbors and saliency[i] >= saliency[ball].max() * (1 - 1e-9):
      keep.append(i)
  keep = np.array(keep, np.int64)
  if max_keypoints is not None:
    keep = np.sort(sorted(keep, key=lambda i: (-saliency[i], i))[:max_keypoints]).astype(np.int64)
  return keep


def bumpy_surface(n=3000, seed=0):
  """A generic cloud: a noisy height field with bumps (no symmetric ties)."""
  rng = np.random.default_rng(seed)
  xy = rng.uniform(0, 1, (n, 2))
  z = 0.1 * np.sin(6 * xy[:, 0]) * np.cos(5 * xy[:, 1]) + 0.004 * rng.normal(size=n)
  return np.column_stack([xy, z])


def _mr(pts):
  return lrf_jax.mesh_resolution(pts)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_brute_force_reference_random(seed):
  pts = bumpy_surface(2500, seed)
  mr = _mr(pts)
  ours = iss_keypoints(pts)
  ref = reference_iss(pts, 6 * mr, 4 * mr)
  assert ours.dtype == np.int64 and np.all(np.diff(ours) > 0)
  assert len(ref) > 20  # the test sees keypoints
  np.testing.assert_array_equal(ours, ref)


def test_matches_reference_with_other_options():
  pts = np.random.default_rng(3).normal(size=(1500, 3)) * [1.0, 0.6, 0.3]  # a 3-D blob
  args = dict(salient_radius=0.5, non_max_radius=0.3, gamma_21=0.9, gamma_32=0.8,
              min_neighbors=8)
  ref = reference_iss(pts, 0.5, 0.3, 0.9, 0.8, 8)
  assert len(ref) > 5
  np.testing.assert_array_equal(iss_keypoints(pts, **args), ref)
  np.testing.assert_array_equal(iss_keypoints(pts, max_keypoints=4, **args),
                                reference_iss(pts, 0.5, 0.3, 0.9, 0.8, 8, max_keypoints=4))
  assert len(iss_keypoints(pts, max_keypoints=0, **args)) == 0
  big = iss_keypoints(pts, max_keypoints=10 ** 6, **args)
  np.testing.assert_array_equal(big, ref)


def test_default_radii_are_multiples_of_mr():
  pts = bumpy_surface(2000, 4)
  mr = _mr(pts)
  np.testing.assert_array_equal(iss_keypoints(pts), iss_keypoints(pts, salient_radius=6 * mr,
                                                                  non_max_radius=4 * mr))
  np.testing.assert_array_equal(iss_keypoints(pts, mr=1.5 * mr),
                                reference_iss(pts, 9 * mr, 6 * mr))


def test_matches_reference_on_bunny_scan(data_root):
  pts = datasets.load_bunny_pairs(data_root, order=("bun000", "bun045"))[0].model_points
  mr = _mr(pts)
  ours = iss_keypoints(pts)
  np.testing.assert_array_equal(ours, reference_iss(pts, 6 * mr, 4 * mr))
  assert len(ours) > 100


def test_matches_reference_on_br_model(br_bunny):
  pts = br_bunny[0][::3]  # a third of the BR bunny's vertices: an uneven real sampling
  mr = _mr(pts)
  np.testing.assert_array_equal(iss_keypoints(pts), reference_iss(pts, 6 * mr, 4 * mr))


def test_rotation_translation_invariance():
  pts = bumpy_surface(3000, 5)
  ours = iss_keypoints(pts)
  assert len(ours) > 20
  rng = np.random.default_rng(6)
  for _ in range(3):
    rot = random_rotation(rng)
    moved = pts @ rot.T + rng.normal(size=3) * 10
    np.testing.assert_array_equal(iss_keypoints(moved), ours)


def test_permutation_gives_the_same_points():
  pts = bumpy_surface(3000, 7)
  ours = iss_keypoints(pts)
  perm = np.random.default_rng(8).permutation(len(pts))
  np.testing.assert_array_equal(np.sort(perm[iss_keypoints(pts[perm])]), ours)


def test_flat_plane_grid_has_no_keypoint():
  g = np.stack(np.meshgrid(np.arange(30.0), np.arange(25.0), indexing="ij"), -1).reshape(-1, 2)
  plane = np.column_stack([g, np.zeros(len(g))])
  assert len(iss_keypoints(plane)) == 0
  rng = np.random.default_rng(9)
  tilted = plane @ random_rotation(rng).T + [3.0, -2.0, 7.0]
  assert len(iss_keypoints(tilted)) == 0
  assert len(iss_keypoints(tilted, salient_radius=4.0, non_max_radius=3.0, gamma_21=1.0,
                           gamma_32=1.0)) == 0


def test_tiny_clouds_have_no_keypoint():
  assert len(iss_keypoints(np.zeros((1, 3)))) == 0
  assert len(iss_keypoints(np.eye(3)[:2])) == 0


@pytest.mark.parametrize("kwargs, match", [
    (dict(salient_radius=0.0), "salient_radius"),
    (dict(salient_radius=-1.0), "salient_radius"),
    (dict(non_max_radius=float("nan")), "non_max_radius"),
    (dict(non_max_radius="big"), "non_max_radius"),
    (dict(gamma_21=0.0), "gamma_21"),
    (dict(gamma_32=1.5), "gamma_32"),
    (dict(gamma_32=float("nan")), "gamma_32"),
    (dict(min_neighbors=0), "min_neighbors"),
    (dict(min_neighbors=2.5), "min_neighbors"),
    (dict(max_keypoints=-1), "max_keypoints"),
    (dict(mr=0.0), "mr"),
    (dict(mr=float("inf")), "mr"),
])
def test_bad_options_raise(kwargs, match):
  with pytest.raises(ValueError, match=match):
    iss_keypoints(bumpy_surface(200), **kwargs)


def test_bad_points_raise():
  pts = bumpy_surface(200)
  pts[17, 1] = np.nan
  with pytest.raises(ValueError, match="points.*non-finite"):
    iss_keypoints(pts)
  with pytest.raises(ValueError, match="points"):
    iss_keypoints(np.zeros((10, 2)))
  with pytest.raises(ValueError, match="the cloud has no spacing"):
    iss_keypoints(np.repeat(bumpy_surface(50), 2, axis=0))  # every point twice: mr = 0


def test_exported():
  assert lrf_jax.iss_keypoints is iss_keypoints
