"""The training job of LRF-Net (paper section 3.2): validation and the loop.

`train_and_evaluate(config, workdir)` is the whole job; `train.py` only parses arguments. The
parts live by concern: batches in `lrf_jax.learning.batches` (data sources in `lrf_jax.learning.data_sources`),
the state, optimiser and step in `lrf_jax.learning.train_step`, checkpoints in `lrf_jax.learning.checkpoints`.

* Data parallelism: a `jax.sharding.Mesh` over all devices with one "data" axis; batches are
  sharded along it and parameters replicated. The same code runs multi-process once
  `jax.distributed.initialize` has been called (train.py's --coordinator flags): every process
  builds the same global batch from the seed and places only the rows of its own devices
  (`batches.global_batch`); every process takes part in each step, validation and checkpoint
  save or restore; only process 0 writes the other files of the workdir (config.json,
  metrics.jsonl, curves.png, final and best parameters) and shows the progress bar. The workdir
  must be one shared folder for all processes.
* Validation: at the end of every epoch, MeanCos on fixed patches of validation pairs (by
  default Stanford bunny scans), with the config's frames function jitted once per run; with
  `z_view="voted"` z is oriented as lrf_net_plus orients it from the points alone (the views of
  `lrf_net_plus.points_only_view`, computed once per run).
* Checkpoints: at the end of every epoch, every `checkpoint_every` steps and at the last step; a
  restarted run resumes from the latest readable one, under the config it was started with
  (config.json): a different config is an error naming the fields, unless `replace_config`,
  which keeps config.json, writes the new config as config.<n>.json and notes the change in
  metrics.jsonl.
* Files: every file is written atomically (`lrf_jax.io.atomic`): a failed write (a full disk)
  leaves the previous file and raises `WriteError`. metrics.jsonl is appended one record at a
  time (one write, flush and fsync; a failed append is truncated away); a torn last line left
  by a killed process is dropped when the run resumes.
* One run per workdir: process 0 holds an exclusive lock (`fcntl.flock`) on
  `<workdir>/train.lock` for the whole run, with its pid written inside; a second run in the
  same workdir stops at once with `WorkdirLockedError` naming the holder's pid. The file is
  removed at the end of the run; the lock dies with its process, so the file a killed run left
  (a dead pid) is simply taken over.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import json
import math
import os
import stat
import sys
import textwrap
import time
from pathlib import Path
from typing import Any, NamedTuple
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from lrf_jax._jax import exact_matmuls
from lrf_jax.extras import missing_extra, pyplot

try:
  import orbax.checkpoint as ocp
except ImportError as e:  # the [train] extra
  raise missing_extra(e.name, "train", "training (lrf_jax.learning.train_lib)") from e

from lrf_jax.learning import data_sources
from lrf_jax.frames import metrics as metrics_lib
from lrf_jax.learning.batches import Batch, BatchMaker, TrainingClouds, global_batch
from lrf_jax.learning.checkpoints import (is_primary, nonfinite_leaves, restore_params, resume,
                                 save_checkpoint)
from lrf_jax.learning.config import TrainConfig, with_new_defaults
from lrf_jax.datasets import repeatability_keypoints
from lrf_jax.frames.lrf_net import MIN_Z_NEIGHBORS
from lrf_jax.frames.lrf_net_plus import points_only_view
from lrf_jax.io import atomic
from lrf_jax.learning.losses import frames_with_view
from lrf_jax.frames.weights import save_params
from lrf_jax.search.neighborhoods import Patches, build_patches
from lrf_jax.learning.train_step import TrainState, create_state, frames_fn, make_train_step


# ----------------------------------------------------------------------------- validation


@dataclasses.dataclass(frozen=True)
class ValidationSet:
  """Fixed patches of corresponding keypoints on validation pairs, built once per run.

  Attributes:
    names: pair names.
    model, scene: per pair, the `Patches` of its keypoints on each side (rows correspond).
    rotations: per pair, the (3, 3) ground-truth rotation from model to scene.
    frames: the jitted `(params, patches[, view]) -> (frames, valid)` of the run's model; built
      once, so calls with patches of the shapes already seen reuse its compiled code.
    model_view, scene_view: per pair, the (N, 3) float32 views of each side's patches
      (`z_view="voted"`: `lrf_net_plus.points_only_view`, the points alone), or None.
  """

  names: list[str]
  model: list[Patches]
  scene: list[Patches]
  rotations: list[np.ndarray]
  frames: Callable[..., tuple[jax.Array, jax.Array]]
  model_view: list[np.ndarray | None] | None = None
  scene_view: list[np.ndarray | None] | None = None


def build_validation(pairs: list[Any], config: TrainConfig) -> ValidationSet:
  """Patches for `config.val_keypoints` protocol keypoints per pair (`lrf_jax.datasets.Pair`),
  and the config's frames function (`train_step.frames_fn`) jitted once. With
  `config.z_view="voted"`, each side's views from its points alone, as lrf_net_plus computes them
  without a viewpoint, faces or normals (`lrf_net_plus.points_only_view`)."""
  names, pm, ps, rots, vm, vs = [], [], [], [], [], []
  for pair in pairs:
    mi, si = repeatability_keypoints(pair, config.val_keypoints, seed=config.seed)
    r = config.radius_mr * pair.mr
    pm.append(build_patches(pair.model_points, mi, r, config.patch_k, seed=config.seed))
    ps.append(build_patches(pair.scene_points, si, r, config.patch_k, seed=config.seed))
    voted = config.z_view == "voted"
    vm.append(points_only_view(pair.model_points, pm[-1], r)[0] if voted else None)
    vs.append(points_only_view(pair.scene_points, ps[-1], r)[0] if voted else None)
    names.append(pair.name)
    rots.append(np.asarray(pair.transform)[:3, :3])
  return ValidationSet(names, pm, ps, rots, jax.jit(exact_matmuls(frames_fn(config))), vm, vs)


def validate(params, val: ValidationSet) -> dict[str, Any]:
  """Mean MeanCos over validation pairs (per pair first), and per pair, with `val.frames`.

  Returns:
    {"val_meancos": float (NaN without pairs), "val_per_pair": {name: float}}.
  """
  per_pair = {}
  none = [None] * len(val.names)
  for name, pm, ps, rot, view_m, view_s in zip(val.names, val.model, val.scene, val.rotations,
                                               val.model_view or none, val.scene_view or none):
    fm, vm = frames_with_view(val.frames, params, jax.tree.map(jnp.asarray, pm), view_m)
    fs, vs = frames_with_view(val.frames, params, jax.tree.map(jnp.asarray, ps), view_s)
    per_pair[name] = float(jnp.mean(metrics_lib.meancos(fm, fs, rot, vm, vs)))
  return {"val_meancos": float(np.mean(list(per_pair.values()))) if per_pair else float("nan"),
          "val_per_pair": per_pair}


# ----------------------------------------------------------------------------- the loop

# The files a run writes in its workdir besides checkpoints/ and config.json / config.<n>.json.
OUTPUT_FILES = ("metrics.jsonl", "curves.png", "final_params.msgpack", "best_params.msgpack")


def train_and_evaluate(config: TrainConfig, workdir: str | Path, *,
                       clouds: TrainingClouds | None = None, val_pairs: list[Any] | None = None,
                       stop_after_steps: int | None = None, progress: bool = True,
                       replace_config: bool = False) -> dict:
  """Train (or resume) a run in `workdir`; returns the final metrics.

  In a multi-process run every process calls this with the same arguments and the same
  (shared) `workdir`; the returned metrics are the same in all of them.

  Args:
    config: the run's configuration.
    workdir: output folder: checkpoints/, metrics.jsonl, config.json, curves.png, final params.
    clouds: training data; built from `config` when None.
    val_pairs: validation pairs; the first `config.val_pairs` bunny scan pairs when None.
    stop_after_steps: stop (as if killed) after this global step; for tests of resumption.
    progress: show a progress bar (in process 0 only).
    replace_config: resume a run started under another config (see `resume_config`).

  Returns:
    {"step", "loss", "val_meancos", ...} of the last step.

  Raises:
    WorkdirLockedError: another run holds the workdir (a ValueError).
    ValueError: `workdir` is a file, its run was started under another config (without
      `replace_config`), or its checkpoints are incompatible or unreadable.
    FloatingPointError: the run diverged (see `check_finite`).
    WriteError: a file of the workdir could not be written (e.g. a full disk).
  """
  workdir = Path(workdir)
  if workdir.exists() and not workdir.is_dir():
    raise ValueError(f"--workdir: {workdir} is a file; expected a folder (new or a run's)")
  workdir.mkdir(parents=True, exist_ok=True)
  with workdir_lock(workdir):
    return _train(config, workdir, clouds=clouds, val_pairs=val_pairs,
                  stop_after_steps=stop_after_steps, progress=progress,
                  replace_config=replace_config)


LOCK_FILE = "train.lock"


class WorkdirLockedError(ValueError):
  """Another train.py holds the workdir's lock (the message names the workdir and its pid)."""


