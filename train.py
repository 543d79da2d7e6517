"""Train LRF-Net.

    python train.py --config default --workdir runs/default            # the paper (needs LRF_DATA)
    python train.py --config smoke --workdir /tmp/smoke epochs=2       # CPU, about a minute
    python train.py --config default --workdir runs/x batch_size=256 noise_mr=0.1,0.3
    python train.py --config default --workdir runs/mine scans=my_sweeps/       # your own scans
    python train.py --config default --workdir runs/mix data=br+scans scans=a/,b/  # b/ validates
    python train.py --config default --workdir /shared/runs/x \
        --coordinator HOST0:1234 --num-processes N --process-id I     # on each of N hosts

Overrides are `key=value` fields of `lrf_jax.learning.config.TrainConfig`; `scans=DIR[,DIR...]`
(folders of scans with a poses.txt, gt.log or .conf: docs/own_scans.md) trains on their
overlapping pairs, alone or with `data=br+scans` beside BR. A run restarted with the same
--workdir resumes from its latest checkpoint, under the same config: another config is an
error naming the fields that differ, unless --replace-config (config.json is kept, the new
config is written as config.<n>.json and noted in metrics.jsonl). One run at a time holds a
workdir (`train.lock`): a second run there is refused, naming the first one's pid. Every bad argument, config or
unwritable file is one `error:` line and exit code 2 (1: the run diverged). With --coordinator, the processes join one
`jax.distributed` job (gloo collectives on CPU), the batch is split over the devices of all of
them, the workdir must be shared, and only process 0 prints and writes files besides the
checkpoints. This file is intentionally kept short; the loop lives in lrf_jax/learning/train_lib.py.
"""

import argparse
import os
import sys
from pathlib import Path

from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.cli.help import DefaultsHelpFormatter
from lrf_jax.extras import MissingExtraError
from lrf_jax.learning import config as config_lib


def build_parser() -> argparse.ArgumentParser:
  """train.py's options (each default shown by --help, the presets listed)."""
  presets = ", ".join(config_lib.preset_names())
  ap = argparse.ArgumentParser(
      description="Train LRF-Net (weakly supervised, Chamfer loss). Writes checkpoints/, "
                  "config.json, metrics.jsonl, curves.png, final_params.msgpack and "
                  "best_params.msgpack to --workdir.",
      epilog=f"config presets (lrf_jax/learning/configs/NAME.py): {presets}",
      formatter_class=DefaultsHelpFormatter)
  ap.add_argument("--config", default="default",
                  help=f"preset name ({presets}) or path (.py / .json)")
  ap.add_argument("--workdir", default=None, help="output folder (default: runs/<config name>)")
  ap.add_argument("--no-progress", action="store_true", help="no progress bar")
  ap.add_argument("--replace-config", action="store_true",
                  help="resume a run started under another config: keep its config.json, "
                       "record the new one as config.<n>.json and continue")
  ap.add_argument("--coordinator", default=None,
                  help="multi-host: coordinator address host:port (jax.distributed)")
  ap.add_argument("--num-processes", type=int, default=None,
                  help="multi-host: number of processes of the job (with --coordinator)")
  ap.add_argument("--process-id", type=int, default=None,
                  help="multi-host: this process's index in [0, N) (with --coordinator)")
  ap.add_argument("overrides", nargs="*", help="key=value config overrides")
  return ap


@interruptible("the checkpoints saved so far are kept; the same command resumes")
def main(argv=None) -> int:
  args = build_parser().parse_args(argv)
  try:
    config = config_lib.replace(config_lib.load_config(args.config),
                                **config_lib.parse_overrides(args.overrides))
  except ValueError as e:  # a bad preset or override: name it, no traceback
    print(f"error: {e}", file=sys.stderr)
    return 2
  if not args.coordinator and (args.num_processes is not None or args.process_id is not None):
    print("error: --num-processes and --process-id need --coordinator host:port",
          file=sys.stderr)
    return 2
  if args.coordinator:
    import jax
    # CPU devices of different processes talk through gloo (no effect on GPU or TPU devices).
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
  try:  # flax, optax, orbax: the [train] extra
    from lrf_jax.learning import checkpoints, train_lib
  except MissingExtraError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  workdir = args.workdir or f"runs/{config.name}"
  problem = _check_workdir(Path(workdir), args.config)
  if problem:
    print(f"error: {problem}", file=sys.stderr)
    return 2
  try:
    final = train_lib.train_and_evaluate(config, workdir, progress=not args.no_progress,
                                         replace_config=args.replace_config)
  except FloatingPointError as e:  # diverged: nothing non-finite was saved
    print(f"error: {e}", file=sys.stderr)
    return 1
  except (ValueError, FileNotFoundError) as e:  # bad data path, incompatible or no checkpoint
    print(f"error: {e}", file=sys.stderr)
    return 2
  except OSError as e:  # a WriteError (full disk, read-only workdir): the old files are intact
    print(f"error: {e}", file=sys.stderr)
    return 2
  if checkpoints.is_primary():
    val = final.get("val_meancos")
    loss = final.get("loss", float("nan"))
    print(f"step {final.get('step')} of {config.total_steps}: loss {loss:.4g}"
          + (f", validation MeanCos {val:.3f}" if val is not None else ""))
    print("wrote " + ", ".join(str(p) for p in train_lib.written_files(workdir)))
  return 0


def _check_workdir(workdir: Path, config_arg: str) -> str | None:
  """What is wrong with --workdir, before any work (None: fine): a file, not creatable or not
  writable, or holding the --config file under the name of an output."""
  from lrf_jax.io.atomic import path_problem, same_file
  from lrf_jax.learning import train_lib
  if path_problem(workdir):
    return f"--workdir: {workdir} {path_problem(workdir)}"
  if workdir.exists() and not workdir.is_dir():
    return f"--workdir: {workdir} is a file; expected a folder (new, or a run's to resume)"
  existing = next((p for p in [workdir, *workdir.absolute().parents] if p.exists()), None)
  if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
    return f"--workdir: {existing} is not writable"
  if Path(config_arg).is_file():
    for name in train_lib.OUTPUT_FILES:
      if same_file(workdir / name, config_arg):
        return (f"--config {config_arg}: is the run's output {name}; refusing to overwrite it "
                "(copy it elsewhere)")
  return None


if __name__ == "__main__":
  exit_with(main())
