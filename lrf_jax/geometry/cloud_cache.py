"""The host's per-cloud results kept for the last cloud: `cache_last` (one entry per kind, keyed
by a digest of the inputs' bytes) and what several of them share, the cloud's k nearest
neighbors (`cloud_knn`).

`compute_frames` calls a method's `prepare` hook once per chunk of keypoints: what the hook
derives from the whole cloud (normals, their orientation, areas, curvature) is computed once.
The cache hands out copies of its arrays: writing into a result never changes a later one.
`lrf_jax.geometry.normals` re-exports `cache_last` (and `CLOUD_CACHE`, which
`caches.clear_caches` empties).
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from lrf_jax.search import engine

# `cache_last`'s store: kind -> (digest of the kind and inputs, result), one entry per kind
# (about 8 kinds); `caches.clear_caches` empties it.
CLOUD_CACHE: dict[str, Any] = {}


def _digest(*arrays: Any) -> str:
  h = hashlib.blake2b(digest_size=16)
  for a in arrays:
    if a is None:
      h.update(b"none")
    elif isinstance(a, np.ndarray):
      a = np.ascontiguousarray(a)
      h.update(str((a.dtype, a.shape)).encode())
      h.update(a.data)
    else:
      h.update(repr(a).encode())
  return h.hexdigest()


def _handed_out(value: Any) -> Any:
  """What the cache gives a caller: numpy arrays (also inside tuples and lists, recursively) as
  fresh writable copies, anything else (e.g. an `engine.Grid`) shared as it is."""
  if isinstance(value, np.ndarray):
    return value.copy()
  if isinstance(value, tuple) and hasattr(value, "_fields"):  # a NamedTuple
    return type(value)(*(_handed_out(v) for v in value))
  if isinstance(value, (tuple, list)):
    return type(value)(_handed_out(v) for v in value)
  return value


def cache_last(kind: str, key_arrays: tuple, fn):
  """One cached result per `kind`: `fn()` is recomputed only when the inputs' digest changes.

  Every call, the first included, returns copies of the stored arrays (directly or inside
  tuples/lists): a caller may write into what it gets without changing what a later call
  returns. Other objects (e.g. an `engine.Grid`) are shared; callers must not modify them.

  Args:
    kind: cache slot name.
    key_arrays: the arrays/values the result depends on.
    fn (Callable[[], Any]): zero-argument function computing the result.

  Returns:
    result (Any): `fn()`, or the stored result for identical inputs (arrays copied).
  """
  key = _digest(kind, *key_arrays)
  hit = CLOUD_CACHE.get(kind)
  if hit is None or hit[0] != key:
    hit = CLOUD_CACHE[kind] = (key, fn())
  return _handed_out(hit[1])


def cloud_knn(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
  """Each point's k nearest points of the cloud, itself included (`engine.knn` on the cloud's
  own `knn_grid`; ties broken by index), cached for the last (points, k): the propagation graph
  of the points-only orientation and lrf_net_plus's sampling density read the same search.

  Args:
    points: (n, 3) float64 cloud.
    k: neighbors per point, 1 <= k <= n.

  Returns:
    (distance to the k-th (n,) float64, indices (n, k) int64, each row by distance). Kept as
    the k-th distance and int32 indices: 44 bytes a point for k = 9.
  """
  pts = np.ascontiguousarray(points, np.float64)
  kk = int(k)

  def search():
    d, i = engine.knn(engine.knn_grid(pts, kk), pts, kk)
    return d[:, -1].copy(), i.astype(np.int32)

  last, nbr = cache_last("cloud_knn", (pts, kk), search)
  return last, nbr.astype(np.int64)
