"""The ablation variants of the paper's section 3.3 on a reduced schedule (5 epochs of 10,000
BR keypoints, otherwise the default config). Choose the variant with overrides:

    LRF_DATA=... python train.py --config ablation --workdir runs/abl_dr_sum2 z_mode=dr x_mode=sum2

z_mode: normal | dr; x_mode: sum (Sum1) | sum2 | dr. "Max" has no gradient through its argmax:
evaluate.py runs it with the Sum1 weights of the same z_mode. The small weights of each variant
are shipped in lrf_jax/weights/ablation/ so that evaluate.py runs the ablation without training.
"""

import dataclasses

from lrf_jax.learning.configs import default


def get_config():
  return dataclasses.replace(default.get_config(), name="ablation", epochs=5,
                             num_train_keypoints=10_000, val_keypoints=300)
