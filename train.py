"""Train LRF-Net.

    python train.py --config default --workdir runs/default            # the paper (needs LRF_DATA)
    python train.py --config smoke --workdir /tmp/smoke epochs=2       # CPU, about a minute
    python train.py --config default --workdir runs/x batch_size=256 noise_mr=0.1,0.3

Overrides are `key=value` fields of `lrf_jax.config.TrainConfig`. A run restarted with the same
--workdir resumes from its latest checkpoint. This file is intentionally kept short; the logic
lives in lrf_jax/train_lib.py.
"""

import argparse
import sys

from lrf_jax import config as config_lib
from lrf_jax import train_lib


def main(argv=None) -> int:
  ap = argparse.ArgumentParser(description="Train LRF-Net (weakly supervised, Chamfer loss).")
  ap.add_argument("--config", default="default", help="preset name or path (.py / .json)")
  ap.add_argument("--workdir", default=None, help="output folder (default: runs/<config name>)")
  ap.add_argument("--no-progress", action="store_true", help="no progress bar")
  ap.add_argument("--coordinator", default=None,
                  help="multi-host: coordinator address host:port (jax.distributed)")
  ap.add_argument("--num-processes", type=int, default=None)
  ap.add_argument("--process-id", type=int, default=None)
  ap.add_argument("overrides", nargs="*", help="key=value config overrides")
  args = ap.parse_args(argv)
  try:
    config = config_lib.replace(config_lib.load_config(args.config),
                                **config_lib.parse_overrides(args.overrides))
  except ValueError as e:  # a bad preset or override: name it, no traceback
    print(f"error: {e}", file=sys.stderr)
    return 2
  if args.coordinator:
    import jax
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
  print({k: v for k, v in final.items() if k != "val_per_pair"})
  return 0


if __name__ == "__main__":
  sys.exit(main())
