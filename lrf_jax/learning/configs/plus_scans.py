"""Beyond the paper: lrf_net_plus fine-tuned on the user's own scans (`scans=DIR`), starting from
its shipped object weights (`init="objects"`): plus_soft's model, loss, noise augmentation and
learning rate, 8 epochs of 20,000 keypoints drawn on the scan pairs (z signed over each
support, as the points-only registration and the `vote=False` frames sign it). The shipped
`lrf_jax/weights/lrf_net_plus_streets.msgpack` and `lrf_net_plus_rooms.msgpack` (their JSON
cards give the folders and overrides).

    python train.py --config plus_scans --workdir runs/streets scans=my_sweeps/
    python train.py --config plus_scans --workdir runs/rooms scans=my_rooms/ scan_match_mr=1.0
"""

import dataclasses

from lrf_jax.learning.configs import plus_soft


def get_config():
  return dataclasses.replace(plus_soft.get_config(), name="plus_scans", init="objects", epochs=8)
