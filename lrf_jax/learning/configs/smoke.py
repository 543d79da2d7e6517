"""A CPU run of well under a minute on the procedural demo set (no data needed): the same code
path as `default` with a tiny schedule, a larger learning rate and noise augmentation so that
the loss visibly moves in a few dozen steps; used by the tests.

    python train.py --config smoke --workdir /tmp/smoke
"""

from lrf_jax.learning.config import TrainConfig


def get_config() -> TrainConfig:
  return TrainConfig(
      name="smoke", data="demo", num_train_keypoints=1024, patch_k=128, batch_size=64,
      epochs=3, learning_rate=3e-3, lr_decay=0.95, noise_mr=(0.1, 0.3, 0.5), val_pairs=1,
      val_keypoints=100, log_every=4, checkpoint_every=8)
