"""Weakly supervised training of LRF-Net (paper section 3.2): data, step, checkpoints, loop.

`train_and_evaluate(config, workdir)` is the whole job; `train.py` only parses arguments.

* Data: a fixed, seeded set of training keypoints over corresponding clouds (noise-free BR: each
  model and the same model under a scene's ground truth). An epoch is one pass in a seeded
  shuffled order; every batch is rebuilt from (seed, epoch, batch index) alone, with 256 points
  sampled independently on each side, so a resumed run sees exactly the batches it would have.
* Step: `train_step(state, batch) -> (state, metrics)`, jitted with the state donated; Adam with
  a learning rate decaying 5% per epoch (a staircase exponential decay).
* Data parallelism: a `jax.sharding.Mesh` over all devices with one "data" axis; batches are
  sharded along it and parameters replicated. The same code runs multi-host once
  `jax.distributed.initialize` has been called (train.py's --coordinator flags).
* Checkpoints: orbax `CheckpointManager` keeps the latest and the best (by validation MeanCos on
  the Stanford bunny scans) checkpoints with the config beside them; a restarted run resumes from
  the latest.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax.training import train_state
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from lrf_jax import metrics as metrics_lib
from lrf_jax.config import TrainConfig
from lrf_jax.frames.ablation import init_variant_params, variant_frames
from lrf_jax.frames.lrf_net import lrf_net_frames
from lrf_jax.losses import siamese_loss
from lrf_jax.model import init_params, save_params
from lrf_jax.neighborhoods import Patches, build_patches


# ----------------------------------------------------------------------------- data


@dataclasses.dataclass(frozen=True)
class TrainingClouds:
  """Corresponding clouds and the fixed training keypoints over them.

  Attributes:
    models: list of (n_c, 3) model clouds.
    scenes: list of (n_c, 3) scene clouds; scene point i corresponds to model point i.
    radii: (C,) support radius of each cloud in its units (radius_mr x the model's mr).
    mr: (C,) mesh resolution of each model.
    keypoints: (P, 2) int64 rows (cloud id, point index): the training set of one epoch.
    names: cloud names, for logs.
  """

  models: list[np.ndarray]
  scenes: list[np.ndarray]
  radii: np.ndarray
  mr: np.ndarray
  keypoints: np.ndarray
  names: list[str]


def _mix(*ints: int) -> int:
  """A deterministic 63-bit seed from integers (so batch seeds depend only on their position)."""
  return int(np.random.SeedSequence(list(ints)).generate_state(1, np.uint64)[0] >> np.uint64(1))


def sample_training_keypoints(sizes: list[int], count: int, seed: int,
                              exclude: list[np.ndarray] | None = None) -> np.ndarray:
  """A seeded set of (cloud id, point index) drawn uniformly over all points of all clouds.

  Args:
    sizes: points per cloud.
    count: keypoints wanted.
    seed: seed.
    exclude: per cloud, point indices that may not be drawn (the evaluation keypoints).

  Returns:
    (count, 2) int64.
  """
  pool = []
  for c, n in enumerate(sizes):
    ok = np.ones(n, bool)
    if exclude is not None and len(exclude[c]):
      ok[exclude[c]] = False
    idx = np.flatnonzero(ok)
    pool.append(np.stack([np.full(idx.size, c), idx], axis=1))
  pool = np.concatenate(pool)
  rng = np.random.default_rng(_mix(seed, 1))
  return pool[np.sort(rng.choice(len(pool), size=min(count, len(pool)), replace=False))]


class Batch(NamedTuple):
  """Corresponding patches: `model[i]` and `scene[i]` are one training pair."""

  model: Patches
  scene: Patches


def crop_patches(patches: Patches, p: float, min_dist: float,
                 rng: np.random.Generator) -> Patches:
  """Partiality augmentation: cut a random fraction `p` of the patches by a plane.

  For a cut patch, a direction u uniform on the sphere and a distance c uniform in
  [min_dist, 1) · r are drawn; the neighbours with offset · u > c are dropped (mask False, offset
  0, index -1), as if a scan's boundary ran there. The keypoint side of the plane is kept, and
  the normal statistics (r/3) are left as they are: the cut teaches the x-axis weights to live
  with a support that ends early on one side.

  Args:
    patches: host `Patches` (N rows).
    p: probability of cutting each row.
    min_dist: smallest plane distance, as a fraction of r.
    rng: numpy generator (the caller seeds it per epoch, side and cloud).

  Returns:
    `Patches` with the same shapes.
  """
  n = patches.offsets.shape[0]
  cut = rng.random(n) < p
  u = rng.normal(size=(n, 3))
  u /= np.linalg.norm(u, axis=1, keepdims=True)
  c = rng.uniform(min_dist, 1.0, n) * np.asarray(patches.radius, np.float64)
  drop = cut[:, None] & (np.einsum("nkc,nc->nk", patches.offsets, u) > c[:, None])
  drop &= patches.mask
  return patches._replace(offsets=np.where(drop[..., None], 0.0, patches.offsets).astype(np.float32),
                          mask=patches.mask & ~drop,
                          indices=np.where(drop, -1, patches.indices).astype(np.int32))


class BatchMaker:
  """Builds the batch of any (epoch, step) from the seed alone.

  The patches of a whole epoch are built at once, cloud by cloud and side by side (one radius
  search per cloud and side instead of one per batch), and batches gather rows from them.
  Subsample seeds depend on (seed, epoch, side), so both sides of a pair sample their 256 points
  independently and every epoch sees new subsamples. With `config.noise_mr`, each cloud's scene
  side gets, per epoch, Gaussian noise of a level drawn from the list (seeded by (seed, epoch,
  cloud)). With `config.crop_p`, patches are cut by random planes (`crop_patches`), seeded by
  (seed, epoch, side, cloud).
  """

  def __init__(self, clouds: TrainingClouds, config: TrainConfig):
    self.clouds = clouds
    self.config = config
    self._epoch: int | None = None
    self._patches: tuple[Patches, Patches] | None = None

  def epoch_order(self, epoch: int) -> np.ndarray:
    rng = np.random.default_rng(_mix(self.config.seed, 2, epoch))
    return rng.permutation(len(self.clouds.keypoints))

  def noise_level(self, epoch: int, cloud: int) -> float:
    """The noise (in mr) added to `cloud`'s scene side during `epoch` (0 without augmentation)."""
    if not self.config.noise_mr:
      return 0.0
    rng = np.random.default_rng(_mix(self.config.seed, 4, epoch, cloud))
    return float(rng.choice(np.asarray(self.config.noise_mr)))

  def epoch_patches(self, epoch: int) -> tuple[Patches, Patches]:
    """(model, scene) patches of every training keypoint for `epoch`, rows as `keypoints`."""
    if self._epoch == epoch:
      return self._patches
    cfg, kp = self.config, self.clouds.keypoints
    sides = []
    for side in (0, 1):
      seed = _mix(cfg.seed, 3, epoch, side)
      parts, rows = [], []
      for c in np.unique(kp[:, 0]):
        sel = np.flatnonzero(kp[:, 0] == c)
        pts = self.clouds.models[c] if side == 0 else self.clouds.scenes[c]
        level = self.noise_level(epoch, int(c)) if side == 1 else 0.0
        if level > 0:
          rng = np.random.default_rng(_mix(cfg.seed, 5, epoch, int(c)))
          pts = pts + rng.normal(scale=level * self.clouds.mr[c], size=pts.shape)
        part = build_patches(pts, kp[sel, 1], float(self.clouds.radii[c]), cfg.patch_k,
                             seed=seed, validate=False)
        if cfg.crop_p > 0:
          crop_rng = np.random.default_rng(_mix(cfg.seed, 6, epoch, side, int(c)))
          part = crop_patches(part, cfg.crop_p, cfg.crop_min, crop_rng)
        parts.append(part)
        rows.append(sel)
      # Scatter each cloud's rows into place (one copy, instead of concatenate + gather).
      fields = [np.empty((len(kp),) + a.shape[1:], a.dtype) for a in parts[0]]
      for part, sel in zip(parts, rows):
        for out, a in zip(fields, part):
          out[sel] = a
      sides.append(Patches(*fields))
    self._epoch, self._patches = epoch, (sides[0], sides[1])
    return self._patches

  def batch(self, epoch: int, step_in_epoch: int) -> Batch:
    bs = self.config.batch_size
    rows = self.epoch_order(epoch)[step_in_epoch * bs:(step_in_epoch + 1) * bs]
    model, scene = self.epoch_patches(epoch)
    return Batch(*(jax.tree.map(lambda a: a[rows], p) for p in (model, scene)))


# ----------------------------------------------------------------------------- state and step


class TrainState(train_state.TrainState):
  """flax TrainState (params, opt_state, step, tx); apply_fn is unused (frames are a pure fn)."""


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
  """Adam with the paper's schedule: lr decays by `lr_decay` once per epoch (staircase)."""
  schedule = optax.exponential_decay(config.learning_rate, config.steps_per_epoch,
                                     config.lr_decay, staircase=True)
  return optax.adam(schedule)


def is_paper_model(config: TrainConfig) -> bool:
  """True when the parameters are plain WeightNet parameters (`lrf_net_frames`)."""
  return config.z_mode == "normal" and config.x_mode in ("sum", "max", "softmax")


def frames_fn(config: TrainConfig):
  """`(params, patches) -> (frames, valid)` for the config's model (LRF-Net or an ablation)."""
  if is_paper_model(config):
    return lambda p, patches: lrf_net_frames(p, patches, x_mode=config.x_mode,
                                             z_sign=config.z_sign)
  x_mode = "sum1" if config.x_mode == "sum" else config.x_mode
  return lambda p, patches: variant_frames(p, patches, z_mode=config.z_mode, x_mode=x_mode)


def create_state(config: TrainConfig) -> TrainState:
  if is_paper_model(config):
    params = init_params(config.seed, widths=config.widths)
  else:
    x_mode = "sum1" if config.x_mode == "sum" else config.x_mode
    params = init_variant_params(config.seed, config.z_mode, x_mode, config.widths)
  return TrainState.create(apply_fn=None, params=params, tx=make_optimizer(config))


def make_train_step(config: TrainConfig):
  """The pure step `(state, batch) -> (state, metrics)`; jit it with `donate_argnums=0`."""
  schedule = optax.exponential_decay(config.learning_rate, config.steps_per_epoch,
                                     config.lr_decay, staircase=True)

  def loss_fn(params, batch: Batch):
    return siamese_loss(params, batch.model, batch.scene, reduction=config.loss_reduction,
                        frames_fn=frames_fn(config))

  def train_step(state: TrainState, batch: Batch):
    (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params, batch)
    state = state.apply_gradients(grads=grads)
    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads),
               "valid_fraction": aux["valid_fraction"], "lr": schedule(state.step - 1)}
    return state, metrics

  return train_step


