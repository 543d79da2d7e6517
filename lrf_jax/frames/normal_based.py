"""The host `prepare` hook shared by the normal-based LRFs (mian, board, flare, ps).

Numpy, outside jit: it gathers the per-point normals (the caller's, else estimated by
`lrf_jax.normals.estimate_normals`) into the patch slots, for the jitted frame functions.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lrf_jax.frames.spec import KEYPOINT, SLOT
from lrf_jax.normals import default_normals


class NormalExtra(NamedTuple):
  """`extra` of the normal-based LRFs: normals of the patch slots and of the keypoint."""

  normals: np.ndarray    # (N, K, 3) float32, 0 in padding, NaN where undefined
  kp_normal: np.ndarray  # (N, 3) float32
  AXES = {"normals": SLOT, "kp_normal": KEYPOINT}


def prepare_normals(points: np.ndarray, keypoints: np.ndarray, patches, *,
                    faces: np.ndarray | None = None, normals: np.ndarray | None = None,
                    radius: float) -> NormalExtra:
  """`MethodSpec.prepare` hook of the normal-based LRFs: their `NormalExtra`.

  Args:
    points: (n, 3) cloud.
    keypoints: (N,) indices.
    patches: their `Patches` (K slots).
    faces: optional (f, 3) triangles (used to orient estimated normals).
    normals: optional (n, 3) normals; None = `estimate_normals`.
    radius: the support radius r.

  Returns:
    `NormalExtra`: (N, K, 3) float32 normals of the patch slots (0 in padding, NaN where
    undefined) and the (N, 3) float32 normal of each keypoint.
  """
  nrm = default_normals(points, radius, faces, normals).astype(np.float32)
  idx = np.asarray(patches.indices)
  gathered = nrm[np.maximum(idx, 0)]
  gathered[idx < 0] = 0.0
  return NormalExtra(gathered, nrm[np.asarray(keypoints)])
