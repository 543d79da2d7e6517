"""Consistent orientation of unit normals without a viewpoint or a mesh (numba, host).

* `orient_by_propagation`: Hoppe et al. (1992). Over a k-nearest-neighbor graph weighted by
  1 - |n_i · n_j|, the minimum spanning tree is grown (Prim) from one seed per connected
  component; each child takes the sign that agrees with its parent. The seed is the component's
  point farthest from the component's centroid, oriented away from that centroid (outward for a
  closed surface).
* `orient_by_vote`: the same, then each component's sign by the majority of its convexity votes
  (lrf_net_plus's z sign from the points alone, `normals.voted_normals`).
* `orient_by_reference`: the sign that agrees with a reference field (a mesh's vertex normals).

`lrf_jax.geometry.normals` re-exports every public name of this module.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax.search import engine
from lrf_jax.geometry.cloud_cache import cloud_knn

# Neighbors per point in the orientation graph of `orient_by_propagation`.
PROPAGATION_K = 8

def orient_by_reference(normals: np.ndarray, reference: np.ndarray) -> np.ndarray:
  """Flip normals where they disagree with a reference field (n · ref < 0); NaN stays NaN."""
  out = np.array(normals, np.float64, copy=True)
  flip = np.einsum("ij,ij->i", np.nan_to_num(out), np.nan_to_num(reference)) < 0
  out[flip] *= -1.0
  return out


@nb.njit(inline="always")
def _heap_put(hk, hv, pos, i, kv, v):
  """Slot i of the binary min-heap (keys hk, nodes hv, pos[node] = slot) := (kv, v)."""
  hk[i] = kv
  hv[i] = v
  pos[v] = i


@nb.njit(inline="always")
def _heap_sift_up(hk, hv, pos, i, kv, v):
  """Insert (kv, v) at slot i (a free slot or v's own) and move it up to its place."""
  while i > 0:
    p = (i - 1) >> 1
    if hk[p] <= kv:
      break
    _heap_put(hk, hv, pos, i, hk[p], hv[p])
    i = p
  _heap_put(hk, hv, pos, i, kv, v)


@nb.njit(inline="always")
def _heap_sift_down(hk, hv, pos, size):
  """Re-insert the heap's last entry (slot `size`) from the root after the root was popped."""
  kv = hk[size]
  v = hv[size]
  i = 0
  while True:
    c = 2 * i + 1
    if c >= size:
      break
    if c + 1 < size and hk[c + 1] < hk[c]:
      c += 1
    if kv <= hk[c]:
      break
    _heap_put(hk, hv, pos, i, hk[c], hv[c])
    i = c
  _heap_put(hk, hv, pos, i, kv, v)


@nb.njit(inline="always")
def _listed_later(nbr, i, j):
  """Whether the edge (i, j) of the k-NN lists `nbr` was already met at j < i (i is in j's
  list): its second mention, which adds only entries that repeat earlier ones."""
  if j >= i:
    return False
  for t in range(nbr.shape[1]):
    if nbr[j, t] == i:
      return True
  return False


@nb.njit(cache=True)
def _knn_graph(nrm, nbr):
  """CSR adjacency (starts (m + 1,), adj, weights 1 - |n_i · n_j|) of the k-NN lists `nbr`
  (m, k), every edge in both directions, each node's entries in the order the lists mention
  them; an edge both ends list is entered once (at its first mention: a repeated entry would
  come later in both nodes' lists, where neither the walk nor Prim's strict key test reads it)."""
  m, kk = nbr.shape
  starts = np.zeros(m + 1, np.int64)
  for i in range(m):
    for t in range(kk):
      j = nbr[i, t]
      if j != i and not _listed_later(nbr, i, j):
        starts[i + 1] += 1
        starts[j + 1] += 1
  for i in range(m):
    starts[i + 1] += starts[i]
  fill = starts[:-1].copy()
  adj = np.empty(starts[m], np.int64)
  wts = np.empty(starts[m])
  for i in range(m):
    for t in range(kk):
      j = nbr[i, t]
      if j != i and not _listed_later(nbr, i, j):
        w = 1.0 - abs(nrm[i, 0] * nrm[j, 0] + nrm[i, 1] * nrm[j, 1] + nrm[i, 2] * nrm[j, 2])
        adj[fill[i]] = j
        wts[fill[i]] = w
        fill[i] += 1
        adj[fill[j]] = i
        wts[fill[j]] = w
        fill[j] += 1
  return starts, adj, wts


@nb.njit(inline="always")
def _component_seed(pts, nrm, starts, adj, s, seen, queue):
  """Mark the component of s as seen (breadth first into queue); return its seed (the point
  farthest from the component's centroid, smallest index on a tie) and the seed's sign
  (+1 where its normal points away from the centroid)."""
  m = pts.shape[0]
  seen[s] = True
  size = 1
  head = 0
  queue[0] = s
  cx = 0.0
  cy = 0.0
  cz = 0.0
  while head < size:
    v = queue[head]
    head += 1
    cx += pts[v, 0]
    cy += pts[v, 1]
    cz += pts[v, 2]
    for e in range(starts[v], starts[v + 1]):
      u = adj[e]
      if not seen[u]:
        seen[u] = True
        queue[size] = u
        size += 1
  cx /= size
  cy /= size
  cz /= size
  best = -1.0
  seed = m
  for h in range(size):
    v = queue[h]
    d = (pts[v, 0] - cx) ** 2 + (pts[v, 1] - cy) ** 2 + (pts[v, 2] - cz) ** 2
    if d > best or (d == best and v < seed):
      best = d
      seed = v
  out = (nrm[seed, 0] * (pts[seed, 0] - cx) + nrm[seed, 1] * (pts[seed, 1] - cy)
         + nrm[seed, 2] * (pts[seed, 2] - cz))
  return seed, 1.0 if out >= 0 else -1.0


@nb.njit(cache=True)
def _propagate_signs(pts, nrm, nbr, sign, label):
  """Hoppe orientation over the symmetrised k-NN graph `nbr` (m, k) of unit normals `nrm`.

  Per connected component: the seed (`_component_seed`) takes the sign that points away from the
  centroid, then Prim's algorithm grows the minimum spanning tree of the weights 1 - |n_i · n_j|
  from it (binary heap with decrease-key) and every node takes its tree parent's sign times
  sign(n_node · n_parent). Writes `sign` (m,) and `label` (m,), the component of each node
  (0, 1, ... in order of each component's smallest index, as `knn_components`), in place.
  """
  m = nbr.shape[0]
  starts, adj, wts = _knn_graph(nrm, nbr)
  seen = np.zeros(m, np.bool_)
  queue = np.empty(m, np.int64)
  key = np.full(m, np.inf)
  parent = np.full(m, -1, np.int64)
  pos = np.full(m, -1, np.int64)  # heap slot; -1 never queued, -2 in the tree
  hk = np.empty(m)
  hv = np.empty(m, np.int64)
  comp = -1
  for s in range(m):
    if seen[s]:
      continue
    comp += 1
    seed, seed_sign = _component_seed(pts, nrm, starts, adj, s, seen, queue)
    sign[seed] = seed_sign
    key[seed] = 0.0
    hk[0] = 0.0
    hv[0] = seed
    pos[seed] = 0
    hs = 1
    while hs > 0:  # Prim
      v = hv[0]
      hs -= 1
      if hs > 0:
        _heap_sift_down(hk, hv, pos, hs)
      pos[v] = -2
      label[v] = comp
      p = parent[v]
      if p >= 0:
        dot = nrm[v, 0] * nrm[p, 0] + nrm[v, 1] * nrm[p, 1] + nrm[v, 2] * nrm[p, 2]
        sign[v] = sign[p] if dot >= 0 else -sign[p]
      for e in range(starts[v], starts[v + 1]):
        u = adj[e]
        pu = pos[u]
        if pu == -2:
          continue
        w = wts[e]
        if w < key[u]:
          key[u] = w
          parent[u] = v
          if pu == -1:
            pu = hs
            hs += 1
          _heap_sift_up(hk, hv, pos, pu, w, u)


def orient_by_propagation(points: np.ndarray, normals: np.ndarray, *, k: int = PROPAGATION_K
                          ) -> np.ndarray:
  """Consistent orientation by minimum-spanning-tree propagation (Hoppe et al. 1992).

  The graph joins every point to its k nearest neighbors (both directions), weighted by
  1 - |n_i · n_j|. Per connected component the seed is the point farthest from the component's
  centroid (smallest index on a tie), oriented away from the centroid (outward for a closed
  surface); the minimum spanning tree is grown from it by Prim's algorithm (one compiled pass)
  and each point takes the sign that agrees with its tree parent. Where several spanning trees
  are minimal (equal weights) the heap's order picks one, deterministically for a given point
  order. Equivariant: the graph, the weights and the seed rule all move with the cloud.

  Args:
    points: (n, 3) cloud.
    normals: (n, 3) unit normals of arbitrary sign; NaN rows are left NaN (and not traversed).
    k: neighbors per point in the graph (the engine's k-NN; ties broken by index).

  Returns:
    (n, 3) float64 consistently oriented normals.

  References:
    Hoppe, DeRose, Duchamp, McDonald, Stuetzle, "Surface reconstruction from unorganized points",
    SIGGRAPH 1992, section 3.3.
  """
  return _propagated(points, normals, k)[0]


def _propagated(points: np.ndarray, normals: np.ndarray, k: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """`orient_by_propagation`: (normals (n, 3), good (g,) indices of the finite normals, labels
  (g,) int64: the component of each, as `knn_components(points[good], k)` numbers them). The
  graph of a cloud whose normals are all finite is the cloud's cached k-NN (`cloud_knn`)."""
  pts = np.asarray(points, np.float64)
  nrm = np.array(normals, np.float64, copy=True)
  idx = np.flatnonzero(np.all(np.isfinite(nrm), axis=1))
  labels = np.zeros(idx.size, np.int64)
  if idx.size == 0:
    return nrm, idx, labels
  kk = min(k + 1, idx.size)
  if idx.size == len(pts):
    sub = np.ascontiguousarray(pts)
    nbr = cloud_knn(sub, kk)[1]
  else:
    sub = np.ascontiguousarray(pts[idx])
    _, nbr = engine.knn(engine.knn_grid(sub, kk), sub, kk)
  sub_n = np.ascontiguousarray(nrm[idx])
  sign = np.ones(idx.size)
  _propagate_signs(sub, sub_n, nbr, sign, labels)
  nrm[idx] = sub_n * sign[:, None]
  return nrm, idx, labels


# Points per connected component whose convexity votes fix its sign (`orient_by_vote`), and the
# vote (a centroid height in units of the vote radius) below which a vote counts as undecided.
VOTE_SAMPLES = 256
VOTE_EPS = 1e-3


def knn_components(points: np.ndarray, k: int = PROPAGATION_K) -> np.ndarray:
  """(n,) int64 connected-component label of every point in the symmetrised k-nearest-neighbor
  graph (each point joined to its k nearest others), labels 0, 1, ... in order of each
  component's smallest point index: the components `orient_by_propagation` orients one by one.
  An empty cloud gives an empty array."""
  from scipy.sparse import coo_matrix
  from scipy.sparse.csgraph import connected_components
  pts = np.asarray(points, np.float64)
  n = len(pts)
  if n == 0:
    return np.zeros(0, np.int64)
  kk = min(k + 1, n)
  _, nbr = engine.knn(engine.knn_grid(pts, kk), pts, kk)
  rows = np.repeat(np.arange(n), kk)
  graph = coo_matrix((np.ones(rows.size), (rows, nbr.ravel())), shape=(n, n))
  _, labels = connected_components(graph, directed=False)
  first = np.full(labels.max() + 1, n, np.int64)
  np.minimum.at(first, labels, np.arange(n))
  rank = np.empty_like(first)
  rank[np.argsort(first, kind="stable")] = np.arange(first.size)
  return rank[labels].astype(np.int64)


def orient_by_vote(points: np.ndarray, normals: np.ndarray, vote_radius: float, *,
                   k: int = PROPAGATION_K, samples: int = VOTE_SAMPLES, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray]:
  """Consistent orientation with a global sign from the points alone: Hoppe propagation
  (`orient_by_propagation`) makes the normals of each connected component agree with each
  other, then each component takes the sign that the majority of its convexity votes picks.

  Vote of a point i (one of the component's `samples` points of smallest
  `neighborhoods.hash_priority(seed, i)`: a subsample that depends on indices and the seed
  only): v_i = -(c_i - p_i) · n_i / vote_radius, with c_i the centroid of the points within
  `vote_radius` of p_i; positive where the surface around p_i lies behind its normal (the
  normal points out of a convex patch: TOLDI's sign rule, Σ (p - q)·n >= 0). The component is
  flipped where Σ v_i < 0. A single patch's convexity is a weak cue (saddles, flat parts, the
  cut edges of a partial scan flip it); thousands of patches tied together by the propagation
  are a strong one. Equivariant: the graph, the propagation, the subsample and the votes all
  move with the cloud.

  Args:
    points: (n, 3) cloud.
    normals: (n, 3) unit normals of arbitrary sign; NaN rows stay NaN.
    vote_radius: radius of the convexity votes (cloud units; lrf_net_plus uses its support
      radius r).
    k: neighbors per point of the propagation graph.
    samples: votes per component (all of its points when it has fewer).
    seed: seed of the vote subsample.

  Returns:
    (normals (n, 3) float64, trust (n,) float64): trust is the component's vote margin
    |Σ v_i| / (Σ |v_i| + VOTE_EPS · n_votes) in [0, 1] (0: the votes cancel or vanish, e.g. a
    plane; 1: unanimous and decisive), 0 where the normal is NaN.

  References:
    Hoppe, DeRose, Duchamp, McDonald, Stuetzle, "Surface reconstruction from unorganized points",
    SIGGRAPH 1992, section 3.3 (the propagation); Yang et al., "TOLDI", Pattern
    Recognition 2017 (the sign rule of one patch).
  """
  from lrf_jax.search.neighborhoods import SearchIndex, hash_priority
  pts = np.asarray(points, np.float64)
  nrm, good, labels = _propagated(pts, normals, k)  # labels: the components it walked
  trust = np.zeros(len(pts))
  if good.size == 0:
    return nrm, trust
  order = np.lexsort((hash_priority(int(seed), good), labels))
  start = np.searchsorted(labels[order], np.arange(labels.max() + 1))
  rank = np.arange(good.size) - np.repeat(start, np.diff(np.r_[start, good.size]))
  voters = order[rank < int(samples)]  # positions in `good`
  centers = pts[good[voters]]
  _, offset, _ = engine.ball_stats(SearchIndex(pts, 0).grid(float(vote_radius)), centers,
                                   float(vote_radius))
  votes = -np.einsum("nc,nc->n", offset, nrm[good[voters]]) / float(vote_radius)
  total = np.bincount(labels[voters], votes, labels.max() + 1)
  size = np.bincount(labels[voters], np.abs(votes), labels.max() + 1)
  flip = np.where(total < 0, -1.0, 1.0)
  nrm[good] *= flip[labels][:, None]
  count = np.bincount(labels[voters], None, labels.max() + 1)
  trust[good] = (np.abs(total) / (size + VOTE_EPS * count))[labels]
  return nrm, trust
