"""`lrf_jax.search.neighborhoods.SearchIndex` handed to the frames and the patches: an index of
another cloud (same shape, other points) is refused by name; an index of equal points is the
cloud's own."""

from __future__ import annotations

import numpy as np
import pytest

from lrf_jax.frames.host_path import host_frames
from lrf_jax.search.neighborhoods import SearchIndex
from tests.lrf_testing import unit_sphere


def test_host_frames_refuses_an_index_of_another_cloud():
  a, b = unit_sphere(seed=1), unit_sphere(seed=2)  # same shape, other points
  with pytest.raises(ValueError, match="index: a SearchIndex of a different cloud"):
    host_frames(b, np.arange(5), 0.5, "shot", index=SearchIndex(a))
  with pytest.raises(ValueError, match="index: expected a SearchIndex"):
    host_frames(b, np.arange(5), 0.5, "shot", index=a)


def test_host_frames_accepts_an_index_of_equal_points():
  pts = unit_sphere()
  kp = np.arange(0, len(pts), 50)
  own, v_own = host_frames(pts, kp, 0.5, "shot", index=SearchIndex(pts))  # the same array
  copy, v_copy = host_frames(pts, kp, 0.5, "shot", index=SearchIndex(pts.copy()))  # equal values
  np.testing.assert_array_equal(copy, own)
  np.testing.assert_array_equal(v_copy, v_own)
  assert v_own.all()


def test_build_patches_refuses_an_index_of_another_cloud():
  from lrf_jax.search.neighborhoods import SearchIndex, build_patches
  rng = np.random.default_rng(0)
  a, b = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
  with pytest.raises(ValueError, match="different cloud"):
    build_patches(b, np.arange(5), 0.5, k=16, index=SearchIndex(a))
  ok = build_patches(b, np.arange(5), 0.5, k=16, index=SearchIndex(b.copy()))
  ref = build_patches(b, np.arange(5), 0.5, k=16)
  np.testing.assert_array_equal(np.asarray(ok.mask), np.asarray(ref.mask))
