"""Beyond the paper (lrf_net_plus): the weight network's output read as a log-weight
(`x_mode="softmax"`, `lrf_net.softmax_weights`): x can concentrate on a few neighbors of the
rim, as FLARE's highest rim point does, instead of LRF-Net's broad linear weights. z sign over the
whole support, noise augmentation 0-0.5 mr on the scene side, a 10x larger learning rate than
the paper's (the log-weights must reach a scale of tens, from an initialisation near 0), 20 epochs
of 20,000 BR keypoints as the paper's schedule (the other fields as the ablation preset: 300
validation keypoints per bunny pair). The shipped `lrf_jax/weights/lrf_net_plus.msgpack`.

    LRF_DATA=... python train.py --config plus_soft --workdir runs/plus_soft
"""

import dataclasses

from lrf_jax.learning.configs import ablation


def get_config():
  return dataclasses.replace(ablation.get_config(), name="plus_soft", z_sign="ball",
                             x_mode="softmax", learning_rate=1e-3, epochs=20,
                             num_train_keypoints=20_000,
                             noise_mr=(0.0, 0.1, 0.2, 0.3, 0.4, 0.5))