# ----------------------------------------------------------------------------- validation


@dataclasses.dataclass(frozen=True)
class ValidationSet:
  """Fixed patches of corresponding keypoints on validation pairs, built once."""

  names: list[str]
  model: list[Patches]
  scene: list[Patches]
  rotations: list[np.ndarray]


def build_validation(pairs: list[Any], config: TrainConfig) -> ValidationSet:
  """Patches for `config.val_keypoints` protocol keypoints per pair (`lrf_jax.datasets.Pair`)."""
  from lrf_jax.datasets import repeatability_keypoints

  names, pm, ps, rots = [], [], [], []
  for pair in pairs:
    mi, si = repeatability_keypoints(pair, config.val_keypoints, seed=config.seed)
    r = config.radius_mr * pair.mr
    pm.append(build_patches(pair.model_points, mi, r, config.patch_k, seed=config.seed))
    ps.append(build_patches(pair.scene_points, si, r, config.patch_k, seed=config.seed))
    names.append(pair.name)
    rots.append(np.asarray(pair.transform)[:3, :3])
  return ValidationSet(names, pm, ps, rots)


def validate(params, val: ValidationSet, fn=None) -> dict[str, float]:
  """Mean MeanCos over validation pairs (per pair first), and per pair.

  `fn(params, patches) -> (frames, valid)` defaults to `lrf_net_frames`."""
  fn = jax.jit(fn or lrf_net_frames)
  per_pair = {}
  for name, pm, ps, rot in zip(val.names, val.model, val.scene, val.rotations):
    fm, vm = fn(params, jax.tree.map(jnp.asarray, pm))
    fs, vs = fn(params, jax.tree.map(jnp.asarray, ps))
    per_pair[name] = float(jnp.mean(metrics_lib.meancos(fm, fs, rot, vm, vs)))
  return {"val_meancos": float(np.mean(list(per_pair.values()))) if per_pair else float("nan"),
          "val_per_pair": per_pair}


