"""The compiled per-patch sums of lrf_net_plus's `prepare` hook (numba, float64): the view and
trust of the z support (`support_sums`, for `lrf_net_plus.support_view`) and the relative area
of each neighbor (`relative_areas`, for `lrf_net_plus.patch_areas`).

Each reproduces the numpy expression it replaced bit for bit, sums included: numpy adds a row of
a contiguous array pairwise (`_pairwise_sum`) and the rows of a strided axis one after another;
`tests/test_lrf_net_plus_points_only.py` and `tests/test_lrf_net.py` hold those expressions and compare.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax.search.engine import run_blocks


@nb.njit(inline="always")
def _block_sum(a, lo, n):
  """numpy's sum of a[lo:lo + n] for n <= 128: 8 accumulators, then the rest in order."""
  if n < 8:
    res = 0.0
    for i in range(n):
      res += a[lo + i]
    return res
  r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
  r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
  i = 8
  while i < n - n % 8:
    r0, r1, r2, r3 = r0 + a[lo + i], r1 + a[lo + i + 1], r2 + a[lo + i + 2], r3 + a[lo + i + 3]
    r4, r5, r6, r7 = r4 + a[lo + i + 4], r5 + a[lo + i + 5], r6 + a[lo + i + 6], r7 + a[lo + i + 7]
    i += 8
  res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
  while i < n:
    res += a[lo + i]
    i += 1
  return res


@nb.njit(inline="always")
def _pairwise_sum(a, n, stack):
  """numpy's sum of a[:n] (float64, contiguous), bit for bit: its pairwise summation (blocks of
  up to 128 values, `_block_sum`, larger runs halved at a multiple of 8), without recursion
  (numba's cache does not reload recursive functions): `stack` (4, >= 64) holds each open
  run's start, length, state (0 new, 1 left half done) and left half's sum."""
  top = 0
  stack[0, 0], stack[1, 0], stack[2, 0] = 0.0, n, 0.0
  ret = 0.0
  while top >= 0:
    lo, cn = int(stack[0, top]), int(stack[1, top])
    if cn <= 128:
      ret = _block_sum(a, lo, cn)
      top -= 1
      continue
    half = cn // 2 - (cn // 2) % 8
    if stack[2, top] == 0.0:  # descend into the left half
      stack[2, top] = 1.0
      top += 1
      stack[0, top], stack[1, top], stack[2, top] = lo, half, 0.0
    elif stack[2, top] == 1.0:  # the left half's sum is ret: the right half
      stack[2, top], stack[3, top] = 2.0, ret
      top += 1
      stack[0, top], stack[1, top], stack[2, top] = lo + half, cn - half, 0.0
    else:  # both halves done
      ret = stack[3, top] + ret
      top -= 1
  return ret


@nb.njit(inline="always")
def _sparse_block_sum(pos, val, e, cnt, lo, n, lanes):
  """`_block_sum` of a vector that is zero but at the sorted positions pos[e:cnt] (values val):
  the same sums bit for bit, adding only the non-zero values (x + 0.0 = x, and no partial sum
  is -0.0). Returns (the sum, the first entry at or beyond lo + n)."""
  end = lo + n
  res = 0.0
  if n >= 8:
    lanes[:] = 0.0
    body = end - n % 8
    while e < cnt and pos[e] < body:
      lanes[(pos[e] - lo) % 8] += val[e]
      e += 1
    res = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + ((lanes[4] + lanes[5])
                                                             + (lanes[6] + lanes[7]))
  while e < cnt and pos[e] < end:
    res += val[e]
    e += 1
  return res, e


