"""`lrf_jax.learning.checkpoints`: a checkpoint whose checksum is missing or unreadable is not
trusted (a partial copy is never restored unverified), and `resume` sets it aside (twice if need
be, keeping both copies) and resumes from the step before. One smoke training to 12 steps
(`checkpointed`, module-scoped) serves every test here."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def checkpointed(tmp_path_factory):
  from lrf_jax.learning import config as config_lib
  from lrf_jax.learning import train_lib
  cfg = config_lib.replace(config_lib.load_config("smoke"), epochs=2)
  work = tmp_path_factory.mktemp("ck")
  train_lib.train_and_evaluate(cfg, work, progress=False, stop_after_steps=12)
  assert (work / "checkpoints" / "12" / "checksum").is_dir()
  return work


def _damaged(checkpointed: Path, tmp_path: Path, damage) -> Path:
  work = tmp_path / "work"
  shutil.copytree(checkpointed, work)
  damage(work / "checkpoints" / "12")
  return work


def _replace_checksum_by_a_file(step: Path) -> None:
  shutil.rmtree(step / "checksum")
  (step / "checksum").write_text("x")


def _empty_checksum_files(step: Path) -> None:
  for f in (step / "checksum").iterdir():
    if f.is_file():
      f.write_bytes(b"")


@pytest.mark.parametrize("damage, message", [
    (lambda step: shutil.rmtree(step / "checksum"), "checksum saved with it is missing"),
    (_replace_checksum_by_a_file, "checksum saved with it is missing"),
    (_empty_checksum_files, "checksum saved with it is unreadable"),
])
def test_a_checkpoint_whose_checksum_is_gone_is_not_trusted(checkpointed, tmp_path, damage,
                                                           message):
  """Before: a checkpoint without its checksum folder (a partial copy) was restored unverified,
  and an unreadable checksum raised a bare JSONDecodeError."""
  from lrf_jax.learning import checkpoints
  work = _damaged(checkpointed, tmp_path, damage)
  with pytest.raises(checkpoints.ChecksumError, match=rf"checkpoints/12: .*{message}"):
    checkpoints.restore_params(work, "latest")


def test_resume_sets_aside_a_checkpoint_whose_checksum_is_gone(checkpointed, tmp_path, smoke):
  from lrf_jax.learning import checkpoints, train_step
  work = _damaged(checkpointed, tmp_path, lambda step: shutil.rmtree(step / "checksum"))
  cfg = _smoke2(smoke)
  with pytest.warns(UserWarning, match=r"checkpoints/12 \(ChecksumError\).*resumed from "
                                       r"checkpoints/8"):
    mngr, state = checkpoints.resume(work, train_step.create_state(cfg), cfg)
  mngr.close()
  assert int(state.step) == 8 and (work / "checkpoints" / "12.unreadable").is_dir()


@pytest.fixture(scope="module")
def smoke():
  from lrf_jax.learning import config as config_lib
  return config_lib.load_config("smoke")


def _smoke2(smoke):
  from lrf_jax.learning import config as config_lib
  return config_lib.replace(smoke, epochs=2)


def test_a_step_set_aside_twice_keeps_both_copies(checkpointed, tmp_path, smoke):
  """Before: a step replayed over a set-aside checkpoint and corrupted again could not be set
  aside (`OSError: Directory not empty: checkpoints/12 -> checkpoints/12.unreadable`): the run
  could not resume at all."""
  from lrf_jax.learning import checkpoints, train_step

  def again(step: Path) -> None:
    shutil.copytree(step, step.parent / "12.unreadable")  # the first time it was set aside
    shutil.rmtree(step / "checksum")
  work = _damaged(checkpointed, tmp_path, again)
  cfg = _smoke2(smoke)
  with pytest.warns(UserWarning, match=r"kept as 12\.unreadable-2; resumed from checkpoints/8"):
    mngr, state = checkpoints.resume(work, train_step.create_state(cfg), cfg)
  mngr.close()
  assert int(state.step) == 8
  assert {"12.unreadable", "12.unreadable-2"} <= {p.name for p in (work / "checkpoints").iterdir()}
