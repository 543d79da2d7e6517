"""Training: the smoke config learns, resumes exactly, shards, and rejects bad configs; train.py's
bad configs and arguments are one `error:` line and exit code 2 before any work; the workdir's
lock refuses a link or a FIFO; a failed write keeps the old file."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lrf_jax.learning import config as config_lib
from lrf_jax.learning import checkpoints
from lrf_jax.learning import data_sources
from lrf_jax.learning import train_lib
from lrf_jax.learning import train_step
from lrf_jax.learning.batches import BatchMaker, crop_patches
from lrf_jax.learning.losses import siamese_loss
from lrf_jax.frames.weights import load_params
from lrf_jax.io import atomic
from tests.lrf_testing import assert_only_files, cli_error, full_disk_midway

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import train  # noqa: E402


@pytest.fixture(scope="module")
def smoke():
  return config_lib.load_config("smoke")


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory, smoke):
  workdir = tmp_path_factory.mktemp("smoke")
  final = train_lib.train_and_evaluate(smoke, workdir, progress=False)
  return workdir, final


def test_smoke_trains_and_loss_falls(smoke_run, smoke):
  workdir, final = smoke_run
  maker = BatchMaker(data_sources.training_clouds(smoke), smoke)
  batches = [jax.tree.map(jnp.asarray, maker.batch(0, i)) for i in range(4)]
  loss = jax.jit(lambda p, b: siamese_loss(p, b.model, b.scene)[0])
  before = np.mean([loss(train_step.create_state(smoke).params, b) for b in batches])
  after = np.mean([loss(load_params(workdir / "final_params.msgpack"), b) for b in batches])
  assert after < 0.98 * before, (before, after)
  rows = [json.loads(l) for l in (workdir / "metrics.jsonl").read_text().splitlines()]
  assert rows[-1]["step"] == smoke.total_steps
  assert all(np.isfinite(r["loss"]) and r["grad_norm"] > 0 for r in rows)
  lrs = [r["lr"] for r in rows]
  np.testing.assert_allclose(max(lrs) / min(lrs), smoke.lr_decay ** -(smoke.epochs - 1), rtol=1e-5)
  assert sum("val_meancos" in r for r in rows) == smoke.epochs
  assert (workdir / "curves.png").stat().st_size > 1000
  assert (workdir / "best_params.msgpack").exists()


@pytest.mark.slow
def test_killed_run_resumes_to_the_same_state(tmp_path, smoke):
  cfg = config_lib.replace(smoke, epochs=2)
  full = train_lib.train_and_evaluate(cfg, tmp_path / "a", progress=False)
  train_lib.train_and_evaluate(cfg, tmp_path / "b", progress=False, stop_after_steps=11)
  assert not (tmp_path / "b" / "final_params.msgpack").exists()
  resumed = train_lib.train_and_evaluate(cfg, tmp_path / "b", progress=False)
  assert resumed["step"] == full["step"] == cfg.total_steps
  pa = load_params(tmp_path / "a" / "final_params.msgpack")
  pb = load_params(tmp_path / "b" / "final_params.msgpack")
  for x, y in zip(jax.tree.leaves(pa), jax.tree.leaves(pb)):
    np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(resumed["loss"], full["loss"], rtol=1e-6)


def test_restore_params_for_evaluation(smoke_run, smoke):
  workdir, _ = smoke_run
  params, cfg = checkpoints.restore_params(workdir, "latest")
  assert cfg == smoke
  final = load_params(workdir / "final_params.msgpack")
  for x, y in zip(jax.tree.leaves(params), jax.tree.leaves(final)):
    np.testing.assert_array_equal(x, y)


def test_incompatible_checkpoint_is_refused(smoke_run, smoke):
  workdir, _ = smoke_run
  other = config_lib.replace(smoke, widths=(8, 16), epochs=smoke.epochs + 1)
  with pytest.raises(ValueError, match="incompatible.*widths"):
    train_lib.train_and_evaluate(other, workdir, progress=False)


def test_mistyped_config_key_is_refused(smoke):
  with pytest.raises(ValueError, match="unknown key.*'epoch'.*valid keys"):
    config_lib.replace(smoke, epoch=3)
  with pytest.raises(ValueError, match="key=value"):
    config_lib.parse_overrides(["epochs"])
  with pytest.raises(ValueError, match="no such preset"):
    config_lib.load_config("defualt")
  with pytest.raises(ValueError, match="loss_reduction"):
    config_lib.replace(smoke, loss_reduction="mean")


def test_overrides_are_typed(smoke):
  cfg = config_lib.replace(smoke, **config_lib.parse_overrides(
      ["epochs=2", "learning_rate=0.5", "noise_mr=0.1,0.3", "widths=8,16"]))
  assert cfg.epochs == 2 and cfg.learning_rate == 0.5
  assert cfg.noise_mr == (0.1, 0.3) and cfg.widths == (8, 16)


def _train_in_subprocess(workdir: Path, devices: int) -> list[dict]:
  env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
             JAX_PLATFORMS="cpu")
  subprocess.run([sys.executable, str(REPO / "train.py"), "--config", "smoke", "--workdir",
                  str(workdir), "--no-progress", "epochs=1", "val_pairs=0", "log_every=1"],
                 check=True, env=env, cwd=REPO, capture_output=True)
  return [json.loads(l) for l in (workdir / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_four_devices_give_the_same_loss_as_one(tmp_path):
  """The batch is sharded over 4 devices: the loss and gradient of a step are the same numbers.

  Only the first step is compared tightly: the reductions run in another order, and Adam's
  first updates are about lr * sign(g), so components of g near 0 amplify float rounding into
  visibly different trajectories after a few steps (also between two 1-device runs with a
  different reduction order); later steps are checked loosely.
  """
  one = _train_in_subprocess(tmp_path / "one", 1)
  four = _train_in_subprocess(tmp_path / "four", 4)
  assert len(one) == len(four) == 16
  np.testing.assert_allclose(four[0]["loss"], one[0]["loss"], rtol=1e-5)
  np.testing.assert_allclose(four[0]["grad_norm"], one[0]["grad_norm"], rtol=1e-4)
  np.testing.assert_allclose([r["loss"] for r in four], [r["loss"] for r in one], rtol=0.2)


def test_epoch_patches_reusing_last_epochs_stats_equal_a_fresh_makers(smoke):
  # A maker that built epoch 0 reuses each unperturbed cloud's counts and r/3 statistics for
  # later epochs; a fresh maker computes them: the same patches. Noise of 0 or 0.5 mr on the
  # scene side: clouds drawn with noise are searched afresh, the others reuse.
  cfg = config_lib.replace(smoke, noise_mr=(0.0, 0.5))
  clouds = data_sources.training_clouds(cfg)
  warm = BatchMaker(clouds, cfg)
  warm.epoch_patches(0)
  levels = set()
  for epoch in (1, 2, 3):
    levels |= {warm.noise_level(epoch, c) for c in range(len(clouds.models))}
    got = warm.epoch_patches(epoch)
    ref = BatchMaker(clouds, cfg).epoch_patches(epoch)
    for side in (0, 1):
      for a, b in zip(got[side], ref[side]):
        np.testing.assert_array_equal(a, b)
  assert levels == {0.0, 0.5}
  assert {side for side, _ in warm._stats} == {0, 1}
  assert all(s.offsets is None for s in warm._stats.values())


def test_crop_augmentation_cuts_by_a_plane():
  from lrf_jax.search.neighborhoods import build_patches

  rng = np.random.default_rng(0)
  pts = rng.normal(size=(4000, 3)) * [1.0, 1.0, 0.05]
  patches = build_patches(pts, np.arange(0, 4000, 40), 0.8, 64)
  same = crop_patches(patches, 0.0, 0.3, np.random.default_rng(1))
  for a, b in zip(same, patches):
    np.testing.assert_array_equal(a, b)
  cut = crop_patches(patches, 1.0, 0.3, np.random.default_rng(1))
  lost = patches.mask & ~cut.mask
  assert lost.any(axis=1).mean() > 0.5  # most patches lose a side
  assert not (cut.mask & ~patches.mask).any()  # nothing is added
  # The kept offsets are the original ones, dropped slots are clean padding, and no neighbor
  # closer than crop_min * r is ever dropped (the plane lies at least that far).
  np.testing.assert_array_equal(cut.offsets[cut.mask], patches.offsets[cut.mask])
  assert (cut.offsets[lost] == 0).all() and (cut.indices[lost] == -1).all()
  assert np.linalg.norm(patches.offsets[lost], axis=-1).min() > 0.3 * 0.8
  again = crop_patches(patches, 1.0, 0.3, np.random.default_rng(1))
  np.testing.assert_array_equal(again.mask, cut.mask)  # seeded
  with pytest.raises(ValueError, match="crop"):
    config_lib.replace(config_lib.TrainConfig(), crop_p=1.5)


def test_diverging_run_stops_without_saving_nonfinite_params(tmp_path, capsys):
  """learning_rate=1e30: the loss reads 0 once every frame is invalid, but the gradient norm,
  the valid fraction and the parameters give it away; no params file is written."""
  sys.path.insert(0, str(REPO))
  import train
  rc = train.main(["--config", "smoke", "--workdir", str(tmp_path), "--no-progress",
                   "learning_rate=1e30", "epochs=1"])
  err = capsys.readouterr().err
  assert rc == 1
  assert err.startswith("error: step ") and ("non-finite" in err or "valid fraction 0" in err)
  assert not (tmp_path / "final_params.msgpack").exists()
  assert not (tmp_path / "best_params.msgpack").exists()
  if any((tmp_path / "checkpoints").glob("[0-9]*")):
    params, _ = checkpoints.restore_params(tmp_path, "latest")
    assert not checkpoints.nonfinite_leaves(params)


@pytest.mark.slow
def test_resumed_run_logs_each_step_once(tmp_path, smoke):
  cfg = config_lib.replace(smoke, epochs=2)
  import shutil
  train_lib.train_and_evaluate(cfg, tmp_path, progress=False, stop_after_steps=12)
  # A kill during step 12's checkpoint write (after its log line): the run resumes from step 8
  # and replays steps 9-12.
  shutil.rmtree(tmp_path / "checkpoints" / "12")
  train_lib.train_and_evaluate(cfg, tmp_path, progress=False)
  steps = [json.loads(line)["step"] for line in (tmp_path / "metrics.jsonl").open()]
  assert steps == sorted(set(steps)), steps
  assert steps[-1] == cfg.total_steps


@pytest.mark.parametrize("override,key", [("epochs=two", "config.epochs"),
                                          ("seed=1e3", "config.seed"),
                                          ("log_every=0", "config.log_every"),
                                          ("radius_mr=-5", "config.radius_mr"),
                                          ("learning_rate=nan", "config.learning_rate"),
                                          ("noise_mr=0.1,x", "config.noise_mr"),
                                          ("epoch=3", "unknown key")])
def test_bad_override_is_a_clean_error_naming_the_key(override, key, tmp_path, capsys):
  sys.path.insert(0, str(REPO))
  import train
  rc = train.main(["--config", "smoke", "--workdir", str(tmp_path), "--no-progress", override])
  err = capsys.readouterr().err
  assert rc == 2 and err.startswith("error: ") and key in err, err
  assert "Traceback" not in err and not any(tmp_path.iterdir())


@pytest.mark.slow
@pytest.mark.parametrize("damaged", ["_METADATA", "manifest.ocdbt"])
def test_corrupt_latest_checkpoint_falls_back_to_the_previous_one(tmp_path, smoke, damaged,
                                                                   capfd):
  cfg = config_lib.replace(smoke, epochs=2)
  train_lib.train_and_evaluate(cfg, tmp_path, progress=False, stop_after_steps=12)
  steps = sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir() if p.name.isdigit())
  assert steps[-2:] == [8, 12], steps  # the latest two are kept
  (tmp_path / "checkpoints" / "12" / "state" / damaged).write_bytes(b"")
  capfd.readouterr()
  with pytest.warns(UserWarning, match=r"checkpoints/12 .*resumed from checkpoints/8"):
    final = train_lib.train_and_evaluate(cfg, tmp_path, progress=False)
  err = capfd.readouterr().err
  assert "Traceback" not in err and "Event loop is closed" not in err, err[:2000]
  assert final["step"] == cfg.total_steps
  assert (tmp_path / "checkpoints" / "12.unreadable").is_dir()
  assert not checkpoints.nonfinite_leaves(load_params(tmp_path / "final_params.msgpack"))


def test_no_readable_checkpoint_is_one_clean_error(tmp_path, smoke, capsys):
  cfg = config_lib.replace(smoke, epochs=2)
  train_lib.train_and_evaluate(cfg, tmp_path, progress=False, stop_after_steps=12)
  for p in (tmp_path / "checkpoints").iterdir():
    if p.name.isdigit():
      (p / "state" / "_METADATA").write_bytes(b"")
      (p / "config" / "metadata").write_bytes(b"") if (p / "config" / "metadata").exists() else None
  sys.path.insert(0, str(REPO))
  import train
  rc = train.main(["--config", "smoke", "--workdir", str(tmp_path), "--no-progress", "epochs=2"])
  err = capsys.readouterr().err
  assert rc == 2 and "no readable checkpoint" in err and "start afresh" in err, err


def test_validate_traces_its_frames_function_once(smoke, monkeypatch):
  """The frames function is jitted once per validation set: a second call (same shapes) reuses
  the compiled code instead of tracing again."""
  traces = []

  def counting_frames_fn(config):
    fn = train_step.frames_fn(config)

    def traced(params, patches):
      traces.append(patches.offsets.shape)  # runs only while tracing
      return fn(params, patches)

    return traced

  monkeypatch.setattr(train_lib, "frames_fn", counting_frames_fn)
  cfg = config_lib.replace(smoke, val_pairs=2, val_keypoints=20)
  val = train_lib.build_validation(data_sources.validation_pairs(cfg), cfg)
  params = train_step.create_state(cfg).params
  first = train_lib.validate(params, val)
  second = train_lib.validate(params, val)
  assert len(val.names) == 2 and len(traces) == 1, traces  # 2 pairs x 2 sides, one shape
  assert val.frames._cache_size() == 1
  assert first == second and np.isfinite(first["val_meancos"])


def test_learning_rate_schedule_is_built_once_per_run(tmp_path, smoke, monkeypatch):
  """The optimiser and the logged lr share the one schedule kept on the state."""
  built = []
  real = train_step.learning_rate_schedule
  monkeypatch.setattr(train_step, "learning_rate_schedule",
                      lambda config: built.append(config) or real(config))
  cfg = config_lib.replace(smoke, val_pairs=0, log_every=1)
  final = train_lib.train_and_evaluate(cfg, tmp_path, progress=False, stop_after_steps=1)
  assert len(built) == 1
  state = train_step.create_state(cfg)
  assert final["lr"] == float(state.lr_schedule(0)) == pytest.approx(cfg.learning_rate)


@pytest.mark.slow
def test_smoke_run_tells_the_user_what_it_does_and_hides_orbax_noise(tmp_path, smoke, capfd,
                                                                     caplog, monkeypatch):
  """A stopped and restarted smoke run: the bar never shows "nan" (no validation yet), the
  restart says where it resumes, orbax's tracked_metric warning is not shown, curves.png is
  titled from the config, and train.py ends with the paths it wrote."""
  import logging

  import train
  cfg = config_lib.replace(smoke, epochs=1)
  caplog.set_level(logging.WARNING)
  titles = []
  real_plot = train_lib.plot_curves
  monkeypatch.setattr(train_lib, "plot_curves",
                      lambda log, out, title="": titles.append(title) or real_plot(log, out,
                                                                                    title))
  train_lib.train_and_evaluate(cfg, tmp_path, progress=True, stop_after_steps=9)
  first = capfd.readouterr().err
  assert "loss=" in first and "nan" not in first  # checkpoint 8 has no validation metric
  assert train.main(["--config", "smoke", "--workdir", str(tmp_path), "epochs=1"]) == 0
  out = capfd.readouterr()
  assert f"resuming from step 9 of {cfg.total_steps} ({tmp_path})" in out.err
  assert "nan" not in out.err.split("val=")[0]
  for text in (first, out.err, out.out, caplog.text):
    assert "tracked_metric" not in text
  assert titles and "demo" in titles[-1] and "smoke" in titles[-1]
  wrote = out.out.strip().splitlines()[-1]
  assert wrote.startswith("wrote ")
  for name in ("checkpoints", "config.json", "metrics.jsonl", "curves.png",
               "final_params.msgpack", "best_params.msgpack"):
    assert str(tmp_path / name) in wrote
  assert "{" not in out.out  # no raw dict


def _flip_bytes_in_largest_file(step_dir: Path) -> Path:
  """16 bytes flipped at 10 % of the largest file of a checkpoint (a corrupt array file that
  still decodes)."""
  largest = max((p for p in step_dir.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
  data = bytearray(largest.read_bytes())
  at = len(data) // 10
  data[at:at + 16] = bytes(b ^ 0xFF for b in data[at:at + 16])
  largest.write_bytes(bytes(data))
  return largest


def test_checkpoint_with_flipped_bytes_is_set_aside_and_named(tmp_path, smoke, capfd):
  """A checkpoint whose array file was corrupted (finite but wrong numbers can decode) fails its
  checksum: the run resumes from the previous one, names it, and `restore_params` raises."""
  cfg = config_lib.replace(smoke, epochs=2)
  train_lib.train_and_evaluate(cfg, tmp_path, progress=False, stop_after_steps=12)
  assert (tmp_path / "checkpoints" / "12" / "checksum").is_dir()
  _flip_bytes_in_largest_file(tmp_path / "checkpoints" / "12" / "state")
  with pytest.raises(checkpoints.ChecksumError, match=r"checkpoints/12\b.*checksum"):
    checkpoints.restore_params(tmp_path, "latest")
  capfd.readouterr()
  with pytest.warns(UserWarning, match=r"checkpoints/12 \(ChecksumError\).*resumed from "
                                       r"checkpoints/8"):
    final = train_lib.train_and_evaluate(cfg, tmp_path, progress=False)
  err = capfd.readouterr().err
  assert "resuming from step 8 " in err and "Traceback" not in err, err[:2000]
  assert final["step"] == cfg.total_steps
  assert (tmp_path / "checkpoints" / "12.unreadable").is_dir()
  params = load_params(tmp_path / "final_params.msgpack")
  assert max(float(np.abs(x).max()) for x in jax.tree.leaves(params)) < 1e3


def test_checkpoint_whose_arrays_do_not_decode_is_set_aside_and_named(tmp_path, smoke):
  """Corrupt bytes that break the array file's compression (not only its numbers) are the same
  corrupt checkpoint: `restore_params` raises ChecksumError naming the step."""
  cfg = config_lib.replace(smoke, epochs=2)
  train_lib.train_and_evaluate(cfg, tmp_path, progress=False, stop_after_steps=12)
  for path in (tmp_path / "checkpoints" / "12" / "state").rglob("*"):
    if path.is_file() and path.stat().st_size > 4096 and path.parent.name == "d":
      data = bytearray(path.read_bytes())
      data[len(data) // 2:] = bytes(len(data) - len(data) // 2)  # the second half zeroed
      path.write_bytes(bytes(data))
  with pytest.raises(checkpoints.ChecksumError, match=r"checkpoints/12\b.*checksum"):
    checkpoints.restore_params(tmp_path, "latest")


def test_state_checksum_sees_one_changed_element(smoke):
  state = jax.tree.map(np.array, checkpoints._state_target(train_step.create_state(smoke)))
  before = checkpoints.state_checksum(state)
  assert checkpoints.state_checksum(jax.tree.map(np.copy, state)) == before
  leaf = jax.tree.leaves(state["params"])[0]
  leaf.reshape(-1)[0] += 1
  assert checkpoints.state_checksum(state) != before


def test_second_run_in_a_locked_workdir_is_one_error_naming_the_holder(tmp_path, capsys):
  """Two train.py in one workdir: the second stops before any work (exit 2, one error: line
  naming the workdir and the holder's pid)."""
  holder = subprocess.Popen(
      [sys.executable, "-c", "import sys, time; from pathlib import Path; "
       "from lrf_jax.learning.train_lib import workdir_lock\n"
       "with workdir_lock(Path(sys.argv[1])):\n  print('locked', flush=True); time.sleep(600)",
       str(tmp_path)], stdout=subprocess.PIPE, text=True, cwd=REPO,
      env={**os.environ, "PYTHONPATH": os.pathsep.join(
          [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])})
  try:
    assert holder.stdout.readline().strip() == "locked"
    sys.path.insert(0, str(REPO))
    import train
    rc = train.main(["--config", "smoke", "--workdir", str(tmp_path), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert str(tmp_path) in err and f"pid {holder.pid}" in err, err
    assert not (tmp_path / "metrics.jsonl").exists() and not (tmp_path / "checkpoints").exists()
  finally:
    holder.kill()
    holder.wait()


def test_stale_workdir_lock_is_taken_over(tmp_path):
  dead = subprocess.Popen([sys.executable, "-c", "pass"])
  dead.wait()
  (tmp_path / train_lib.LOCK_FILE).write_text(f"{dead.pid}\n")
  with train_lib.workdir_lock(tmp_path):
    assert (tmp_path / train_lib.LOCK_FILE).read_text() == f"{os.getpid()}\n"
    with pytest.raises(train_lib.WorkdirLockedError, match=rf"pid {os.getpid()}\b"):
      with train_lib.workdir_lock(tmp_path):
        pass
  assert not (tmp_path / train_lib.LOCK_FILE).exists()  # removed at the end of the block
  with train_lib.workdir_lock(tmp_path):  # and free again
    pass


# --------------------------- train.py's bad configs and arguments (in-process, before any work)


@pytest.mark.parametrize("name,text,fragment", [
    ("noise.json", '{"noise_mr": 0.1}', "config.noise_mr"),
    ("widths.json", '{"widths": 16}', "config.widths"),
    ("list.json", "[1, 2]", "expected an object"),
    ("lr.json", '{"learning_rate": true}', "config.learning_rate"),
    ("radius.json", '{"radius_mr": true}', "config.radius_mr"),
    ("decay.json", '{"lr_decay": true}', "config.lr_decay"),
    ("crop.json", '{"crop_p": true}', "config.crop_p"),
    ("name.json", '{"name": 3}', "config.name"),
    ("syntax.json", '{"epochs": 2,', "syntax.json"),
    ("nofn.py", "x = 1\n", "get_config"),
    ("dict.py", "def get_config():\n  return {'epochs': 1}\n", "TrainConfig"),
    ("raises.py", "import nosuchmodule\n", "raises.py"),
])
def test_train_bad_config_file(tmp_path, capsys, name, text, fragment):
  path = tmp_path / name
  path.write_text(text)
  work = tmp_path / "run"
  assert train.main(["--config", str(path), "--workdir", str(work), "--no-progress"]) == 2
  err = cli_error(capsys)
  assert fragment in err, err
  assert not work.exists()


def test_train_config_folder_and_workdir_file(tmp_path, capsys):
  (tmp_path / "dir.json").mkdir()
  assert train.main(["--config", str(tmp_path / "dir.json"), "--workdir",
                     str(tmp_path / "run")]) == 2
  assert "dir.json" in cli_error(capsys)
  (tmp_path / "afile").write_text("mine")
  assert train.main(["--config", "smoke", "--workdir", str(tmp_path / "afile")]) == 2
  assert "--workdir" in cli_error(capsys)
  assert (tmp_path / "afile").read_text() == "mine"


def test_train_batch_larger_than_the_training_set(tmp_path, capsys):
  """batch_size=2048 with 1,024 training keypoints trained on batches of 1,024 before."""
  assert train.main(["--config", "smoke", "--workdir", str(tmp_path / "run"),
                     "batch_size=2048"]) == 2
  err = cli_error(capsys)
  assert "config.batch_size" in err and "1024" in err
  with pytest.raises(ValueError, match="config.batch_size"):
    config_lib.TrainConfig(num_train_keypoints=100, batch_size=101)


def test_train_resume_under_another_config_is_refused(tmp_path, capsys):
  """A finished run resumed with other values ran with rc 0 and overwrote config.json."""
  smoke = config_lib.load_config("smoke")
  work = tmp_path / "run"
  work.mkdir()
  (work / "config.json").write_text(smoke.to_json())
  (work / "metrics.jsonl").write_text('{"step": 48, "loss": 0.1}\n')
  before = {p: p.read_bytes() for p in work.iterdir()}
  assert train.main(["--config", "smoke", "--workdir", str(work), "--no-progress", "epochs=3",
                     "batch_size=16", "learning_rate=0.1", "seed=5"]) == 2
  err = cli_error(capsys)
  for field in ("batch_size", "learning_rate", "seed"):
    assert field in err, err
  assert "--replace-config" in err
  assert {p: p.read_bytes() for p in work.iterdir()} == before


def test_train_replace_config_keeps_both(tmp_path):
  smoke = config_lib.load_config("smoke")
  other = config_lib.replace(smoke, learning_rate=0.1)
  work = tmp_path / "run"
  work.mkdir()
  (work / "config.json").write_text(smoke.to_json())
  (work / "metrics.jsonl").write_text('{"step": 8, "loss": 0.1}\n{"step": 12, "loss"')  # torn
  assert train_lib.resume_config(work, smoke) is None  # the same config: resume
  with pytest.raises(ValueError, match="learning_rate: saved 0.003 vs requested 0.1"):
    train_lib.resume_config(work, other)
  name = train_lib.resume_config(work, other, replace=True)
  assert name == "config.1.json"
  train_lib._Log(work, other, 8, other.total_steps, False, name).close()
  assert config_lib.TrainConfig.from_dict(json.loads((work / "config.json").read_text())) == smoke
  assert json.loads((work / "config.1.json").read_text())["learning_rate"] == 0.1
  rows = [json.loads(line) for line in (work / "metrics.jsonl").read_text().splitlines()]
  assert rows[0] == {"step": 8, "loss": 0.1} and "config.1.json" in rows[1]["note"]
  assert len(rows) == 2  # the torn line is gone
  assert train_lib.resume_config(work, other) is None  # now compared with config.1.json
  with pytest.raises(ValueError, match="config.1.json"):
    train_lib.resume_config(work, smoke)


def test_train_resume_with_other_model_fields_is_incompatible(tmp_path):
  smoke = config_lib.load_config("smoke")
  work = tmp_path / "run"
  (work / "checkpoints" / "8").mkdir(parents=True)
  (work / "config.json").write_text(smoke.to_json())
  with pytest.raises(ValueError, match="incompatible.*widths"):
    train_lib.resume_config(work, config_lib.replace(smoke, widths=(8,)), replace=True)


def _batch(z_count: int, count: int):
  from lrf_jax.learning.batches import Batch
  from lrf_jax.search.neighborhoods import Patches
  n, k = 8, 4
  p = Patches(np.zeros((n, k, 3), np.float32), np.ones((n, k), bool), np.zeros((n, k), np.int32),
              np.full(n, count, np.int32), np.ones(n, np.float32), np.zeros((n, 3, 3), np.float32),
              np.zeros((n, 3), np.float32), np.full(n, z_count, np.int32))
  return Batch(p, p)


def test_all_invalid_frames_blame_the_support_when_patches_are_too_small():
  """radius_mr=1: every frame invalid was blamed on the learning rate ("diverged"); the patches
  hold a median of 1 point within r/3, where the z axis needs 3."""
  m = {"loss": 0.0, "grad_norm": 0.0, "valid_fraction": 0.0}
  with pytest.raises(FloatingPointError, match="support is too small.*raise radius_mr") as e:
    train_lib.check_finite(m, {}, 4, 0, _batch(z_count=1, count=4))
  assert "learning rate" not in str(e.value)
  with pytest.raises(FloatingPointError, match="lower the learning rate"):
    train_lib.check_finite(m, {}, 4, 0, _batch(z_count=40, count=200))


# --------------------------------------------------------------------------- the workdir's lock


def test_a_symlinked_train_lock_never_truncates_its_target(tmp_path):
  """Before: `train.lock -> ~/precious` was opened through the link, truncated and overwritten
  with the pid."""
  from lrf_jax.learning import train_lib
  victim = tmp_path / "precious.txt"
  victim.write_text("precious data\n")
  work = tmp_path / "work"
  work.mkdir()
  (work / train_lib.LOCK_FILE).symlink_to(victim)
  with pytest.raises(ValueError, match="not a regular file"):
    with train_lib.workdir_lock(work):
      pass
  assert victim.read_text() == "precious data\n"
  assert (work / train_lib.LOCK_FILE).is_symlink()  # left as it was


def test_a_fifo_train_lock_is_refused_and_left_alone(tmp_path):
  from lrf_jax.learning import train_lib
  os.mkfifo(tmp_path / train_lib.LOCK_FILE)
  with pytest.raises(ValueError, match="not a regular file"):
    with train_lib.workdir_lock(tmp_path):
      pass
  assert (tmp_path / train_lib.LOCK_FILE).exists()


# --------------------------------------------- writes that fail (a full disk) keep the old file


def test_params_on_a_full_disk_keep_the_old_file(tmp_path, monkeypatch):
  """train.py on a full disk: a traceback and a truncated best_params.msgpack."""
  params = {"enc0": {"kernel": np.ones((2, 16), np.float32), "bias": np.zeros(16, np.float32)}}
  path = tmp_path / "best_params.msgpack"
  train_lib._save_params(params, path)
  good = path.read_bytes()
  def half_written(p, tmp):
    with open(tmp, "wb") as f:
      full_disk_midway(f)
  monkeypatch.setattr(train_lib, "save_params", half_written)
  with pytest.raises(atomic.WriteError, match="best_params.msgpack: No space left"):
    train_lib._save_params(params, path)
  assert path.read_bytes() == good
  assert_only_files(tmp_path, "best_params.msgpack")


def test_curves_skip_notes_and_torn_lines(tmp_path):
  log = tmp_path / "metrics.jsonl"
  log.write_text('{"step": 4, "loss": 1.0}\n{"step": 4, "note": "config replaced"}\n'
                 '{"step": 8, "loss": 0.5, "epoch": 1.0, "val_meancos": 0.5}\n{"step": 9, "lo')
  train_lib.plot_curves(log, tmp_path / "curves.png")
  assert (tmp_path / "curves.png").stat().st_size > 1000
  train_lib._trim_log(log, 8)
  assert [json.loads(l)["step"] for l in log.read_text().splitlines()] == [4, 4, 8]
  assert_only_files(tmp_path, "metrics.jsonl", "curves.png")
