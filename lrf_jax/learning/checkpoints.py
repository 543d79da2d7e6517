"""Checkpoints of a training run: orbax, in `<workdir>/checkpoints`, with the config beside them.

The `CheckpointManager` keeps the latest two checkpoints and the best one by validation MeanCos
(Stanford bunny scans); a restarted run resumes from the newest readable one
(`restore_readable`), and `restore_params` gives evaluate.py and lrf-register the parameters of a
finished run. A checkpoint holds the state's params, opt_state and step (host arrays) and the
run's `TrainConfig` as JSON. In a multi-process run every process takes part in each save and
restore (orbax works collectively); only process 0 (`is_primary`) renames files and warns.

Each checkpoint also holds a checksum item: the SHA-256 of the state's leaves (path, dtype,
shape and bytes) as saved. A restore recomputes it from what was read and refuses a checkpoint
whose arrays differ (`ChecksumError`): a flipped byte in an array file can decode to finite but
wrong numbers that no other check sees. A checkpoint whose metadata names the checksum item
but whose checksum is missing or unreadable is refused too (a partial copy would otherwise skip
the check). Checkpoints written before the checksum existed are restored without it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

from lrf_jax.extras import missing_extra

try:
  import orbax.checkpoint as ocp
except ImportError as e:  # the [train] extra
  raise missing_extra(e.name, "train", "training checkpoints (lrf_jax.learning.checkpoints)") from e

from lrf_jax.learning.config import TrainConfig, with_new_defaults
from lrf_jax.learning.train_step import TrainState, create_state


class _QuietOrbax(logging.Filter):
  """Drops orbax's "Requested `tracked_metric`; did not provide metrics." warning: a checkpoint
  saved between validations has no metric by design (it is kept as one of the latest, not
  ranked), so the warning says nothing a user can act on."""

  def filter(self, record: logging.LogRecord) -> bool:
    return "Requested `tracked_metric`" not in record.getMessage()


_QUIET = _QuietOrbax()
logging.getLogger("absl").addFilter(_QUIET)  # orbax logs through absl's logger


def is_primary() -> bool:
  """True in the process that writes the workdir's files and prints (process 0)."""
  return jax.process_index() == 0


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
                               item_names=("state", "config", "checksum"))


class ChecksumError(ValueError):
  """A checkpoint's arrays differ from the checksum saved with them (a corrupt file)."""


def state_checksum(target: Any) -> str:
  """SHA-256 (hex) of a checkpointed state (`_state_target`): each leaf's path, shape and values,
  in tree order. Integer leaves are hashed as int64 (the restore target's step counter may be
  int64 where the trained one is int32); floating leaves in their own dtype, bit for bit."""
  h = hashlib.sha256()
  for path, leaf in jax.tree_util.tree_flatten_with_path(target)[0]:
    a = np.asarray(leaf)
    if not np.issubdtype(a.dtype, np.floating):
      a = a.astype(np.int64)
    h.update(f"{jax.tree_util.keystr(path)}|{a.dtype.str}|{a.shape}|".encode())
    h.update(np.ascontiguousarray(a).tobytes())
  return h.hexdigest()


def _restore_state(mngr: ocp.CheckpointManager, step: int, target: dict[str, Any]) -> dict[str, Any]:
  """The state of checkpoint `step`, verified against its saved checksum (when it has one).

  Raises:
    ChecksumError: the arrays read differ from those saved, or do not decode at all (a corrupt
      compressed chunk: tensorstore's ValueError) where a checksum was saved with them, or the
      checksum is missing or unreadable (the message names the step).
  """
  expected = _saved_checksum(mngr, step)
  try:
    restored = mngr.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(target)))["state"]
  except ValueError as e:
    if expected is None:
      raise
    raise ChecksumError(f"checkpoints/{step}: its arrays do not decode, so they cannot match the "
                        f"checksum saved with them (a corrupt file: {str(e)[:120]})") from None
  if expected is not None and expected != state_checksum(restored):
    raise ChecksumError(f"checkpoints/{step}: its arrays differ from the checksum saved with "
                        "them (a corrupt file)")
  return restored


