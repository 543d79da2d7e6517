"""Radius search on the accelerator: fixed-shape voxel grids, the same patches as the host search.

On an accelerator the jitted frames are cheap next to the host search that feeds them; this
module builds the same `Patches` as `neighborhoods.build_patches` (for an integer K) inside one
jitted function, so that the patches never leave the device:

* Host, once per cloud (numpy, O(n log n)): the cloud in seeded priority order (as `SearchIndex`),
  and two uniform grids, of cell edge r (the patch) and z_ratio * r (the normal support). Each
  grid stores its points sorted by (cell key, priority rank), the sorted distinct cell keys and
  each cell's start and length.
* Device, per chunk of keypoints (jitted, vmapped): the 27 cells around the keypoint's cell are
  found by binary search among the cell keys; the first `cap` points of each (in priority order)
  are the candidates. The patch is the K candidates of smallest rank within r (`lax.top_k`), the
  normal support all candidates within z_ratio * r (two-pass mean and covariance, float32 offsets
  from the keypoint).

Exactness: the inner grid's cap is its largest cell, so the normal statistics are exact. The
patch grid's cap (default 2K) can truncate a dense cell; a keypoint's patch is then still exact
when every truncated cell's last candidate ranks above the K-th selected rank (the cell's
untaken points all rank higher still). Keypoints that fail this test, or whose cells include a
truncated one while the ball holds fewer than K candidates, are flagged, and `build_patches_device`
recomputes them with the host search, so the result equals the host search's (tested).

`count` (points within r before subsampling) is exact when no patch cell of the keypoint is
truncated and otherwise a lower bound that is at least K; the fixed-K methods (lrf_net,
lrf_net_plus, uniform) do not read it. All-neighbor patches (K = None) stay on the host.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from lrf_jax._jax import jit
from lrf_jax.checks import validate_scale
from lrf_jax.search.neighborhoods import Patches, SearchIndex, build_patches

_OFFS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)


class Grid(NamedTuple):
  """One uniform grid over a cloud (device arrays, a pytree).

  Attributes:
    points: (n, 3) float32 points sorted by (cell key, rank), relative to `origin`.
    rank: (n,) int32 priority rank of each sorted point (index into the priority-order cloud).
    keys: (u,) int32 sorted distinct cell keys.
    start: (u,) int32 first sorted point of each cell.
    length: (u,) int32 points per cell.
    cell: () float32 cell edge.
    dims: (3,) int32 grid size per axis (keys are (i * dims[1] + j) * dims[2] + k).
  """

  points: jax.Array
  rank: jax.Array
  keys: jax.Array
  start: jax.Array
  length: jax.Array
  cell: jax.Array
  dims: jax.Array


def _grid(pts: np.ndarray, lo: np.ndarray, cell: float) -> tuple[Grid, int]:
  ijk = np.floor((pts - lo) / cell).astype(np.int64)
  dims = ijk.max(axis=0) + 3  # one empty layer beyond the last cell (neighbor lookups)
  ijk += 1
  if np.prod(dims.astype(np.float64)) >= 2**31 - 1:
    raise ValueError(f"device search: the grid of cell {cell:g} needs {dims.tolist()} cells, "
                     "more than int32 keys hold; use search='host' for this cloud and radius")
  key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
  order = np.lexsort((np.arange(len(pts)), key))  # by key, then rank (pts are in rank order)
  keys, start, length = np.unique(key[order], return_index=True, return_counts=True)
  grid = Grid(points=jnp.asarray((pts[order] - lo).astype(np.float32)),
              rank=jnp.asarray(order.astype(np.int32)), keys=jnp.asarray(keys.astype(np.int32)),
              start=jnp.asarray(start.astype(np.int32)),
              length=jnp.asarray(length.astype(np.int32)),
              cell=jnp.float32(cell), dims=jnp.asarray(dims.astype(np.int32)))
  return grid, int(length.max())


class DeviceIndex:
  """The host-built grids of one cloud for one radius (reuse it across keypoint chunks).

  Args:
    points: (n, 3) cloud (float64 on the host).
    radius: support radius r.
    k: patch size K.
    seed: subsample seed (the same priority order as `SearchIndex`).
    z_ratio: normal support radius / r.
    cap: candidates taken per patch cell (default 2K); larger is exact more often and slower.
  """

  def __init__(self, points: np.ndarray, radius: float, k: int, seed: int = 0,
               z_ratio: float = 1.0 / 3.0, cap: int | None = None):
    self.host = SearchIndex(points, seed)
    validate_scale(self.host.max_abs, float(radius))
    self.radius, self.k, self.seed, self.z_ratio = float(radius), int(k), int(seed), z_ratio
    pts = self.host.data  # priority order
    self.lo = pts.min(axis=0)
    self.patch_grid, max_patch = _grid(pts, self.lo, self.radius)
    self.inner_grid, max_inner = _grid(pts, self.lo, self.radius * z_ratio)
    self.cap = min(max_patch, int(cap or 2 * k))
    self.inner_cap = max_inner
    self.order = jnp.asarray(self.host.order.astype(np.int32))
    self.points_rank = jnp.asarray((pts - self.lo).astype(np.float32))


def _cells(grid: Grid, p: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Start and length of the 27 cells around point p (relative to the grid origin)."""
  ijk = jnp.floor(p / grid.cell).astype(jnp.int32) + 1 + jnp.asarray(_OFFS, jnp.int32)
  ijk = jnp.clip(ijk, 0, grid.dims - 1)
  key = (ijk[:, 0] * grid.dims[1] + ijk[:, 1]) * grid.dims[2] + ijk[:, 2]
  pos = jnp.clip(jnp.searchsorted(grid.keys, key), 0, grid.keys.shape[0] - 1)
  hit = grid.keys[pos] == key
  return grid.start[pos], jnp.where(hit, grid.length[pos], 0)


