"""Beyond the paper (lrf_net_plus from the points alone): `plus_soft` with the z sign that
lrf_net_plus gives without a viewpoint, faces or normals (`z_view="voted"`). Each side of every
batch carries the view direction of `lrf_net_plus.points_only_view` on its own cloud (the scene
after its noise): normals oriented over the whole cloud (PCA over 0.2 r, propagation, each
component's sign by convexity votes over r) summed over the z support, zero where the vote's
margin is below `MIN_VOTE_TRUST`; z is flipped towards it where it is non-zero and keeps the
ball sign elsewhere, so the x weights are trained under the z that points-only inference uses
(`plus_soft` trains under the ball sign everywhere). Validation on the bunny scans orients z the
same way. The other fields are plus_soft's: softmax x, noise augmentation 0-0.5 mr on the scene
side, learning rate 1e-3, 20 epochs of 20,000 BR keypoints, 300 validation keypoints per pair.

    LRF_DATA=... python train.py --config plus_points --workdir runs/plus_points
"""

import dataclasses

from lrf_jax.learning.configs import plus_soft


def get_config():
  return dataclasses.replace(plus_soft.get_config(), name="plus_points", z_view="voted")