# ----------------------------------------------------------------------------- checkpoints


def checkpoint_manager(workdir: Path, create: bool = True) -> ocp.CheckpointManager:
  """Keeps the latest two checkpoints (one to fall back to) and the best by validation MeanCos."""
  policy = ocp.checkpoint_managers.AnyPreservationPolicy([
      ocp.checkpoint_managers.LatestN(n=2),
      ocp.checkpoint_managers.BestN(get_metric_fn=lambda m: m["val_meancos"], reverse=False, n=1,
                                    keep_checkpoints_without_metrics=False),
  ])
  options = ocp.CheckpointManagerOptions(
      preservation_policy=policy, best_fn=lambda m: m["val_meancos"], best_mode="max",
      create=create)
  return ocp.CheckpointManager((Path(workdir) / "checkpoints").absolute(), options=options,
                               item_names=("state", "config"))


def check_compatible(saved: dict[str, Any], config: TrainConfig, where: Path) -> None:
  """Raise if a checkpoint was written under a config whose parameters differ in shape/meaning."""
  diffs = [f for f in TrainConfig.MODEL_FIELDS
           if json.dumps(saved.get(f)) != json.dumps(getattr(config, f), default=list)]
  if diffs:
    detail = ", ".join(f"{f}: checkpoint {saved.get(f)!r} vs config {getattr(config, f)!r}"
                       for f in diffs)
    raise ValueError(f"{where}: checkpoint is incompatible with this config ({detail}); use "
                     "another --workdir or the checkpoint's own config")