def _candidates(grid: Grid, p: jax.Array, cap: int):
  start, length = _cells(grid, p)
  slot = jnp.arange(cap, dtype=jnp.int32)
  idx = start[:, None] + slot[None, :]  # (27, cap)
  ok = slot[None, :] < length[:, None]
  idx = jnp.where(ok, idx, 0)
  return grid.points[idx] - p, grid.rank[idx], ok, length


@jit(static_argnames=("k", "cap", "inner_cap"))
def _search(patch_grid: Grid, inner_grid: Grid, order: jax.Array, centers: jax.Array,
            radius: jax.Array, inner_radius: jax.Array, *, k: int, cap: int, inner_cap: int):
  """Patches of `centers` (N, 3) (grid-relative float32) and a per-keypoint exactness flag."""
  big = jnp.iinfo(jnp.int32).max

  def one(p):
    off, rank, ok, length = _candidates(patch_grid, p, cap)
    d2 = jnp.sum(off * off, -1)
    inball = ok & (d2 <= radius * radius)
    key = jnp.where(inball, rank, big).reshape(-1)
    neg, pos = jax.lax.top_k(-key, k)  # the K smallest ranks, ascending
    sel = -neg
    mask = sel < big
    offsets = jnp.where(mask[:, None], off.reshape(-1, 3)[pos], 0.0)
    indices = jnp.where(mask, order[jnp.where(mask, sel, 0)], -1)
    count = jnp.sum(inball)
    # Exactness: a truncated cell is harmless when its last candidate ranks above the K-th pick.
    truncated = length > cap
    last_rank = rank[:, cap - 1]
    # Fewer than K picked: the ball may hold more than was seen, so any truncation is fatal.
    threshold = jnp.where(mask[-1], sel[-1], big)
    exact = jnp.all(~truncated | (last_rank > threshold))
    # Normal support: every point within z_ratio * r (uncapped cells: exact), two-pass moments.
    ioff, _, iok, _ = _candidates(inner_grid, p, inner_cap)
    ioff, iok = ioff.reshape(-1, 3), iok.reshape(-1)
    iin = iok & (jnp.sum(ioff * ioff, -1) <= inner_radius * inner_radius)
    n_in = jnp.sum(iin)
    w = iin.astype(jnp.float32)
    mean = jnp.sum(ioff * w[:, None], 0) / jnp.maximum(n_in, 1)
    c = (ioff - mean) * w[:, None]
    cov = c.T @ c / jnp.maximum(n_in, 1)
    return offsets, mask, indices, count, mean, cov, n_in, exact

  offsets, mask, indices, count, mean, cov, n_in, exact = jax.vmap(one)(centers)
  return (Patches(offsets=offsets, mask=mask, indices=indices, count=count.astype(jnp.int32),
                  radius=jnp.full(centers.shape[:1], radius, jnp.float32), z_cov=cov,
                  z_mean=mean, z_count=n_in.astype(jnp.int32)), exact)


def build_patches_device(points: np.ndarray, keypoints: np.ndarray, radius: float, k: int = 256,
                         *, seed: int = 0, z_ratio: float = 1.0 / 3.0,
                         index: DeviceIndex | None = None,
                         fallback: bool = True) -> tuple[Patches, np.ndarray]:
  """`neighborhoods.build_patches` for an integer K, searched on the default device.

  Args:
    points: (n, 3) cloud (validated by the caller).
    keypoints: (m,) int indices.
    radius: support radius r (cloud units).
    k: patch size K (an integer: all-neighbor patches stay on the host).
    seed: subsample seed.
    z_ratio: normal support radius / r.
    index: a `DeviceIndex(points, radius, k, seed, z_ratio)` to reuse across chunks.
    fallback: recompute the keypoints whose device patch may differ from the host search's with
      the host search (then the result equals `build_patches` up to float32 round-off of the
      normal statistics); False leaves them as computed and only reports them.

  Returns:
    (patches, inexact): `Patches` with device arrays (N = m), and (m,) bool, True where the
    device search could not guarantee the host result (recomputed on the host if `fallback`).
  """
  if k is None:
    raise ValueError("device search: k must be an integer patch size (all-neighbor patches, "
                     "k=None, use the host search)")
  if index is None or (index.radius, index.k, index.seed, index.z_ratio) != (
      float(radius), int(k), int(seed), z_ratio):
    index = DeviceIndex(points, radius, k, seed, z_ratio)
  kp = np.asarray(keypoints, np.int64)
  centers = jnp.asarray((np.asarray(points, np.float64)[kp] - index.lo).astype(np.float32))
  patches, exact = _search(index.patch_grid, index.inner_grid, index.order, centers,
                           jnp.float32(radius), jnp.float32(radius * z_ratio), k=int(k),
                           cap=index.cap, inner_cap=index.inner_cap)
  inexact = ~np.asarray(exact)
  if fallback and inexact.any():
    redo = np.flatnonzero(inexact)
    host = build_patches(points, kp[redo], radius, k, seed=seed, z_ratio=z_ratio,
                         index=index.host, validate=False)
    patches = Patches(*[jnp.asarray(a).at[redo].set(jnp.asarray(h))
                        for a, h in zip(patches, host)])
  return patches, inexact
