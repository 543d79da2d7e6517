"""LRF-Net's frames from prepared patches on the CPU (numba, float64): the host counterpart of
`lrf_net.frames_with_weight_fn` for the table-read weights (`lut_weights`).

`compute_frames` runs it by default on a CPU backend for lrf_net, lrf_net_plus and uniform
(`MethodSpec.host_patch_frames`): one keypoint per thread, the same rules as the jitted function
(TOLDI z over r/3 with its sign, `ball_sign`, `view_sign`, the bilinear weight table, softmax and
area weights, the x axis and its test `X_EPS` (`host_geometry.x_axis_sum_of`, shared with TOLDI's
kernel), `geometry.frame_from_zx`), in float64 instead of float32. Frames then agree with the
jitted ones to float32 rounding, except at keypoints whose sign tests sit on a tie (a patch
height Σ (q_i - p)·z or a view product of about 0).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba as nb
import numpy as np

from lrf_jax.frames import host_geometry as hg
from lrf_jax.search.engine import run_blocks

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# Weight modes of the kernel.
UNIFORM, TABLE_SUM, TABLE_SOFTMAX = 0, 1, 2


@nb.njit(inline="always")
def _table_weight(table, dist_r, cos):
  """`lrf_net.lut_weights` for one neighbor: bilinear read of the size x size table at
  (clip(|pq|/r, 0, 1), clip(cos, -1, 1))."""
  n = table.shape[0] - 1
  u = min(max(dist_r, 0.0), 1.0) * n
  v = (min(max(cos, -1.0), 1.0) + 1.0) * 0.5 * n
  i0 = min(max(int(np.floor(u)), 0), n - 1)
  j0 = min(max(int(np.floor(v)), 0), n - 1)
  fu, fv = u - i0, v - j0
  return ((1.0 - fu) * ((1.0 - fv) * table[i0, j0] + fv * table[i0, j0 + 1])
          + fu * ((1.0 - fv) * table[i0 + 1, j0] + fv * table[i0 + 1, j0 + 1]))


_x_axis_sum = hg.x_axis_sum_of(hg.listed_weight)  # w = 0 in padding: skipped


def _lrf_net_host_kernel(offsets, mask, z_cov, z_mean, z_count, radius, table, mode, ball, view,
                         area, eps, x_eps, min_count, frames, valid):
  """Frames of every patch (see the module docstring); view (N, 3) and area (N, K) are used
  when their first axis is N (zero-length arrays: none). Spans of keypoints on the engine's
  threads, each one call of `_lrf_net_task` (`search.engine.run_blocks`)."""
  run_blocks(lambda lo, hi: _lrf_net_task(lo, hi, offsets, mask, z_cov, z_mean, z_count, radius,
                                          table, mode, ball, view, area, eps, x_eps, min_count,
                                          frames, valid), mask.shape[0])


# Allocates (per-keypoint arrays): numba's reference counting stays on; releases the GIL.
@nb.njit(cache=True, nogil=True)
def _lrf_net_task(lo, hi, offsets, mask, z_cov, z_mean, z_count, radius, table, mode, ball, view,
                  area, eps, x_eps, min_count, frames, valid):
  """Keypoints lo..hi-1 of `_lrf_net_host_kernel`."""
  n, k = mask.shape
  has_view = view.shape[0] == n
  has_area = area.shape[0] == n
  for i in range(lo, hi):
    hg.set_identity(frames, valid, i)
    r = float(radius[i])
    cov = z_cov[i].astype(np.float64)
    mean = z_mean[i].astype(np.float64)
    if not (np.isfinite(r) and r > 0.0 and np.all(np.isfinite(cov)) and np.all(np.isfinite(mean))):
      continue
    ok, z = hg.smallest_z(cov, z_count[i], eps, min_count)
    if not ok:
      continue
    if mean[0] * z[0] + mean[1] * z[1] + mean[2] * z[2] > 0.0:  # TOLDI's sign: mean · z <= 0
      z = -z
    finite = True
    dot = np.zeros(k)  # pq_s · z, for the signs, the attributes and the tangent projections
    h = 0.0
    for s in range(k):
      if mask[i, s]:
        o0, o1, o2 = offsets[i, s, 0], offsets[i, s, 1], offsets[i, s, 2]
        finite = finite and np.isfinite(o0) and np.isfinite(o1) and np.isfinite(o2)
        dot[s] = o0 * z[0] + o1 * z[1] + o2 * z[2]
        h += dot[s]
    if not finite:
      continue
    sign = 1.0
    if ball and h > 0.0:
      z = -z
      sign = -sign
    if has_view and view[i, 0] * z[0] + view[i, 1] * z[1] + view[i, 2] * z[2] < 0.0:
      z = -z
      sign = -sign
    if sign < 0.0:
      dot = -dot
    w = np.zeros(k)
    top = -np.inf
    for s in range(k):
      if not mask[i, s]:
        continue
      if mode == UNIFORM:
        w[s] = 1.0
        continue
      o0, o1, o2 = float(offsets[i, s, 0]), float(offsets[i, s, 1]), float(offsets[i, s, 2])
      d = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
      w[s] = _table_weight(table, d / r, dot[s] / d if d > 0.0 else 0.0)
      top = max(top, w[s])
    if mode == TABLE_SOFTMAX or has_area:
      for s in range(k):
        if mask[i, s]:
          if mode == TABLE_SOFTMAX:
            w[s] = np.exp(w[s] - top)
          if has_area:
            w[s] *= area[i, s]
    ok, x = _x_axis_sum(offsets[i], (0.0, 0.0, 0.0), None, 0, k, z, (w, dot), x_eps)
    if ok:
      hg.write_frame(frames, valid, i, z, x)


def lrf_net_frames_host(patches, table: AnyArray | None, *, x_eps: float, min_count: int,
                        x_mode: str = "sum", z_sign: str = "toldi",
                        view: AnyArray | None = None, area: AnyArray | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
  """`lrf_net.lrf_net_frames` with table weights (or uniform ones) on the host, float64.

  Args:
    patches: host `Patches` (N keypoints, K neighbors).
    table: (size, size) weight table (`lrf_net.weight_table(...).values`), or None for uniform
      weights (w = 1, `lrf_net.uniform_frames`).
    x_mode: "sum" or "softmax" (`lrf_net.softmax_weights`).
    z_sign: "toldi" or "ball" (`lrf_net.ball_sign`).
    view: optional (N, 3) sensor position minus keypoint (`lrf_net.view_sign`).
    area: optional (N, K) area per neighbor multiplying the weights.
    x_eps: the x-sum test (`lrf_net.X_EPS`): |Σ w v| must exceed x_eps Σ |w| |v|.
    min_count: fewer neighbors within r/3 make z invalid (`lrf_net.MIN_Z_NEIGHBORS`).

  Returns:
    (frames (N, 3, 3) float32 rows x, y, z, the identity where invalid; valid (N,) bool).
  """
  if x_mode not in ("sum", "softmax"):
    raise ValueError(f"x_mode: the host kernel takes 'sum' or 'softmax', got {x_mode!r}")
  if z_sign not in ("toldi", "ball"):
    raise ValueError(f"z_sign: expected 'toldi' or 'ball', got {z_sign!r}")
  mode = UNIFORM if table is None else (TABLE_SOFTMAX if x_mode == "softmax" else TABLE_SUM)
  tab = np.zeros((2, 2)) if table is None else np.ascontiguousarray(table, np.float64)
  n = patches.mask.shape[0]
  return hg.run_kernel(
      _lrf_net_host_kernel, n, np.asarray(patches.offsets), np.asarray(patches.mask),
      np.asarray(patches.z_cov), np.asarray(patches.z_mean), np.asarray(patches.z_count),
      np.asarray(patches.radius), tab, mode, z_sign == "ball",
      np.zeros((0, 3), np.float32) if view is None else np.asarray(view, np.float32),
      np.zeros((0, 1), np.float32) if area is None else np.asarray(area, np.float32),
      hg.EPS, float(x_eps), int(min_count))