@contextlib.contextmanager
def workdir_lock(workdir: Path) -> Iterator[None]:
  """Hold `<workdir>/train.lock` (process 0 only; the other processes of a multi-process run
  share the workdir with it) for the duration of the block.

  Raises:
    WorkdirLockedError: another process holds it.
    ValueError: `train.lock` is not a regular file (a symbolic link: the pid written into the
      lock would truncate the file it points to; a folder, a FIFO).
  """
  if not is_primary():
    yield
    return
  path = Path(workdir) / LOCK_FILE
  while True:
    fd = _open_lock(path)
    try:
      fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "unknown"
      os.close(fd)
      raise WorkdirLockedError(
          f"--workdir: {workdir} is in use by another train.py (pid {holder}); wait for it to "
          "finish, stop it, or choose another --workdir") from None
    try:  # the holder we waited on may have removed the file: lock the one at `path`
      same = os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
      same = False
    if same:
      break
    os.close(fd)
  try:
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    yield
  finally:
    try:
      path.unlink()  # while still holding it: a later run creates and locks a new file
    except OSError:
      pass
    os.close(fd)  # releases the lock


def _open_lock(path: Path) -> int:
  """A descriptor of the lock file at `path` (created if missing), never following a symbolic
  link and only for a regular file (ValueError otherwise)."""
  refusal = (f"--workdir: {path} is not a regular file; it is {LOCK_FILE}, the workdir's "
             "lock: remove it (nothing else writes there)")
  try:
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
  except OSError as e:
    if e.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
      raise ValueError(refusal) from None
    raise
  if not stat.S_ISREG(os.fstat(fd).st_mode):
    os.close(fd)
    raise ValueError(refusal)
  return fd