def restore_params(workdir: str | Path, which: str = "best") -> tuple[Any, TrainConfig]:
  """Parameters and config of a training run's best (or latest) checkpoint (for evaluate.py)."""
  mngr = checkpoint_manager(Path(workdir), create=False)
  step = mngr.best_step() if which == "best" else mngr.latest_step()
  if step is None:
    raise FileNotFoundError(f"{Path(workdir) / 'checkpoints'}: no checkpoint found")
  cfg_dict = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
  config = TrainConfig.from_dict({k: tuple(v) if isinstance(v, list) else v
                                  for k, v in cfg_dict.items()})
  restored = mngr.restore(step, args=ocp.args.Composite(
      state=ocp.args.StandardRestore(_state_target(create_state(config)))))
  return restored["state"]["params"], config


def _state_target(state: TrainState) -> dict[str, Any]:
  """The checkpointed part of a TrainState, as host arrays (the restore target)."""
  return jax.tree.map(np.asarray, {"params": state.params, "opt_state": state.opt_state,
                                   "step": state.step})


# ----------------------------------------------------------------------------- the loop


def _mesh() -> Mesh:
  return jax.make_mesh((jax.device_count(),), ("data",),
                       axis_types=(jax.sharding.AxisType.Auto,))


def train_and_evaluate(config: TrainConfig, workdir: str | Path, *,
                       clouds: TrainingClouds | None = None, val_pairs: list[Any] | None = None,
                       stop_after_steps: int | None = None, progress: bool = True) -> dict:
  """Train (or resume) a run in `workdir`; returns the final metrics.

  Args:
    config: the run's configuration.
    workdir: output folder: checkpoints/, metrics.jsonl, config.json, curves.png, final params.
    clouds: training data; built from `config` when None.
    val_pairs: validation pairs; the first `config.val_pairs` bunny scan pairs when None.
    stop_after_steps: stop (as if killed) after this global step; for tests of resumption.
    progress: show a progress bar.

  Returns:
    {"step", "loss", "val_meancos", ...} of the last step.
  """
  from lrf_jax import data_sources

  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  if clouds is None:
    clouds = data_sources.training_clouds(config)
  if val_pairs is None:
    val_pairs = data_sources.validation_pairs(config)
  val = build_validation(val_pairs, config) if val_pairs else None
  maker = BatchMaker(clouds, config)

  mesh = _mesh()
  if config.batch_size % mesh.size:
    raise ValueError(f"config.batch_size: {config.batch_size} is not divisible by the "
                     f"{mesh.size} devices of the data mesh")
  replicated = NamedSharding(mesh, P())
  data_sharding = NamedSharding(mesh, P("data"))

  state = create_state(config)
  mngr = checkpoint_manager(workdir)
  if mngr.latest_step() is not None:
    mngr, state = _restore_readable(mngr, state, config, workdir)
  start = int(state.step)
  state = jax.device_put(state, replicated)
  step_fn = jax.jit(make_train_step(config), donate_argnums=0,
                    out_shardings=(replicated, replicated))
  (workdir / "config.json").write_text(config.to_json())

  total = config.total_steps if stop_after_steps is None else min(config.total_steps,
                                                                   stop_after_steps)
  log_path = workdir / "metrics.jsonl"
  _trim_log(log_path, start)  # steps after the checkpoint are replayed: log them once
  last: dict[str, Any] = {"step": start}
  bar = _progress(total, start, progress)
  t_last, pairs_since = time.perf_counter(), 0
  for step in range(start, total):
    epoch, in_epoch = divmod(step, config.steps_per_epoch)
    batch = jax.device_put(maker.batch(epoch, in_epoch), data_sharding)
    state, m = step_fn(state, batch)
    pairs_since += config.batch_size
    done = step + 1
    end_of_epoch = done % config.steps_per_epoch == 0
    will_save = end_of_epoch or done % config.checkpoint_every == 0 or done == total
    if done % config.log_every == 0 or will_save:
      m = {k: float(v) for k, v in jax.device_get(m).items()}
      check_finite(m, state.params, done, epoch)  # before anything is logged or saved
    if done % config.log_every == 0 or end_of_epoch or done == total:
      now = time.perf_counter()
      m.update(step=done, epoch=done / config.steps_per_epoch,
               pairs_per_s=pairs_since / max(now - t_last, 1e-9))
      t_last, pairs_since = now, 0
      if end_of_epoch and val is not None:
        m.update(validate(state.params, val, frames_fn(config)))
      _append_jsonl(log_path, m)
      last = m
      bar.set_postfix(loss=f"{m['loss']:.4g}", val=f"{m.get('val_meancos', float('nan')):.3f}")
    if end_of_epoch or done % config.checkpoint_every == 0 or done == total:
      val_m = ({"val_meancos": last["val_meancos"]}
               if end_of_epoch and "val_meancos" in last and last["step"] == done else None)
      _save(mngr, done, state, config, val_m)
    bar.update(1)
  bar.close()
  mngr.wait_until_finished()
  if int(jax.device_get(state.step)) >= config.total_steps:
    save_params(state.params, workdir / "final_params.msgpack")
    best = mngr.best_step()
    if best is not None:
      params, _ = restore_params(workdir, "best")
      save_params(params, workdir / "best_params.msgpack")
    plot_curves(log_path, workdir / "curves.png")
  mngr.close()
  return last


