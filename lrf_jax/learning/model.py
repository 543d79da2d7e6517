"""The trainable parameters: seeded initial values of LRF-Net's weight network and of the
ablation variants.

The networks are defined in flax (`networks.py`); their forward passes for inference, the
parameter files and the shipped weights are `lrf_jax.frames.weights` (no flax there), and the
ablation variants' frames are `lrf_jax.frames.ablation.variant_frames`.
"""

from __future__ import annotations

from collections.abc import Sequence

from lrf_jax.frames.ablation import check_modes
from lrf_jax.frames.weights import Params


def init_params(seed: int = 0, num_attributes: int = 2,
                widths: Sequence[int] = (16, 32, 64)) -> Params:
  """Seeded initial parameters of the weight network (`networks.WeightNet`).

  Args:
    seed: PRNG seed (`jax.random.key(seed)`).
    num_attributes: A, the number of per-point attributes (2 in the paper).
    widths: encoder widths.

  Returns:
    A flax params pytree: {"enc<i>", "dec<i>", "out"} each {"kernel", "bias"}.
  """
  from lrf_jax.learning.networks import init_weight_net  # flax, only to initialise
  return init_weight_net(seed, num_attributes, widths)


def init_variant_params(seed: int, z_mode: str, x_mode: str,
                        widths: tuple[int, ...] = (16, 32, 64)) -> dict[str, Params]:
  """Seeded parameters of one ablation variant (`lrf_jax.frames.ablation`)."""
  check_modes(z_mode, x_mode)
  params = {}
  if x_mode in ("sum1", "max"):
    params["weights"] = init_params(seed, 2, widths)
  elif x_mode == "sum2":
    params["weights"] = init_params(seed, 6, widths)
  else:
    from lrf_jax.learning.networks import init_regressor  # flax: only the "dr" variants need it
    params["x_reg"] = init_regressor(seed + 1, 6)
  if z_mode == "dr":
    from lrf_jax.learning.networks import init_regressor
    params["z_reg"] = init_regressor(seed + 2, 3)
  return params
