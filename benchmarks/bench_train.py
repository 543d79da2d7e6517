"""Training throughput: pairs per second of the jitted train step, with and without building the
batches on the host, for the default config's shapes (512 pairs, K = 256).

    LRF_DATA=/path/to/data python benchmarks/bench_train.py [--data br|demo] [--steps 10]

Also reports the projected wall time of the default config (20 epochs of 20,000 pairs) from the
measured rate. The baseline in the same run is the same step without jit (op-by-op dispatch),
timed on a single step.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrf_jax.learning import config as config_lib  # noqa: E402
from lrf_jax.learning import data_sources  # noqa: E402
from lrf_jax.learning import train_step  # noqa: E402
from lrf_jax.learning.batches import BatchMaker  # noqa: E402


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default="br" if os.environ.get("LRF_DATA") else "demo")
  ap.add_argument("--steps", type=int, default=10)
  ap.add_argument("--batch-size", type=int, default=512)
  ap.add_argument("--host-epochs", type=int, default=8,
                  help="epochs of host batch building timed (median reported)")
  args = ap.parse_args()
  cfg = config_lib.replace(config_lib.load_config("default"), data=args.data,
                           batch_size=args.batch_size, val_pairs=0)
  clouds = data_sources.training_clouds(cfg)
  maker = BatchMaker(clouds, cfg)
  state = train_step.create_state(cfg)
  step = jax.jit(train_step.make_train_step(cfg), donate_argnums=0)
  batches = [maker.batch(0, i % cfg.steps_per_epoch) for i in range(args.steps)]
  state, m = step(state, batches[0])
  jax.block_until_ready(m)
  t0 = time.perf_counter()
  for b in batches:
    state, m = step(state, b)
  jax.block_until_ready(m)
  jitted = args.steps * cfg.batch_size / (time.perf_counter() - t0)
  t0 = time.perf_counter()
  for i in range(args.steps):
    state, m = step(state, maker.batch(1, i % cfg.steps_per_epoch))
  jax.block_until_ready(m)
  end_to_end = args.steps * cfg.batch_size / (time.perf_counter() - t0)
  # Host batch building alone: the patches of whole epochs (every pair, both sides), timed one
  # epoch at a time; the median epoch is reported.
  epoch_seconds = []
  for epoch in range(2, 2 + args.host_epochs):
    t0 = time.perf_counter()
    maker.epoch_patches(epoch)
    epoch_seconds.append(time.perf_counter() - t0)
  host = len(clouds.keypoints) / float(np.median(epoch_seconds))
  with jax.disable_jit():
    t0 = time.perf_counter()
    train_step.make_train_step(cfg)(train_step.create_state(cfg), batches[0])
    eager = cfg.batch_size / (time.perf_counter() - t0)
  total = cfg.epochs * cfg.steps_per_epoch * cfg.batch_size
  print(f"machine: {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} on "
        f"{jax.devices()[0].platform} x{jax.device_count()}; data {args.data}, "
        f"batch {cfg.batch_size}, K {cfg.patch_k}\n")
  print("| what | pairs/s |")
  print("|---|---:|")
  print(f"| train step, jitted (batches prebuilt) | {jitted:,.0f} |")
  print(f"| train step + host batch building | {end_to_end:,.0f} |")
  print(f"| host batch building alone (epoch patches, both sides; median of "
        f"{args.host_epochs} epochs) | {host:,.0f} |")
  print(f"| baseline: train step without jit | {eager:,.0f} |")
  print(f"\nprojected wall time of the default config ({total:,} pairs): "
        f"{total / end_to_end / 60:.1f} min")


if __name__ == "__main__":
  main()