def _train(config: TrainConfig, workdir: Path, *, clouds: TrainingClouds | None,
           val_pairs: list[Any] | None, stop_after_steps: int | None, progress: bool,
           replace_config: bool) -> dict:
  """`train_and_evaluate` once the workdir is locked."""
  replaced = resume_config(workdir, config, replace_config)
  maker, val = _training_data(config, clouds, val_pairs)
  mesh = _mesh(config)
  replicated, data_sharding = NamedSharding(mesh, P()), NamedSharding(mesh, P("data"))
  mngr, state = resume(workdir, create_state(config), config)
  start = int(state.step)
  state = jax.device_put(state, replicated)
  step_fn = jax.jit(exact_matmuls(make_train_step(config)), donate_argnums=0,
                    out_shardings=(replicated, replicated))
  total = config.total_steps if stop_after_steps is None else min(config.total_steps,
                                                                   stop_after_steps)
  if start and is_primary():
    print(f"resuming from step {start} of {config.total_steps} ({workdir})", file=sys.stderr)
  log = _Log(workdir, config, start, total, progress, replaced)
  try:
    for step in range(start, total):
      epoch, in_epoch = divmod(step, config.steps_per_epoch)
      batch = maker.batch(epoch, in_epoch)
      state, m = step_fn(state, global_batch(batch, data_sharding))
      log.count(config.batch_size)
      done = step + 1
      due = _due(config, done, total)
      if due.check:
        m = {k: float(v) for k, v in jax.device_get(m).items()}
        check_finite(m, state.params, done, epoch, batch)  # before anything is logged or saved
      if due.log:
        m = log.stamp(m, done, done / config.steps_per_epoch)
        if due.end_of_epoch and val is not None:
          m.update(validate(state.params, val))
        log.write(m)
      if due.save:
        save_checkpoint(mngr, done, state, config, _ranking(log.last, done, due.end_of_epoch))
      log.advance()
  except KeyboardInterrupt:
    log.close()
    mngr.close()  # a save in flight is finished: no partial checkpoint is left
    raise
  log.close()
  mngr.wait_until_finished()
  if int(jax.device_get(state.step)) >= config.total_steps:
    _write_results(state, mngr, workdir, config)
  mngr.close()
  return log.last


