"""Beyond the paper: the default schedule with Gaussian noise augmentation on the scene side.

The paper trains on noise-free BR only; this preset draws, per batch and cloud, a noise level
from {0, 0.1, ..., 0.5} mr and adds it to the scene side (the training vertices of the noise-free
models, never the stored noisy scenes; the evaluation keypoints stay excluded).

    LRF_DATA=/path/to/data python train.py --config noise_aug --workdir runs/noise_aug
"""

import dataclasses

from lrf_jax.learning.configs import default


def get_config():
  return dataclasses.replace(default.get_config(), name="noise_aug",
                             noise_mr=(0.0, 0.1, 0.2, 0.3, 0.4, 0.5))
