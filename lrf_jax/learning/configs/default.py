"""The paper's training setup (section 3.1): noise-free BR, 256 points per patch, 512 pairs per
batch, Adam 1e-4 decaying 5% per epoch, 20 epochs, Chamfer eq_cham (the smaller directed mean).

    LRF_DATA=/path/to/data python train.py --config default --workdir runs/default
"""

from lrf_jax.learning.config import TrainConfig


def get_config() -> TrainConfig:
  return TrainConfig(name="default")