def _saved_checksum(mngr: ocp.CheckpointManager, step: int) -> str | None:
  """The checksum saved with checkpoint `step`, or None for a checkpoint saved without one (its
  `_CHECKPOINT_METADATA` names no "checksum" item).

  Raises:
    ChecksumError: the metadata names a checksum item that is missing or unreadable.
  """
  step_dir = Path(mngr.directory) / str(step)
  try:
    meta = json.loads((step_dir / "_CHECKPOINT_METADATA").read_text())
    declared = "checksum" in (meta.get("item_handlers") or {})
  except (OSError, ValueError, AttributeError, TypeError):
    declared = False  # unreadable metadata: orbax's own restore reports it
  if not (step_dir / "checksum").is_dir():
    if declared:
      raise ChecksumError(f"checkpoints/{step}: the checksum saved with it is missing (it was "
                          "saved with one)")
    return None
  try:
    saved = mngr.restore(step, args=ocp.args.Composite(
        checksum=ocp.args.JsonRestore()))["checksum"]
  except Exception as e:  # noqa: BLE001 -- orbax raises JSON, Key, Value and OS errors here
    raise ChecksumError(f"checkpoints/{step}: the checksum saved with it is unreadable "
                        f"({type(e).__name__})") from None
  if not isinstance(saved, dict) or not isinstance(saved.get("sha256"), str):
    raise ChecksumError(f"checkpoints/{step}: the checksum saved with it is unreadable (expected "
                        f'{{"sha256": ...}}, found {str(saved)[:60]})')
  return saved["sha256"]


def check_compatible(saved: dict[str, Any], config: TrainConfig, where: Path) -> None:
  """Raise if a checkpoint was written under a config whose parameters differ in shape/meaning."""
  saved = with_new_defaults(saved)
  diffs = [f for f in TrainConfig.MODEL_FIELDS
           if json.dumps(saved.get(f)) != json.dumps(getattr(config, f), default=list)]
  if diffs:
    detail = ", ".join(f"{f}: checkpoint {saved.get(f)!r} vs config {getattr(config, f)!r}"
                       for f in diffs)
    raise ValueError(f"{where}: checkpoint is incompatible with this config ({detail}); use "
                     "another --workdir or the checkpoint's own config")


def restore_params(workdir: str | Path, which: str = "best") -> tuple[Any, TrainConfig]:
  """Parameters and config of a training run's best (or latest) checkpoint (for evaluate.py).

  Raises:
    FileNotFoundError: `workdir` has no checkpoints/ folder, or no checkpoint (for "best": none
      ranked by validation) in it.
    ChecksumError: that checkpoint's arrays differ from its saved checksum (a corrupt file); the
      message names the workdir and the step.
  """
  root = Path(workdir) / "checkpoints"
  if not root.is_dir():
    raise FileNotFoundError(f"{workdir}: not a train.py workdir (no checkpoints/ folder)")
  mngr = checkpoint_manager(Path(workdir), create=False)
  step = mngr.best_step() if which == "best" else mngr.latest_step()
  if step is None:
    what = "ranked by validation (val_pairs=0?)" if which == "best" else "found"
    raise FileNotFoundError(f"{root}: no checkpoint {what}")
  cfg_dict = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
  config = TrainConfig.from_dict({k: tuple(v) if isinstance(v, list) else v
                                  for k, v in cfg_dict.items()})
  try:
    restored = _restore_state(mngr, step, _state_target(create_state(config)))
  except ChecksumError as e:
    raise ChecksumError(f"{workdir}: {e}") from None
  return restored["params"], config


def save_checkpoint(mngr: ocp.CheckpointManager, step: int, state: TrainState,
                    config: TrainConfig, metrics: dict[str, float] | None) -> None:
  """Save `state` and `config` as checkpoint `step` (asynchronously).

  metrics: {"val_meancos": ...} to rank it among the best, or None (kept as one of the latest
  only).
  """
  target = _state_target(state)
  mngr.save(step, args=ocp.args.Composite(
      state=ocp.args.StandardSave(target),
      config=ocp.args.JsonSave(json.loads(config.to_json())),
      checksum=ocp.args.JsonSave({"sha256": state_checksum(target)})), metrics=metrics)


def _state_target(state: TrainState) -> dict[str, Any]:
  """The checkpointed part of a TrainState, as host arrays (the restore target)."""
  return jax.tree.map(np.asarray, {"params": state.params, "opt_state": state.opt_state,
                                   "step": state.step})


def resume(workdir: Path, state: TrainState,
           config: TrainConfig) -> tuple[ocp.CheckpointManager, TrainState]:
  """The run's checkpoint manager, and `state` replaced by its newest readable checkpoint (if
  there is one; see `restore_readable`)."""
  mngr = checkpoint_manager(workdir)
  if mngr.latest_step() is None:
    return mngr, state
  return restore_readable(mngr, state, config, workdir)


