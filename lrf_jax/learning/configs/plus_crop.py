"""Beyond the paper: lrf_net_plus weights trained with partiality augmentation (half of the
training patches of each side cut by a random plane 0.3-1 r from the keypoint, independently per
side, `crop_p=0.5`), on the reduced schedule of the ablation preset, z sign over the whole
support, no noise augmentation. Compare with `plus` + `noise_mr=` (the same without cuts).

    LRF_DATA=... python train.py --config plus_crop --workdir runs/plus_crop
"""

import dataclasses

from lrf_jax.learning.configs import ablation


def get_config():
  return dataclasses.replace(ablation.get_config(), name="plus_crop", z_sign="ball",
                             crop_p=0.5, crop_min=0.3)
