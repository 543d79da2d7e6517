"""The state, optimiser and step of LRF-Net training (paper section 3.2).

`create_state(config)` builds the parameters of the config's model (LRF-Net, or a variant of
`lrf_jax.frames.ablation`) and Adam with the paper's learning-rate schedule: the rate decays by
`lr_decay` once per epoch (a staircase exponential decay). The schedule is built once per state
(`learning_rate_schedule`) and kept on it (`TrainState.lr_schedule`), so the optimiser and the
"lr" the step reports are the same function. `make_train_step(config)` is the pure step
`(state, batch) -> (state, metrics)`; the loop jits it with the state donated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from lrf_jax.extras import missing_extra

try:
  import optax
  from flax import struct
  from flax.training import train_state
except ImportError as e:  # the [train] extra
  raise missing_extra(e.name, "train", "training (lrf_jax.learning.train_step)") from e

from lrf_jax.learning.batches import Batch
from lrf_jax.learning.config import TrainConfig, is_paper_model_fields
from lrf_jax.frames.ablation import variant_frames
from lrf_jax.frames.lrf_net import lrf_net_frames
from lrf_jax.frames.weights import load_params_numpy, weights_file
from lrf_jax.learning.losses import siamese_loss
from lrf_jax.learning.model import init_params, init_variant_params


class TrainState(train_state.TrainState):
  """flax TrainState (params, opt_state, step, tx) and the learning-rate schedule `tx` uses.

  apply_fn is unused (frames are a pure function of the parameters, `frames_fn`).
  lr_schedule: step -> learning rate, a static field (not a leaf, not checkpointed).
  """

  lr_schedule: optax.Schedule = struct.field(pytree_node=False)


def learning_rate_schedule(config: TrainConfig) -> optax.Schedule:
  """The paper's schedule: `learning_rate` decayed by `lr_decay` once per epoch (staircase)."""
  return optax.exponential_decay(config.learning_rate, config.steps_per_epoch,
                                 config.lr_decay, staircase=True)


def make_optimizer(schedule: optax.Schedule) -> optax.GradientTransformation:
  """Adam with the learning rate `schedule(step)`."""
  return optax.adam(schedule)


def is_paper_model(config: TrainConfig) -> bool:
  """True when the parameters are plain WeightNet parameters (`lrf_net_frames`)."""
  return is_paper_model_fields(config.z_mode, config.x_mode)


def frames_fn(config: TrainConfig):
  """`(params, patches, view=None) -> (frames, valid)` for the config's model (LRF-Net or an
  ablation). `view`: optional (N, 3) direction z must not point away from where non-zero
  (`lrf_net.view_sign`; `config.z_view="voted"`, which only the paper's model takes)."""
  if is_paper_model(config):
    return lambda p, patches, view=None: lrf_net_frames(p, patches, x_mode=config.x_mode,
                                                        z_sign=config.z_sign, view=view)
  x_mode = "sum1" if config.x_mode == "sum" else config.x_mode

  def variant(p, patches, view=None):
    if view is not None:
      raise ValueError(f"frames_fn: the ablation variant z_mode={config.z_mode!r} x_mode="
                       f"{config.x_mode!r} takes no view (config.z_view)")
    return variant_frames(p, patches, z_mode=config.z_mode, x_mode=x_mode)

  return variant


def create_state(config: TrainConfig) -> TrainState:
  """Step 0 of a run: initial parameters (seeded by `config.seed`, or read from `config.init`),
  Adam and its schedule.

  Raises:
    ValueError: `config.init` names no parameter file, or one whose layers or shapes are not
      this config's model's (the message names the first that differs).
  """
  if is_paper_model(config):
    params = init_params(config.seed, widths=config.widths)
    if config.init:
      params = _initial_params(config, params)
  else:
    x_mode = "sum1" if config.x_mode == "sum" else config.x_mode
    params = init_variant_params(config.seed, config.z_mode, x_mode, config.widths)
  schedule = learning_rate_schedule(config)
  return TrainState.create(apply_fn=None, params=params, tx=make_optimizer(schedule),
                           lr_schedule=schedule)


def _initial_params(config: TrainConfig, fresh):
  """The parameters of `config.init`, checked against the tree `fresh` of this model."""
  path = weights_file(config.init_weights_stem, config.init)
  loaded = load_params_numpy(path)
  want = jax.tree_util.tree_map(np.shape, fresh)
  got = jax.tree_util.tree_map(np.shape, loaded)
  same_tree = str(jax.tree_util.tree_structure(want)) == str(jax.tree_util.tree_structure(got))
  if not same_tree or want != got:
    raise ValueError(f"config.init: {path} holds parameters of another network (layer shapes "
                     f"{got}); expected this config's (widths {list(config.widths)}): {want}")
  return jax.tree_util.tree_map(lambda a, b: jnp.asarray(a, jnp.asarray(b).dtype), loaded, fresh)


def make_train_step(config: TrainConfig):
  """The pure step `(state, batch) -> (state, metrics)`; jit it with `donate_argnums=0`.

  metrics: scalar "loss" (Chamfer, `config.loss_reduction`), "grad_norm" (global L2 norm),
  "valid_fraction" (of the batch's frames) and "lr" (the rate this step's update used).
  """

  def loss_fn(params, batch: Batch):
    return siamese_loss(params, batch.model, batch.scene, reduction=config.loss_reduction,
                        frames_fn=frames_fn(config), model_view=batch.model_view,
                        scene_view=batch.scene_view)

  def train_step(state: TrainState, batch: Batch):
    (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params, batch)
    state = state.apply_gradients(grads=grads)
    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads),
               "valid_fraction": aux["valid_fraction"], "lr": state.lr_schedule(state.step - 1)}
    return state, metrics

  return train_step
