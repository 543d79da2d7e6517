"""The accelerator radius search (`lrf_jax.search.device`) gives the host search's patches."""

from __future__ import annotations

import numpy as np
import pytest

import lrf_jax
from lrf_jax.search.device import DeviceIndex, build_patches_device
from lrf_jax.search.neighborhoods import build_patches


def _cloud(seed=0):
  """A wavy height field with a 20x denser strip, so that some grid cells overflow their cap."""
  rng = np.random.default_rng(seed)
  xy = np.concatenate([rng.uniform(0, 10, (12000, 2)), rng.uniform([4, 0], [5, 10], (8000, 2))])
  z = 0.6 * np.sin(1.3 * xy[:, 0]) + 0.4 * np.cos(0.9 * xy[:, 1])
  return np.c_[xy, z] + 100.0  # away from the origin: float32 offsets must still be exact


def _assert_same(dev, host, rows=None):
  rows = slice(None) if rows is None else rows
  np.testing.assert_array_equal(np.asarray(dev.indices)[rows], host.indices[rows])
  np.testing.assert_array_equal(np.asarray(dev.mask)[rows], host.mask[rows])
  np.testing.assert_allclose(np.asarray(dev.offsets)[rows], host.offsets[rows], atol=2e-5)
  np.testing.assert_array_equal(np.asarray(dev.z_count)[rows], host.z_count[rows])
  np.testing.assert_allclose(np.asarray(dev.z_mean)[rows], host.z_mean[rows], atol=2e-6)
  np.testing.assert_allclose(np.asarray(dev.z_cov)[rows], host.z_cov[rows], atol=2e-6)


@pytest.mark.parametrize("k", [32, 128])
def test_device_patches_equal_host_patches(k):
  pts = _cloud()
  kp = np.random.default_rng(1).choice(len(pts), 600, replace=False)
  r = 0.8
  host = build_patches(pts, kp, r, k, seed=3)
  dev, inexact = build_patches_device(pts, kp, r, k, seed=3)
  _assert_same(dev, host)
  full = np.asarray(dev.count) >= 0
  assert full.all()


def test_truncated_cells_are_detected_and_redone_on_the_host():
  pts = _cloud()
  kp = np.random.default_rng(2).choice(len(pts), 600, replace=False)
  r, k = 0.8, 128
  index = DeviceIndex(pts, r, k, seed=0, cap=96)  # too small for the dense strip: cells overflow
  host = build_patches(pts, kp, r, k)
  raw, inexact = build_patches_device(pts, kp, r, k, index=index, fallback=False)
  assert 0.05 < inexact.mean() < 1.0  # the criterion fires, and not everywhere
  _assert_same(raw, host, rows=~inexact)  # what it vouches for is exact even with cap = 16
  wrong = (np.asarray(raw.indices) != host.indices).any(1)
  assert wrong[inexact].any() and not wrong[~inexact].any()
  fixed, _ = build_patches_device(pts, kp, r, k, index=index)
  _assert_same(fixed, host)


def test_compute_frames_device_search_matches_host():
  pts = _cloud(4)
  kp = np.arange(0, len(pts), 41)
  f0, v0 = lrf_jax.compute_frames(pts, kp, 0.8, "lrf_net", search="host", chunk_size=200)
  f1, v1 = lrf_jax.compute_frames(pts, kp, 0.8, "lrf_net", search="device", chunk_size=200)
  np.testing.assert_array_equal(np.asarray(v0), np.asarray(v1))
  # Same patches; the normal statistics differ by float32 round-off (two-pass on the device,
  # float64 on the host), which moves an ill-conditioned frame by a few 1e-4 at most.
  err = np.abs(np.asarray(f0) - np.asarray(f1)).max(axis=(1, 2))
  assert np.quantile(err, 0.99) < 1e-4 and err.max() < 1e-3, np.sort(err)[-5:]


def test_device_search_rejects_all_neighbor_patches_and_bad_names():
  pts = _cloud()
  with pytest.raises(ValueError, match="integer patch size"):
    lrf_jax.compute_frames(pts, np.arange(5), 0.8, "flare", search="device")
  with pytest.raises(ValueError, match="search"):
    lrf_jax.compute_frames(pts, np.arange(5), 0.8, "lrf_net", search="gpu")
  with pytest.raises(ValueError, match="integer"):
    build_patches_device(pts, np.arange(5), 0.8, None)


@pytest.mark.data
def test_device_search_on_br_bunny(br_bunny):
  points, faces, mr, _ = br_bunny
  kp = np.random.default_rng(0).choice(len(points), 500, replace=False)
  host = build_patches(points, kp, 15 * mr, 256)
  dev, inexact = build_patches_device(points, kp, 15 * mr, 256)
  assert inexact.mean() < 0.01  # the default cap (2K) is exact almost everywhere on real scans
  _assert_same(dev, host)
