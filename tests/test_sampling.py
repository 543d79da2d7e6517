"""voxel_downsample: one centroid per occupied voxel, against a brute-force numpy reference."""

import numpy as np
import pytest

from lrf_jax.geometry.sampling import voxel_downsample


def _reference(points: np.ndarray, size: float) -> np.ndarray:
  """Brute force: for every voxel key (in sorted order) the mean of the points whose key it is."""
  lo = points.min(0)
  keys = [tuple(int(v) for v in np.floor((p - lo) / size)) for p in points]
  out = []
  for key in sorted(set(keys)):
    members = [p for p, k in zip(points, keys) if k == key]
    out.append(np.mean(members, axis=0))
  return np.array(out)


@pytest.mark.parametrize("size", [0.05, 0.3, 2.0])
def test_matches_brute_force_centroids(size):
  pts = np.random.default_rng(1).normal(size=(400, 3)) * [1.0, 0.5, 0.2] + 7.0
  got = voxel_downsample(pts, size)
  want = _reference(pts, size)
  assert got.shape == want.shape and got.dtype == np.float64
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
  assert 1 <= len(got) <= len(pts)


def test_deterministic_and_independent_of_row_order():
  pts = np.random.default_rng(2).uniform(size=(1000, 3))
  a = voxel_downsample(pts, 0.1)
  b = voxel_downsample(pts[np.random.default_rng(3).permutation(len(pts))], 0.1)
  np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)
  np.testing.assert_array_equal(a, voxel_downsample(pts, 0.1))


def test_single_point_voxels_return_the_point_exactly_and_huge_voxels_the_mean():
  pts = np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.0], [0.1, 0.2, 0.3]])
  out = voxel_downsample(pts, 1.0)
  np.testing.assert_array_equal(out[1], pts[1])  # alone in voxel (1, 0, 0), bit for bit
  np.testing.assert_allclose(out[0], pts[[0, 2]].mean(0))
  np.testing.assert_allclose(voxel_downsample(pts, 100.0), pts.mean(0, keepdims=True))


def test_each_centroid_lies_in_its_voxel_and_the_count_falls_with_size():
  pts = np.random.default_rng(4).uniform(-1, 1, size=(3000, 3))
  counts = [len(voxel_downsample(pts, s)) for s in (0.05, 0.2, 0.8)]
  assert counts[0] > counts[1] > counts[2]
  out = voxel_downsample(pts, 0.2)
  cell = np.floor((out - pts.min(0)) / 0.2)
  assert len(np.unique(cell, axis=0)) == len(out)  # one centroid per voxel, inside it


@pytest.mark.parametrize("size", [0.0, -1.0, float("nan"), float("inf"), "big"])
def test_bad_size_is_a_value_error_naming_it(size):
  with pytest.raises(ValueError, match="size"):
    voxel_downsample(np.zeros((5, 3)), size)


def test_bad_cloud_is_a_value_error():
  with pytest.raises(ValueError):
    voxel_downsample(np.zeros((5, 2)), 1.0)
  with pytest.raises(ValueError, match="too small"):
    voxel_downsample(np.array([[0.0, 0, 0], [1e30, 0, 0]]), 1e-20)