def _restore_readable(mngr: ocp.CheckpointManager, state: Any, config: TrainConfig,
                      workdir: Path) -> tuple[ocp.CheckpointManager, Any]:
  """Restore the newest readable checkpoint, newest first.

  An unreadable one (a corrupt file, non-finite parameters) is renamed
  `checkpoints/<step>.unreadable` (kept, out of the way of the steps replayed over it) with one
  warning naming it. A checkpoint written under an incompatible config is an error, not skipped.

  Raises:
    ValueError: no checkpoint is readable (the message says how to start afresh).
  """
  root = workdir / "checkpoints"
  skipped = []
  for step in sorted(mngr.all_steps(), reverse=True):
    try:
      saved = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    except Exception as e:  # orbax raises JSON, tensorstore, Key and Value errors here
      skipped.append((step, e))
      continue
    check_compatible(saved["config"], config, workdir)
    try:
      restored = mngr.restore(step, args=ocp.args.Composite(
          state=ocp.args.StandardRestore(_state_target(state))))["state"]
      bad = nonfinite_leaves(restored["params"])
      if bad:
        raise FloatingPointError(f"non-finite parameters in {bad}")
    except Exception as e:
      skipped.append((step, e))
      continue
    if skipped:
      mngr.close()
      for bad_step, err in skipped:
        (root / str(bad_step)).rename(root / f"{bad_step}.unreadable")
      names = ", ".join(f"checkpoints/{s} ({type(e).__name__})" for s, e in skipped)
      warnings.warn(f"{names}: unreadable, kept as <step>.unreadable; resumed from "
                    f"checkpoints/{step}", stacklevel=3)
      mngr = checkpoint_manager(workdir)
    return mngr, state.replace(params=restored["params"], opt_state=restored["opt_state"],
                               step=restored["step"])
  tried = ", ".join(f"{s} ({type(e).__name__}: {str(e).splitlines()[0][:80]})"
                    for s, e in skipped)
  raise ValueError(f"{root}: no readable checkpoint (tried {tried}); delete that folder (or "
                   "choose another --workdir) to start afresh")