def _training_data(config: TrainConfig, clouds: TrainingClouds | None,
                   val_pairs: list[Any] | None) -> tuple[BatchMaker, ValidationSet | None]:
  """The run's batch maker and validation set (None without validation pairs); `clouds` and
  `val_pairs` default to the config's data sources."""
  if clouds is None:
    clouds = data_sources.training_clouds(config)
  if val_pairs is None:
    val_pairs = data_sources.validation_pairs(config)
  val = build_validation(val_pairs, config) if val_pairs else None
  return BatchMaker(clouds, config), val


def _mesh(config: TrainConfig) -> Mesh:
  """A 1-axis ("data") mesh over all devices of all processes; its size divides the batch."""
  mesh = jax.make_mesh((jax.device_count(),), ("data",),
                       axis_types=(jax.sharding.AxisType.Auto,))
  if config.batch_size % mesh.size:
    raise ValueError(f"config.batch_size: {config.batch_size} is not divisible by the "
                     f"{mesh.size} devices of the data mesh")
  return mesh


class _Due(NamedTuple):
  """What happens after a step: `check` its metrics and parameters for non-finite values, `log`
  a record (with validation at the `end_of_epoch`), `save` a checkpoint."""

  check: bool
  log: bool
  save: bool
  end_of_epoch: bool


def _due(config: TrainConfig, done: int, total: int) -> _Due:
  """`_Due` after `done` steps of a run that stops at `total`."""
  end_of_epoch = done % config.steps_per_epoch == 0
  save = end_of_epoch or done % config.checkpoint_every == 0 or done == total
  return _Due(check=done % config.log_every == 0 or save,
              log=done % config.log_every == 0 or end_of_epoch or done == total,
              save=save, end_of_epoch=end_of_epoch)


def _ranking(last: dict[str, Any], done: int, end_of_epoch: bool) -> dict[str, float] | None:
  """The metrics that rank checkpoint `done` among the best: this epoch's validation MeanCos,
  when it was just measured; None otherwise."""
  if end_of_epoch and "val_meancos" in last and last["step"] == done:
    return {"val_meancos": last["val_meancos"]}
  return None


def _write_results(state: TrainState, mngr: ocp.CheckpointManager, workdir: Path,
                   config: TrainConfig) -> None:
  """At the end of a run: final_params.msgpack, best_params.msgpack (the best checkpoint's, if
  any was ranked) and curves.png. Every process restores; process 0 writes."""
  primary = is_primary()
  if primary:
    _save_params(state.params, workdir / "final_params.msgpack")
  if mngr.best_step() is not None:
    params, _ = restore_params(workdir, "best")  # every process: orbax restores collectively
    if primary:
      _save_params(params, workdir / "best_params.msgpack")
  if primary:
    plot_curves(workdir / "metrics.jsonl", workdir / "curves.png",
                title=f"{config.name}: validation on "
                      f"{data_sources.validation_label(config)}")


def _save_params(params: Any, path: Path) -> None:
  """`weights.save_params` into a temporary file renamed to `path` (atomic)."""
  with atomic.atomic_path(path) as tmp:
    save_params(params, tmp)


def check_finite(metrics: dict, params: Any, step: int, epoch: int,
                 batch: Batch | None = None) -> None:
  """Raise FloatingPointError naming the step and what went wrong: a non-finite loss or gradient
  norm, a batch whose frames were all invalid (valid fraction 0: the loss is then 0 and means
  nothing), or non-finite parameters.

  With the step's host `batch`, a batch of invalid frames whose patches mostly hold fewer than
  the z axis's `MIN_Z_NEIGHBORS` points within r/3 is blamed on the support (radius_mr too
  small for the data's resolution), not on the learning rate."""
  for key in ("loss", "grad_norm"):
    if key in metrics and not math.isfinite(metrics[key]):
      raise FloatingPointError(
          f"step {step} (epoch {epoch}): non-finite {key} {metrics[key]}; metrics {metrics}. "
          "Lower the learning rate or check the data for degenerate patches.")
  if metrics.get("valid_fraction", 1.0) <= 0.0:
    support = _support_problem(batch)
    if support:
      raise FloatingPointError(f"step {step} (epoch {epoch}): valid fraction 0 (every frame of "
                               f"the batch is invalid): {support}")
    raise FloatingPointError(
        f"step {step} (epoch {epoch}): valid fraction 0 (every frame of the batch is invalid); "
        f"metrics {metrics}. The parameters have probably diverged: lower the learning rate.")
  bad = nonfinite_leaves(params)
  if bad:
    raise FloatingPointError(f"step {step} (epoch {epoch}): non-finite parameters in {bad}")


