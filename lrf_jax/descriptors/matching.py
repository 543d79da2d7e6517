"""Matching in descriptor space: nearest neighbour with Lowe's ratio score (jnp, blocked).

For each query descriptor the nearest and second-nearest reference descriptors in the L2 distance
are found; the match is (query, nearest) with the score ratio = d1 / d2 in [0, 1] (smaller = more
distinctive). Recall vs 1-precision curves threshold this ratio (`lrf_jax.evaluation.description`),
correspondence selection keeps the matches of smallest ratio (`lrf_jax.registration`).

References:
  Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004 (the ratio test);
  Tombari et al. 2010 and Guo et al. 2016 (its use for recall vs 1-precision).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Matches(NamedTuple):
  """Nearest-neighbour matches of queries into references.

  Attributes:
    nearest: (m,) int32 index of the nearest valid reference (-1 where the query is invalid or
      there is no valid reference).
    distance: (m,) float32 L2 distance to it (inf where none).
    ratio: (m,) float32 d1 / d2 (1 where there is a single valid reference; inf where none).
  """

  nearest: np.ndarray
  distance: np.ndarray
  ratio: np.ndarray


@jax.jit
def _block(query: jax.Array, ref: jax.Array, ref_ok: jax.Array) -> tuple[jax.Array, jax.Array]:
  q2 = jnp.sum(query * query, axis=1)
  r2 = jnp.sum(ref * ref, axis=1)
  d2 = q2[:, None] + r2[None, :] - 2.0 * query @ ref.T
  d2 = jnp.where(ref_ok[None, :], jnp.maximum(d2, 0.0), jnp.inf)
  neg, idx = jax.lax.top_k(-d2, 2)
  return -neg, idx


def match_descriptors(query: np.ndarray, reference: np.ndarray, query_valid=None,
                      reference_valid=None, *, block: int = 1024) -> Matches:
  """Nearest and second-nearest reference of every query descriptor (L2), with the ratio score.

  Args:
    query: (m, D) descriptors.
    reference: (n, D) descriptors.
    query_valid: (m,) bool (None: all valid).
    reference_valid: (n,) bool (None: all valid); invalid references are never matched.
    block: queries per jitted call (memory: block x n floats).

  Returns:
    `Matches` for the m queries.

  Raises:
    ValueError: non-2-D inputs or different descriptor lengths.
  """
  q = np.asarray(query, np.float32)
  r = np.asarray(reference, np.float32)
  if q.ndim != 2 or r.ndim != 2 or q.shape[1] != r.shape[1]:
    raise ValueError(f"descriptors: expected (m, D) queries and (n, D) references with the same "
                     f"D, got {q.shape} and {r.shape}")
  qv = np.ones(len(q), bool) if query_valid is None else np.asarray(query_valid, bool)
  rv = np.ones(len(r), bool) if reference_valid is None else np.asarray(reference_valid, bool)
  if qv.shape != (len(q),) or rv.shape != (len(r),):
    raise ValueError(f"valid flags: expected shapes ({len(q)},) and ({len(r)},), got {qv.shape} "
                     f"and {rv.shape}")
  m = len(q)
  nearest = np.full(m, -1, np.int32)
  dist = np.full(m, np.inf, np.float32)
  ratio = np.full(m, np.inf, np.float32)
  if m == 0 or not rv.any():
    return Matches(nearest, dist, ratio)
  ref = r
  if len(r) < 2:  # top_k needs two columns: pad with an invalid reference
    ref = np.concatenate([r, np.zeros((2 - len(r), r.shape[1]), np.float32)])
    rv = np.concatenate([rv, np.zeros(2 - len(r), bool)])
  ref_j, rv_j = jax.device_put(ref), jax.device_put(rv)
  b = min(block, m)
  for s in range(0, m, b):
    qb = q[s:s + b]
    n_real = len(qb)
    if n_real < b:
      qb = np.concatenate([qb, np.zeros((b - n_real, q.shape[1]), np.float32)])
    d2, idx = (np.asarray(a)[:n_real] for a in _block(qb, ref_j, rv_j))
    d1 = np.sqrt(d2[:, 0])
    d_2 = np.sqrt(d2[:, 1])
    nearest[s:s + n_real] = idx[:, 0]
    dist[s:s + n_real] = d1
    with np.errstate(divide="ignore", invalid="ignore"):
      rt = np.where(np.isinf(d_2), 1.0, np.where(d_2 > 0, d1 / d_2, 1.0))
    ratio[s:s + n_real] = rt
  nearest[~qv] = -1
  dist[~qv] = np.inf
  ratio[~qv] = np.inf
  return Matches(nearest, dist, ratio)


def top_correspondences(matches: Matches, n: int) -> tuple[np.ndarray, np.ndarray]:
  """The `n` matches of smallest ratio (ties: smaller distance, then lower query index).

  Args:
    matches: `Matches` of m queries.
    n: how many to keep (fewer when fewer queries have a match).

  Returns:
    (query_idx, reference_idx): (k,) int64 each, k = min(n, matched), best first.
  """
  ok = np.flatnonzero(matches.nearest >= 0)
  order = np.lexsort((ok, matches.distance[ok], matches.ratio[ok]))
  keep = ok[order[:max(0, int(n))]]
  return keep.astype(np.int64), matches.nearest[keep].astype(np.int64)
