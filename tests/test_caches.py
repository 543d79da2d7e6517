"""`lrf_jax.caches`: the module-level caches hand out the caller's own copies (estimated normals,
`cache_last`'s arrays, mean curvature) or read-only arrays (the host weight tables), so writing
into what a cache gave never changes a later result."""

from __future__ import annotations

import numpy as np
import pytest

import lrf_jax
from lrf_jax.geometry import normals
from tests.lrf_testing import tetrahedron, unit_sphere


def test_estimated_normals_are_the_callers_own_copy():
  pts = unit_sphere()
  first = normals.estimate_normals(pts, 0.3)
  expected = first.copy()
  first[:] = 7.0  # writing into what the cache gave must not reach the next caller
  again = normals.estimate_normals(pts, 0.3)
  np.testing.assert_array_equal(again, expected)
  assert again is not first


def test_writing_into_estimated_normals_does_not_change_later_frames():
  pts = unit_sphere()
  kp = np.arange(0, len(pts), 20)
  f0, v0 = lrf_jax.compute_frames(pts, kp, 0.5, "board")
  nrm = normals.estimate_normals(pts, normals.NORMAL_RADIUS_RATIO * 0.5)
  nrm[:] = -nrm[::-1]
  f1, v1 = lrf_jax.compute_frames(pts, kp, 0.5, "board")
  np.testing.assert_array_equal(np.asarray(f1), np.asarray(f0))
  np.testing.assert_array_equal(np.asarray(v1), np.asarray(v0))


def test_cache_last_copies_arrays_in_tuples():
  calls = []

  def fn():
    calls.append(1)
    return np.arange(3.0), (np.ones(2), "tag")

  key = (np.arange(5),)
  a, (b, tag) = normals.cache_last("test_caches", key, fn)
  a[:] = -1
  b[:] = -1
  a2, (b2, tag2) = normals.cache_last("test_caches", key, fn)
  assert len(calls) == 1 and tag2 == tag == "tag"
  np.testing.assert_array_equal(a2, np.arange(3.0))
  np.testing.assert_array_equal(b2, np.ones(2))
  normals.CLOUD_CACHE.pop("test_caches")


def test_mean_curvature_cache_hands_out_copies():
  pts, faces = tetrahedron()
  h = normals.mean_curvature(pts, faces)
  expected = h.copy()
  h[:] = 1e9
  np.testing.assert_array_equal(normals.mean_curvature(pts, faces), expected)


def test_cached_host_weight_table_is_read_only():
  from lrf_jax.frames import patch_frames
  params = lrf_jax.default_params("lrf_net")
  table = patch_frames.cached_weight_table(params, 17, host=True)
  with pytest.raises(ValueError, match="read-only"):
    table.values[0, 0] = 1.0
  assert patch_frames.cached_weight_table(params, 17, host=True) is table