# ----------------------------------------------------------------------------- logs and plots


class _Log:
  """metrics.jsonl, config.json, the progress bar and the throughput of a run.

  Only process 0 writes files and shows the bar. On creation the records after `start` (steps a
  resumed run replays) are dropped from metrics.jsonl and config.json is written if missing
  (`replaced`: the new config goes to that file instead, with a note record in the log).
  `last` is the latest record (`{"step": start}` before the first).
  """

  def __init__(self, workdir: Path, config: TrainConfig, start: int, total: int,
               progress: bool, replaced: str | None = None):
    self.path = workdir / "metrics.jsonl"
    self.primary = is_primary()
    if self.primary:
      _trim_log(self.path, start)  # steps after the checkpoint are replayed: log them once
      if replaced:  # the old config stays; the new one beside it, and a note in the log
        atomic.write_text(workdir / replaced, config.to_json())
        _append_jsonl(self.path, {"step": start, "note": f"config replaced by {replaced} at "
                                                          f"step {start}"})
      elif not (workdir / "config.json").exists():
        atomic.write_text(workdir / "config.json", config.to_json())
    self.last: dict[str, Any] = {"step": start}
    self._val: float | None = None  # the latest validation MeanCos shown on the bar
    self._bar = _progress(total, start, progress and self.primary)
    self._since, self._pairs = time.perf_counter(), 0

  def count(self, pairs: int) -> None:
    """`pairs` more training pairs went through a step."""
    self._pairs += pairs

  def stamp(self, m: dict, step: int, epoch: float) -> dict:
    """`m` with "step", "epoch" and "pairs_per_s" (since the previous stamp) added."""
    now = time.perf_counter()
    m.update(step=step, epoch=epoch, pairs_per_s=self._pairs / max(now - self._since, 1e-9))
    self._since, self._pairs = now, 0
    return m

  def write(self, m: dict) -> None:
    """Append record `m` to metrics.jsonl, make it `last` and show it on the bar."""
    if self.primary:
      _append_jsonl(self.path, m)
    self.last = m
    if "val_meancos" in m:
      self._val = m["val_meancos"]
    shown = {"loss": f"{m['loss']:.4g}"}
    if self._val is not None:  # nothing before the first validation (no "nan")
      shown["val"] = f"{self._val:.3f}"
    self._bar.set_postfix(**shown)

  def advance(self) -> None:
    self._bar.update(1)

  def close(self) -> None:
    self._bar.close()


def _support_problem(batch: Batch | None) -> str | None:
  """Why the patches of `batch` cannot give frames (None: they can, or no batch): most of them
  hold fewer than `MIN_Z_NEIGHBORS` points within r/3, where the z axis (the normal) is fitted."""
  if batch is None:
    return None
  z_count = np.concatenate([np.asarray(batch.model.z_count), np.asarray(batch.scene.z_count)])
  count = np.concatenate([np.asarray(batch.model.count), np.asarray(batch.scene.count)])
  short = float(np.mean(z_count < MIN_Z_NEIGHBORS))
  if short < 0.5:
    return None
  return (f"{100 * short:.0f}% of its patches hold fewer than {MIN_Z_NEIGHBORS} points within "
          f"r/3 (median {np.median(z_count):g} there, {np.median(count):g} within r), too few "
          "for the z axis: the support is too small for the data's resolution; raise radius_mr")


