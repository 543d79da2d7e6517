"""`lrf_jax.registration.stages`, the stages of `register` run one at a time: the stage timer,
the keypoint draw and `reseed`, the working cloud (thinned or kept) and its map back to the input
points, and `prepare`'s checks. (`register` end to end: tests/test_registration.py; the stages
pooled by `effort="high"`: tests/test_effort.py.)"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lrf_jax import datasets
from lrf_jax.geometry.cloud import as_cloud
from lrf_jax.registration import stages
from lrf_jax.registration.options import RegisterOptions

KW = dict(n_keypoints=200, n_correspondences=100, method="toldi", descriptor="toldi")


@pytest.fixture(scope="module")
def demo():
  return datasets.make_demo_pair(0, seed=0, noise_mr=0.0, partial=True)


@pytest.fixture(scope="module")
def prepared(demo):
  opts = RegisterOptions(mr=demo.mr, **KW)
  return stages.prepare(demo.model_points, demo.scene_points, opts), opts


def test_stage_timer_adds_up_the_time_of_each_named_stage():
  timer = stages.StageTimer()
  for _ in range(2):
    with timer("a"):
      time.sleep(0.01)
  with pytest.raises(RuntimeError), timer("b"):  # a stage that fails is still timed
    raise RuntimeError("x")
  assert set(timer.seconds) == {"a", "b"}
  assert timer.seconds["a"] >= 0.02 and timer.seconds["b"] >= 0.0
  assert timer.total() >= sum(timer.seconds.values())


@pytest.mark.parametrize("n_keypoints", [1, 50, 499, 500, 10_000])
def test_random_keypoints_are_sorted_distinct_in_range_and_seeded(n_keypoints):
  pts = np.random.default_rng(0).normal(size=(500, 3))
  opts = RegisterOptions(n_keypoints=n_keypoints)
  kp = stages.draw_keypoints(pts, 1.0, opts, np.random.default_rng(7))
  assert len(kp) == min(n_keypoints, 500) and len(np.unique(kp)) == len(kp)
  assert (np.diff(kp) > 0).all() and kp.min() >= 0 and kp.max() < 500
  np.testing.assert_array_equal(kp, stages.draw_keypoints(pts, 1.0, opts,
                                                          np.random.default_rng(7)))


def test_prepare_keeps_a_clean_pair_and_draws_each_sides_keypoints(prepared, demo):
  p, opts = prepared
  assert p.mr == demo.mr and p.voxel_size == 0.0 and p.seed == 0
  assert p.radius == pytest.approx(opts.radius_mr * demo.mr)
  for side, pts in zip(p.sides, (demo.model_points, demo.scene_points)):
    np.testing.assert_array_equal(side.points, pts)  # not thinned: the input cloud itself
    assert side.input_index is None and side.raw is None
    assert len(side.keypoints) == KW["n_keypoints"] and (np.diff(side.keypoints) > 0).all()
  assert not np.array_equal(p.sides[0].keypoints, p.sides[1].keypoints)


def test_reseed_with_prepares_own_seed_draws_its_keypoints_again(prepared):
  p, opts = prepared
  same = stages.reseed(p, opts, p.seed)
  for a, b in zip(same.sides, p.sides):
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    assert a.cloud is b.cloud and a.normals is b.normals
  other = stages.reseed(p, opts, p.seed + 1)
  assert other.seed == p.seed + 1 and (other.mr, other.radius) == (p.mr, p.radius)
  assert not np.array_equal(other.sides[0].keypoints, p.sides[0].keypoints)
  with pytest.raises(ValueError, match="seed"):
    stages.reseed(p, opts, -1)


def test_a_thinned_working_cloud_maps_back_to_its_input_points(demo):
  cloud = as_cloud(demo.model_points, "source")
  kept, index, voxel = stages.working_cloud(cloud, demo.mr, 0.0)
  assert kept is cloud and index is None and voxel == 0.0
  thin, index, voxel = stages.working_cloud(cloud, demo.mr, 2 * demo.mr)
  assert voxel == 2 * demo.mr and len(thin.points) == len(index) < len(cloud.points)
  assert len(np.unique(index)) == len(index) and index.max() < len(cloud.points)
  # a working point is its voxel's centroid: within one voxel diagonal of its first input point
  gap = np.linalg.norm(thin.points - cloud.points[index], axis=1)
  assert gap.max() <= np.sqrt(3) * voxel
  sides = tuple(stages.Side(thin, None, np.arange(3), None, idx) for idx in (index, None))
  p = stages.Prepared(sides, demo.mr, 1.0, np.random.default_rng(0), 0, voxel)
  src, dst = np.array([0, 5, 9]), np.array([1, 2, 3])
  pairs = stages.input_indices(p, src, dst)
  assert pairs.dtype == np.int64
  np.testing.assert_array_equal(pairs, np.stack([index[src], dst], axis=1))


@pytest.mark.parametrize("which", [0, 1])
def test_prepare_refuses_a_cloud_of_fewer_than_10_points_by_name(demo, which):
  clouds = [demo.model_points, demo.scene_points]
  clouds[which] = clouds[which][:9]
  name = ("source", "target")[which]
  with pytest.raises(ValueError, match=rf"^{name}: expected a cloud of at least 10 points, got 9"):
    stages.prepare(*clouds, RegisterOptions(mr=demo.mr, **KW))