def restore_readable(mngr: ocp.CheckpointManager, state: TrainState, config: TrainConfig,
                     workdir: Path) -> tuple[ocp.CheckpointManager, TrainState]:
  """Restore the newest readable checkpoint, newest first.

  An unreadable one (a corrupt file, arrays that differ from the checksum saved with them,
  non-finite parameters) is renamed
  `checkpoints/<step>.unreadable` (`-2`, `-3`, ... when that name is taken; kept, out of the
  way of the steps replayed over it) with one warning naming it. A checkpoint written under an incompatible config is an error, not skipped.
  In a multi-process run process 0 renames and warns, and the others wait for it.

  Returns:
    (manager, state): a new manager when checkpoints were renamed, else `mngr`.

  Raises:
    ValueError: no checkpoint is readable (the message says how to start afresh).
  """
  root = workdir / "checkpoints"
  skipped: list[tuple[int, Exception]] = []
  for step in sorted(mngr.all_steps(), reverse=True):
    damage = visible_damage(root / str(step))
    if damage is not None:  # not handed to orbax: tensorstore's failed reads print tracebacks
      skipped.append((step, ValueError(damage)))
      continue
    try:
      saved = mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    except Exception as e:  # orbax raises JSON, tensorstore, Key and Value errors here
      skipped.append((step, e))
      continue
    check_compatible(saved["config"], config, workdir)
    try:
      restored = _restore_state(mngr, step, _state_target(state))
      bad = nonfinite_leaves(restored["params"])
      if bad:
        raise FloatingPointError(f"non-finite parameters in {bad}")
    except Exception as e:
      skipped.append((step, e))
      continue
    if skipped:
      mngr = _set_aside(mngr, skipped, step, workdir)
    return mngr, state.replace(params=restored["params"], opt_state=restored["opt_state"],
                               step=restored["step"])
  tried = ", ".join(f"{s} ({type(e).__name__}: {str(e).splitlines()[0][:80]})"
                    for s, e in skipped)
  raise ValueError(f"{root}: no readable checkpoint (tried {tried}); delete that folder (or "
                   "choose another --workdir) to start afresh")


def visible_damage(step_dir: Path) -> str | None:
  """What makes a checkpoint folder unreadable at a glance (None: nothing visible).

  Checks, in every item folder, that an OCDBT manifest (`manifest.ocdbt`) is not empty and that
  `_METADATA` and `_CHECKPOINT_METADATA` parse as JSON; a corrupt array file is only found by
  reading it.
  """
  for path in sorted(step_dir.rglob("*")):
    if path.name == "manifest.ocdbt" and path.stat().st_size == 0:
      return f"{path.relative_to(step_dir.parent)}: empty"
    if path.name in ("_METADATA", "_CHECKPOINT_METADATA"):
      try:
        json.loads(path.read_text())
      except (ValueError, UnicodeDecodeError):
        return f"{path.relative_to(step_dir.parent)}: not JSON"
  return None


def _set_aside(mngr: ocp.CheckpointManager, skipped: list[tuple[int, Exception]],
               resumed: int, workdir: Path) -> ocp.CheckpointManager:
  """Rename the `skipped` (step, error) checkpoints to `<step>.unreadable` and warn once (process
  0; the others wait for it); returns a fresh manager over what is left."""
  root = workdir / "checkpoints"
  mngr.close()
  if is_primary():
    kept = []
    for bad_step, _ in skipped:
      kept.append(_free_name(root, f"{bad_step}.unreadable"))
      (root / str(bad_step)).rename(root / kept[-1])
    names = ", ".join(f"checkpoints/{s} ({type(e).__name__})" for s, e in skipped)
    # stacklevel: _set_aside < restore_readable < resume < train_and_evaluate < its caller.
    warnings.warn(f"{names}: unreadable, kept as {', '.join(kept)}; resumed from "
                  f"checkpoints/{resumed}", stacklevel=5)
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices("lrf_jax: unreadable checkpoints renamed")
  return checkpoint_manager(workdir)


def _free_name(root: Path, name: str) -> str:
  """`name`, or `name-2`, `name-3`, ... the first not taken in `root`: a step replayed over a
  set-aside checkpoint can be set aside again (its first copy is kept)."""
  k, out = 1, name
  while (root / out).exists() or (root / out).is_symlink():
    k += 1
    out = f"{name}-{k}"
  return out


def nonfinite_leaves(tree: Any) -> list[str]:
  """Paths of the leaves of `tree` that hold a NaN or an infinity."""
  bad = []
  for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
    if not bool(jnp.all(jnp.isfinite(jnp.asarray(leaf)))):
      bad.append(jax.tree_util.keystr(path))
  return bad