def nonfinite_leaves(tree: Any) -> list[str]:
  """Paths of the leaves of `tree` that hold a NaN or an infinity."""
  bad = []
  for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
    if not bool(jnp.all(jnp.isfinite(jnp.asarray(leaf)))):
      bad.append(jax.tree_util.keystr(path))
  return bad


def check_finite(metrics: dict, params: Any, step: int, epoch: int) -> None:
  """Raise FloatingPointError naming the step and what went wrong: a non-finite loss or gradient
  norm, a batch whose frames were all invalid (valid fraction 0: the loss is then 0 and means
  nothing), or non-finite parameters."""
  for key in ("loss", "grad_norm"):
    if key in metrics and not math.isfinite(metrics[key]):
      raise FloatingPointError(
          f"step {step} (epoch {epoch}): non-finite {key} {metrics[key]}; metrics {metrics}. "
          "Lower the learning rate or check the data for degenerate patches.")
  if metrics.get("valid_fraction", 1.0) <= 0.0:
    raise FloatingPointError(
        f"step {step} (epoch {epoch}): valid fraction 0 (every frame of the batch is invalid); "
        f"metrics {metrics}. The parameters have probably diverged: lower the learning rate.")
  bad = nonfinite_leaves(params)
  if bad:
    raise FloatingPointError(f"step {step} (epoch {epoch}): non-finite parameters in {bad}")


def _trim_log(path: Path, step: int) -> None:
  """Drop the records of `metrics.jsonl` after `step` (a resumed run logs them again)."""
  if not path.exists():
    return
  keep = [line for line in path.read_text().splitlines()
          if line.strip() and json.loads(line).get("step", 0) <= step]
  path.write_text("".join(line + "\n" for line in keep))


def _save(mngr, step, state, config, val_metrics):
  mngr.save(step, args=ocp.args.Composite(
      state=ocp.args.StandardSave(_state_target(state)),
      config=ocp.args.JsonSave(json.loads(config.to_json()))), metrics=val_metrics)


def _append_jsonl(path: Path, record: dict) -> None:
  with path.open("a") as f:
    f.write(json.dumps(record) + "\n")


class _NoBar:
  def update(self, n): ...
  def set_postfix(self, **kw): ...
  def close(self): ...


def _progress(total: int, start: int, enabled: bool):
  if not enabled:
    return _NoBar()
  from tqdm.auto import tqdm
  return tqdm(total=total, initial=start, unit="step", desc="train", dynamic_ncols=True)


def plot_curves(log_path: Path, out: Path) -> None:
  """Loss and validation MeanCos against the step, as a PNG."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  rows = [json.loads(l) for l in log_path.read_text().splitlines() if l.strip()]
  fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
  ax[0].plot([r["step"] for r in rows], [r["loss"] for r in rows])
  ax[0].set(xlabel="step", ylabel="Chamfer loss", title="training loss")
  val = [r for r in rows if "val_meancos" in r]
  ax[1].plot([r["epoch"] for r in val], [r["val_meancos"] for r in val], marker="o")
  ax[1].set(xlabel="epoch", ylabel="MeanCos", title="validation (bunny scans)")
  fig.tight_layout()
  fig.savefig(out, dpi=120)
  plt.close(fig)