def resume_config(workdir: Path, config: TrainConfig, replace: bool = False) -> str | None:
  """Check `config` against the one `workdir`'s run was started (or last replaced) under.

  The run's config is the newest of config.json, config.1.json, ...; none: a new run.

  Args:
    workdir: the run's folder.
    config: the requested config.
    replace: on a difference, continue under `config` instead of refusing.

  Returns:
    None (a new run, or the same config); with `replace` and a different config, the name of
    the file to record `config` in (config.<n>.json, n one more than the newest).

  Raises:
    ValueError: the configs differ and not `replace` (the message names every differing field),
      a parameter-shape field differs while checkpoints exist (never resumable), or the saved
      config is not readable JSON.
  """
  saved_path, n = _latest_config(workdir)
  if saved_path is None:
    return None
  try:
    saved = json.loads(saved_path.read_text())
    if not isinstance(saved, dict):
      raise ValueError("expected a JSON object")
  except (ValueError, UnicodeDecodeError) as e:
    raise ValueError(f"{saved_path}: the run's saved config is not readable ({e}); restore it "
                     "or choose another --workdir") from None
  saved = with_new_defaults(saved)  # a run from before a field existed had its default
  wanted = json.loads(config.to_json())
  diffs = [k for k in sorted(set(saved) | set(wanted)) if saved.get(k) != wanted.get(k)]
  if not diffs:
    return None
  if any(f in diffs for f in TrainConfig.MODEL_FIELDS) and any(
      p.name.isdigit() for p in (workdir / "checkpoints").glob("*")):
    from lrf_jax.learning.checkpoints import check_compatible
    check_compatible(saved, config, workdir)
  detail = ", ".join(f"{k}: saved {saved.get(k)!r} vs requested {wanted.get(k)!r}"
                     for k in diffs)
  if not replace:
    raise ValueError(f"{workdir}: this run was started under another config ({saved_path.name}; "
                     f"{detail}); resume it with the same config, choose another --workdir, or "
                     "pass --replace-config to continue under the new one (both are kept)")
  return f"config.{n + 1}.json"


def _latest_config(workdir: Path) -> tuple[Path | None, int]:
  """The newest recorded config of a run and its number (config.json: 0; none: (None, 0))."""
  numbered = sorted((int(p.name.split(".")[1]), p) for p in workdir.glob("config.*.json")
                    if p.name.split(".")[1].isdigit() and p.name.count(".") == 2)
  if numbered:
    return numbered[-1][1], numbered[-1][0]
  plain = workdir / "config.json"
  return (plain, 0) if plain.is_file() else (None, 0)


def _read_jsonl(path: Path) -> list[tuple[str, dict]]:
  """(line, record) of a metrics.jsonl; lines that do not parse (a torn last line) are skipped."""
  rows = []
  for line in path.read_text(errors="replace").splitlines():
    try:
      row = json.loads(line)
    except ValueError:
      continue
    if isinstance(row, dict):
      rows.append((line, row))
  return rows


def _trim_log(path: Path, step: int) -> None:
  """Drop the records of `metrics.jsonl` after `step` (a resumed run logs them again), and any
  torn line; the file is rewritten atomically (when anything is dropped)."""
  if not path.exists():
    return
  text = path.read_text(errors="replace")
  keep = "".join(line + "\n" for line, row in _read_jsonl(path) if row.get("step", 0) <= step)
  if keep != text:
    atomic.write_text(path, keep)


def _append_jsonl(path: Path, record: dict) -> None:
  atomic.append_line(path, json.dumps(record))


class _NoBar:
  def update(self, n): ...
  def set_postfix(self, **kw): ...
  def close(self): ...


def _progress(total: int, start: int, enabled: bool):
  if not enabled:
    return _NoBar()
  from tqdm.auto import tqdm
  return tqdm(total=total, initial=start, unit="step", desc="train", dynamic_ncols=True)


def written_files(workdir: str | Path) -> list[Path]:
  """The outputs of a run that exist in `workdir`: checkpoints/, the config files and
  `OUTPUT_FILES` (what train.py lists at the end of a run)."""
  workdir = Path(workdir)
  names = ["checkpoints", "config.json"] + sorted(
      p.name for p in workdir.glob("config.*.json")) + list(OUTPUT_FILES)
  return [workdir / n for n in names if (workdir / n).exists()]


def plot_curves(log_path: Path, out: Path, title: str = "validation") -> None:
  """Loss and validation MeanCos against the step, as a PNG; `title` heads the validation
  panel (say what was validated on: `data_sources.validation_label`)."""
  plt = pyplot("train", "the training curves")

  rows = [r for _, r in _read_jsonl(log_path) if "loss" in r]  # not the notes
  fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
  ax[0].plot([r["step"] for r in rows], [r["loss"] for r in rows])
  ax[0].set(xlabel="step", ylabel="Chamfer loss", title="training loss")
  val = [r for r in rows if "val_meancos" in r]
  ax[1].plot([r["epoch"] for r in val], [r["val_meancos"] for r in val], marker="o")
  ax[1].set(xlabel="epoch", ylabel="MeanCos", title=textwrap.fill(title, 48))  # no clipping
  fig.tight_layout()
  atomic.save_figure(fig, out, dpi=120)
  plt.close(fig)
