"""Train LRF-Net.

    python train.py --config default --workdir runs/default            # the paper (needs LRF_DATA)
    python train.py --config smoke --workdir /tmp/smoke epochs=2       # CPU, about a minute
    python train.py --config default --workdir runs/x batch_size=256 noise_mr=0.1,0.3
    python train.py --config default --workdir /shared/runs/x \
        --coordinator HOST0:1234 --num-processes N --process-id I     # on each of N hosts

Overrides are `key=value` fields of `lrf_jax.config.TrainConfig`. A run restarted with the same
--workdir resumes from its latest checkpoint. With --coordinator, the processes join one
`jax.distributed` job (gloo collectives on CPU), the batch is split over the devices of all of
them, the workdir must be shared, and only process 0 prints and writes files besides the
checkpoints. This file is intentionally kept short; the loop lives in lrf_jax/train_lib.py.
"""

import argparse
import sys

from lrf_jax import checkpoints
from lrf_jax import config as config_lib
from lrf_jax import train_lib


def main(argv=None) -> int:
  ap = argparse.ArgumentParser(description="Train LRF-Net (weakly supervised, Chamfer loss).")
  ap.add_argument("--config", default="default", help="preset name or path (.py / .json)")
  ap.add_argument("--workdir", default=None, help="output folder (default: runs/<config name>)")
  ap.add_argument("--no-progress", action="store_true", help="no progress bar")
  ap.add_argument("--coordinator", default=None,
                  help="multi-host: coordinator address host:port (jax.distributed)")
  ap.add_argument("--num-processes", type=int, default=None,
                  help="multi-host: number of processes of the job (with --coordinator)")
  ap.add_argument("--process-id", type=int, default=None,
                  help="multi-host: this process's index in [0, N) (with --coordinator)")
  ap.add_argument("overrides", nargs="*", help="key=value config overrides")
  args = ap.parse_args(argv)
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
  workdir = args.workdir or f"runs/{config.name}"
  try:
    final = train_lib.train_and_evaluate(config, workdir, progress=not args.no_progress)
  except FloatingPointError as e:  # diverged: nothing non-finite was saved
    print(f"error: {e}", file=sys.stderr)
    return 1
  except (ValueError, FileNotFoundError) as e:  # bad data path, incompatible or no checkpoint
    print(f"error: {e}", file=sys.stderr)
    return 2
  if checkpoints.is_primary():
    print({k: v for k, v in final.items() if k != "val_per_pair"})
  return 0


if __name__ == "__main__":
  sys.exit(main())
