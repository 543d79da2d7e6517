"""Training for lrf_net_plus from the points alone (`TrainConfig.z_view="voted"`, the
`plus_points` preset): the batches carry the views inference computes, the step and validation
use them, and `z_view="none"` changes nothing."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lrf_jax
from lrf_jax.datasets import repeatability_keypoints
from lrf_jax.frames import METHODS
from lrf_jax.frames.lrf_net_plus import prepare_view
from lrf_jax.learning import checkpoints, data_sources, train_lib, train_step
from lrf_jax.learning import config as config_lib
from lrf_jax.learning.batches import Batch, BatchMaker, TrainingClouds, global_batch
from tests.lrf_testing import random_rotation


def _tiny(**overrides) -> config_lib.TrainConfig:
  """plus_points on the demo set at sizes that build an epoch in about a second."""
  return config_lib.replace(config_lib.load_config("plus_points"), **{
      "data": "demo", "num_train_keypoints": 256, "patch_k": 128, "batch_size": 32,
      "epochs": 1, "noise_mr": (0.0, 0.3), "val_pairs": 1, "val_keypoints": 40,
      **overrides})


@pytest.fixture(scope="module")
def voted():
  cfg = _tiny()
  clouds = data_sources.training_clouds(cfg)
  return cfg, clouds, BatchMaker(clouds, cfg)


def _rows(tree, sel):
  return jax.tree.map(lambda a: a[sel], tree)


def test_z_view_is_validated_and_the_preset_is_plus_soft_with_votes():
  with pytest.raises(ValueError, match=r"config\.z_view: expected 'none' or 'voted', got 'vote'"):
    config_lib.replace(config_lib.TrainConfig(), z_view="vote")
  with pytest.raises(ValueError, match=r"config\.z_view: 'voted'.*z_mode 'normal'"):
    config_lib.replace(config_lib.TrainConfig(), z_view="voted", z_mode="dr")
  with pytest.raises(ValueError, match=r"config\.z_view.*x_mode"):
    config_lib.replace(config_lib.TrainConfig(), z_view="voted", x_mode="sum2")
  assert config_lib.TrainConfig().z_view == "none"
  assert "plus_points" in config_lib.preset_names()
  plus, soft = config_lib.load_config("plus_points"), config_lib.load_config("plus_soft")
  assert plus == config_lib.replace(soft, name="plus_points", z_view="voted")
  assert soft.z_view == "none"


def test_batch_views_are_prepare_views_on_the_epochs_clouds(voted):
  cfg, clouds, maker = voted
  kp = clouds.keypoints
  levels = set()
  for epoch in (0, 1):
    patches = maker.epoch_patches(epoch)
    views = maker.epoch_views(epoch)
    for side in (0, 1):
      assert views[side].shape == (len(kp), 3) and views[side].dtype == np.float32
      assert np.isfinite(views[side]).all()
      assert np.any(views[side] != 0, axis=1).mean() > 0.9  # closed shapes: decisive votes
      for c in np.unique(kp[:, 0]):
        sel = np.flatnonzero(kp[:, 0] == c)
        pts, level = maker.side_points(epoch, side, int(c))
        levels.add(level)
        ref = prepare_view(pts, kp[sel, 1], _rows(patches[side], sel),
                           radius=float(clouds.radii[c]))
        np.testing.assert_array_equal(views[side][sel], ref.view)
  assert levels == {0.0, 0.3}  # noisy scenes and cached noise-free ones both checked
  batch = maker.batch(1, 2)
  rows = maker.epoch_order(1)[2 * cfg.batch_size:3 * cfg.batch_size]
  np.testing.assert_array_equal(batch.model_view, maker.epoch_views(1)[0][rows])
  np.testing.assert_array_equal(batch.scene_view, maker.epoch_views(1)[1][rows])


def test_unperturbed_clouds_keep_their_normals_across_epochs(voted, monkeypatch):
  cfg, clouds, maker = voted
  from lrf_jax.learning import batches
  maker.epoch_patches(0)
  calls = []
  real = batches.points_only_normals
  monkeypatch.setattr(batches, "points_only_normals",
                      lambda pts, r: calls.append(r) or real(pts, r))
  cached = set(maker._voted)
  ids = range(len(clouds.models))
  assert {(0, c) for c in ids} <= cached  # every model side after one epoch
  maker.epoch_patches(5)
  noisy = [c for c in ids if maker.noise_level(5, c) > 0]
  fresh = [c for c in ids if c not in noisy and (1, c) not in cached]
  # Only the scenes with noise this epoch, and the noise-free ones seen for the first time, are
  # oriented; every model side is reused.
  assert noisy and len(calls) == len(noisy) + len(fresh)
  assert (1, noisy[0]) not in maker._voted or (1, noisy[0]) in cached


def test_views_rotate_with_the_cloud():
  cfg = _tiny(noise_mr=(), num_train_keypoints=96)
  pairs = data_sources.training_clouds(_tiny())
  c = 1  # one cloud of the demo set (32768 points)
  rot, shift = random_rotation(3), np.array([2.0, -1.0, 0.5])
  keypoints = np.stack([np.zeros(96, np.int64), np.arange(96) * 311], axis=1)

  def views(move):
    clouds = TrainingClouds([move(pairs.models[c])], [move(pairs.scenes[c])],
                            pairs.radii[c:c + 1], pairs.mr[c:c + 1], keypoints, ["c"])
    return BatchMaker(clouds, cfg).epoch_views(0)

  before = views(lambda p: p)
  after = views(lambda p: p @ rot.T + shift)
  for a, b in zip(before, after):
    given = np.any(a != 0, axis=1)
    assert given.mean() > 0.9
    np.testing.assert_array_equal(given, np.any(b != 0, axis=1))
    scale = np.linalg.norm(a, axis=1, keepdims=True) + 1e-9
    np.testing.assert_allclose(b / scale, (a @ rot.T) / scale, atol=1e-4)


def test_a_jitted_step_with_views_is_finite_and_z_follows_the_view(voted):
  cfg, _, maker = voted
  batch = maker.batch(0, 0)
  state = train_step.create_state(cfg)
  mesh = jax.make_mesh((1,), ("data",), axis_types=(jax.sharding.AxisType.Auto,))  # as the loop's
  placed = global_batch(batch, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data")))
  assert len(jax.tree.leaves(placed)) == 18  # 2 x 8 patch fields + 2 views
  new, m = jax.jit(train_step.make_train_step(cfg))(state, placed)
  assert np.isfinite(float(m["loss"])) and 0 < float(m["grad_norm"]) < np.inf
  assert float(m["valid_fraction"]) > 0.9
  assert not checkpoints.nonfinite_leaves(new.params)
  frames, valid = jax.jit(train_step.frames_fn(cfg))(
      state.params, jax.tree.map(jnp.asarray, batch.model), batch.model_view)
  dots = np.einsum("nc,nc->n", np.asarray(frames)[:, 2], batch.model_view)
  given = np.asarray(valid) & np.any(batch.model_view != 0, axis=1)
  assert given.mean() > 0.9 and (dots[given] >= 0).all()


def test_z_view_none_batches_have_no_view_leaves_and_the_same_patches(voted):
  cfg, clouds, maker = voted
  plain = BatchMaker(clouds, config_lib.replace(cfg, z_view="none"))
  a, b = plain.batch(0, 1), maker.batch(0, 1)
  assert a.model_view is None and a.scene_view is None
  assert len(jax.tree.leaves(a)) == len(jax.tree.leaves(Batch(a.model, a.scene))) == 16
  assert plain.epoch_views(0) == (None, None)
  for x, y in zip(jax.tree.leaves((a.model, a.scene)), jax.tree.leaves((b.model, b.scene))):
    np.testing.assert_array_equal(x, y)


def test_validation_orients_z_as_points_only_inference(voted):
  cfg = config_lib.replace(voted[0], val_keypoints=30)
  pairs = data_sources.validation_pairs(cfg)
  val = train_lib.build_validation(pairs, cfg)
  params = lrf_jax.default_params("lrf_net_plus")
  pair, pm, view = pairs[0], val.model[0], val.model_view[0]
  # lrf_net_plus with the points alone (no viewpoint), exact network and no density weights:
  # the frames validation computes.
  kp, _ = repeatability_keypoints(pair, cfg.val_keypoints, seed=cfg.seed)
  extra = prepare_view(pair.model_points, kp, pm, radius=cfg.radius_mr * pair.mr)
  np.testing.assert_array_equal(view, extra.view)
  want = jax.jit(lambda p, e: METHODS["lrf_net_plus"].fn(p, e, params=params, lut=0,
                                                         density=False))(pm, extra)
  got = val.frames(params, jax.tree.map(jnp.asarray, pm), view)
  for x, y in zip(got, want):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  result = train_lib.validate(params, val)
  assert np.isfinite(result["val_meancos"])
  plain = train_lib.build_validation(pairs, config_lib.replace(cfg, z_view="none"))
  assert plain.model_view == [None] and plain.scene_view == [None]


def test_runs_saved_before_z_view_existed_resume(tmp_path):
  cfg = config_lib.load_config("smoke")
  saved = json.loads(cfg.to_json())
  del saved["z_view"]
  (tmp_path / "config.json").write_text(json.dumps(saved))
  assert train_lib.resume_config(tmp_path, cfg) is None
  checkpoints.check_compatible(saved, cfg, tmp_path)  # no error
  with pytest.raises(ValueError, match="z_view"):
    checkpoints.check_compatible(saved, config_lib.replace(
        cfg, z_view="voted"), tmp_path)
