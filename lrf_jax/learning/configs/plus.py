"""Beyond the paper (lrf_net_plus): z sign over the whole support (`z_sign="ball"`) and noise
augmentation (0-0.5 mr on the scene side), on the reduced schedule of the ablation preset (5
epochs of 10,000 BR keypoints). Switch either off with overrides to measure its share.

On the bunny validation scans the noise-augmented weights (lrf_jax/weights/ablation/
plus_noise_aug.msgpack, 0.662) lost to the paper-config LRF-Net weights used with the ball sign
(0.739), so `lrf_net_plus` shipped with the latter until the softmax x of `plus_soft`
(its current weights); both are kept for the ablation.

    LRF_DATA=... python train.py --config plus --workdir runs/plus
    LRF_DATA=... python train.py --config plus --workdir runs/plus_noaug noise_mr=
"""

import dataclasses

from lrf_jax.learning.configs import ablation


def get_config():
  return dataclasses.replace(ablation.get_config(), name="plus", z_sign="ball",
                             noise_mr=(0.0, 0.1, 0.2, 0.3, 0.4, 0.5))