@nb.njit(inline="always")
def _sparse_pairwise_sum(pos, val, cnt, n, stack, lanes):
  """`_pairwise_sum` of a length-n vector that is zero but at the sorted positions pos[:cnt]
  (values val[:cnt]), bit for bit: the same runs and halves, each run's values taken in turn."""
  top = 0
  stack[0, 0], stack[1, 0], stack[2, 0] = 0.0, n, 0.0
  ret = 0.0
  e = 0
  while top >= 0:
    lo, cn = int(stack[0, top]), int(stack[1, top])
    if cn <= 128:
      ret, e = _sparse_block_sum(pos, val, e, cnt, lo, cn, lanes)
      top -= 1
      continue
    half = cn // 2 - (cn // 2) % 8
    if stack[2, top] == 0.0:
      stack[2, top] = 1.0
      top += 1
      stack[0, top], stack[1, top], stack[2, top] = lo, half, 0.0
    elif stack[2, top] == 1.0:
      stack[2, top], stack[3, top] = 2.0, ret
      top += 1
      stack[0, top], stack[1, top], stack[2, top] = lo + half, cn - half, 0.0
    else:
      ret = stack[3, top] + ret
      top -= 1
  return ret


def support_sums(nrm, per_point, idx, off, r2, weigh, min_trust, view, trust):
  """`lrf_net_plus.support_view` into view (N, 3) and trust (N,) (zeros on entry): per patch,
  the finite normals of the slots within sqrt(r2) summed in slot order; with `weigh`, the mean
  of their per_point values (numpy's pairwise sum over the row, 0 off the support) and the view
  zeroed below min_trust. The squared distance adds x² + z² first, then y², as numpy's einsum
  does. The slots within sqrt(r2) are first listed by a branch-free pass (most are not).
  Spans of patches on the engine's threads (`_support_span`)."""
  run_blocks(lambda lo, hi: _support_span(nrm, per_point, idx, off, r2, weigh, min_trust, view,
                                          trust, lo, hi), idx.shape[0])


@nb.njit(cache=True, nogil=True)
def _support_span(nrm, per_point, idx, off, r2, weigh, min_trust, view, trust, lo, hi):
  """Patches lo..hi-1 of `support_sums`."""
  k = idx.shape[1]
  pos = np.empty(k, np.int64)
  val = np.empty(k)
  stack = np.empty((4, 64))
  lanes = np.empty(8)
  for i in range(lo, hi):
    c = 0
    for s in range(k):
      x, y, z = np.float64(off[i, s, 0]), np.float64(off[i, s, 1]), np.float64(off[i, s, 2])
      pos[c] = s
      c += (idx[i, s] >= 0) & ((x * x + z * z) + y * y <= r2)
    vx = vy = vz = 0.0
    count = 0
    for e in range(c):
      s = pos[e]
      j = idx[i, s]
      a, b, cz = nrm[j, 0], nrm[j, 1], nrm[j, 2]
      if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(cz)):
        continue
      vx += a
      vy += b
      vz += cz
      pos[count] = s  # count <= e: the list compacted in place to the finite normals
      if weigh:
        val[count] = per_point[j]
      count += 1
    if weigh:
      trust[i] = (0.0 + _sparse_pairwise_sum(pos, val, count, k, stack, lanes)) / max(count, 1)
      if not trust[i] >= min_trust:
        continue
    view[i, 0], view[i, 1], view[i, 2] = vx, vy, vz


# Serial: 1 ms per 1000 patches of 512, and every lrf_net_plus call (register's too) compiles it
# on a first run, where parallel=True took 4.1-4.8 s against 2.0 s (loaded machine).
@nb.njit(cache=True)
def relative_areas(per_point, idx, mask, out):
  """`lrf_net_plus.patch_areas` from the per-point areas into out (N, K) float32: each slot's
  area (0 in padding, idx -1) over the mean of its row's (numpy's pairwise sum over the K slots
  divided by the row's mask count; 1 where that mean is not positive), divided in float64 and
  rounded once to float32."""
  m, k = idx.shape
  w = np.empty(k)
  stack = np.empty((4, 64))
  for i in range(m):
    count = 0
    for s in range(k):
      j = idx[i, s]
      w[s] = per_point[j] if j >= 0 else 0.0
      count += mask[i, s]
    mean = (0.0 + _pairwise_sum(w, k, stack)) / max(count, 1)
    mean = mean if mean > 0 else 1.0
    for s in range(k):
      out[i, s] = np.float32(w[s] / mean)
