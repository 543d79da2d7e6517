"""Matching in descriptor space: nearest neighbor with Lowe's ratio score (jnp, blocked).

For each query descriptor the nearest and second-nearest reference descriptors in the L2 distance
are found; the match is (query, nearest) with the score ratio = d1 / d2 in [0, 1] (smaller = more
distinctive). Recall vs 1-precision curves threshold this ratio (`lrf_jax.evaluation.description`),
correspondence selection keeps the matches of smallest ratio (`lrf_jax.registration`).

`select_correspondences` is the general selection: each query's k nearest references, mutual
nearest neighbors, Lowe's ratio test, capped at n, best first. Every search is exact. Two
searches give the same neighbors:

* "dense": blocked over the queries, one jitted distance block (a matrix product) per block (the
  mutual check's reverse nearest queries come from the same block); its float32 expansion
  |q|^2 + |r|^2 - 2 q.r rounds at about 1e-7 |q|^2, which can swap near ties of large
  descriptors;
* "occupancy", for descriptors whose entries are either one "empty" value far from all the
  others or lie in a narrow interval (TOLDI's depth images: empty pixels 100, depths in [0, 1]):
  the entries where exactly one of two descriptors is empty, counted on bit masks
  (`_occupancy_knn_kernel`), bound the distance from below and above, so only the references
  those bounds cannot rule out get their exact distance, summed in float64 (on scans, a few per
  query instead of all of them). `search="auto"` (the default) takes it when the descriptors
  have that form (`_occupancy_form`).

Robustness (none of it changes a result on ordinary descriptors): a row holding NaN or inf is
invalid, as if its valid flag were False (it never matches and is never matched); descriptors
whose typical size (the median over the valid rows of their largest entry) lies outside
[2^-20, 2^20] are searched scaled by a power of two that brings it to [0.5, 1) (`_unit`), an
exact scaling: the same matches and ratios as at scale 1, where float32 squares of 1e19 would
overflow and those of 1e-20 vanish; a distance that overflows anyway (a row far larger than
the others) counts as infinite, never as NaN; and `k` is capped at the number of valid
references (the mutual check's queries at the number of valid queries).

References:
  Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004 (the ratio test);
  Tombari et al. 2010 and Guo et al. 2016 (its use for recall vs 1-precision).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

from lrf_jax._jax import jax, jit, jnp
import numba as nb
import numpy as np

from lrf_jax.search.bits import pack_rows, popcount
from lrf_jax.search.grid import num_threads
from lrf_jax.search.nearest import insert_sorted


class Matches(NamedTuple):
  """Nearest-neighbor matches of queries into references.

  Attributes:
    nearest: (m,) int32 index of the nearest valid reference (-1 where the query is invalid or
      there is no valid reference).
    distance: (m,) float32 L2 distance to it (inf where none).
    ratio: (m,) float32 d1 / d2 (1 where there is a single valid reference; inf where none).
  """

  nearest: np.ndarray
  distance: np.ndarray
  ratio: np.ndarray


def _d2(query: jax.Array, ref: jax.Array, ref_ok: jax.Array) -> jax.Array:
  """(b, n) squared L2 distances, inf where the reference is invalid or the expansion is NaN
  (float32 overflow of a row far larger than the others: inf - inf)."""
  q2 = jnp.sum(query * query, axis=1)
  r2 = jnp.sum(ref * ref, axis=1)
  d2 = q2[:, None] + r2[None, :] - 2.0 * query @ ref.T
  return jnp.where(ref_ok[None, :] & ~jnp.isnan(d2), jnp.maximum(d2, 0.0), jnp.inf)


@jit(static_argnames="k")
def _block(query: jax.Array, ref: jax.Array, ref_ok: jax.Array, k: int = 2
           ) -> tuple[jax.Array, jax.Array]:
  """The k nearest references of each query: squared distances (b, k) and indices (b, k),
  nearest first (equal distances: lower index first, `lax.top_k`'s order)."""
  neg, idx = jax.lax.top_k(-_d2(query, ref, ref_ok), k)
  return -neg, idx


@jit(static_argnames=("k", "kc"))
def _block_both(query: jax.Array, query_ok: jax.Array, ref: jax.Array, ref_ok: jax.Array, k: int,
                kc: int) -> tuple[jax.Array, ...]:
  """`_block`'s k nearest references of each query, and the kc nearest valid queries of the
  block for each reference: squared distances (n, kc) and block-local indices (n, kc)."""
  d2 = _d2(query, ref, ref_ok)
  neg, idx = jax.lax.top_k(-d2, k)
  neg_c, idx_c = jax.lax.top_k(-jnp.where(query_ok[:, None], d2, jnp.inf).T, kc)
  return -neg, idx, -neg_c, idx_c


def _check_inputs(query, reference, query_valid, reference_valid):
  """float32 descriptors and bool valid flags; a row holding NaN or inf is invalid (and zeroed,
  so that it cannot turn another row's distances into NaN)."""
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
  q, qv = _finite_rows(q, qv)
  r, rv = _finite_rows(r, rv)
  return q, r, qv, rv


def _finite_rows(x: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """`x` and `valid` as they are when every row is finite; else copies with the other rows
  zeroed and invalid."""
  finite = np.isfinite(x).all(axis=1)
  if finite.all():
    return x, valid
  return np.where(finite[:, None], x, np.float32(0.0)), valid & finite


# `_unit`: descriptors whose typical size lies in this range are searched as they are.
UNIT_RANGE = (2.0 ** -20, 2.0 ** 20)


def _unit(q: np.ndarray, r: np.ndarray, qv: np.ndarray, rv: np.ndarray) -> float:
  """The power of two u the descriptors are searched in units of (the search sees x / u): 1
  when their typical size (the median over the valid rows of the largest absolute entry) lies
  in `UNIT_RANGE` or is 0, else 2^e with the size / 2^e in [0.5, 1). Dividing by a power of two
  is exact, so the neighbors and ratios do not depend on a common scale of the descriptors."""
  sizes = np.concatenate([np.abs(x[v]).max(axis=1) for x, v in ((q, qv), (r, rv))
                          if v.any() and x.shape[1]])
  sizes = sizes[sizes > 0]
  if not len(sizes):
    return 1.0
  size = float(np.median(sizes))
  if UNIT_RANGE[0] <= size <= UNIT_RANGE[1]:
    return 1.0
  return float(np.ldexp(1.0, int(np.frexp(size)[1])))


def _in_units(x: np.ndarray, unit: float) -> np.ndarray:
  return x if unit == 1.0 else (x / np.float32(unit)).astype(np.float32)


def _distance(d2: np.ndarray, unit: float) -> np.ndarray:
  """L2 distances in the descriptors' units from squared ones in `unit`s (float32, as before
  for unit 1)."""
  if unit == 1.0:
    return np.sqrt(d2)
  return (np.sqrt(d2.astype(np.float64)) * unit).astype(np.float32)


def _pad_rows(a: np.ndarray, rows: int) -> np.ndarray:
  if len(a) >= rows:
    return a
  return np.concatenate([a, np.zeros((rows - len(a),) + a.shape[1:], a.dtype)])


def _nearest(q: np.ndarray, r: np.ndarray, qv: np.ndarray, rv: np.ndarray, k: int, kc: int,
             block: int, search: str = "auto") -> tuple[np.ndarray, ...]:
  """Exact search, m >= 1 queries and at least one valid reference: the occupancy search where
  `search` asks for it or is "auto" and the descriptors have its form (`_occupancy_form`), else
  the dense blocks (`_nearest_dense`, whose returns these are).

  Raises:
    ValueError: search="occupancy" on descriptors without that form.
  """
  form = None if search == "dense" else _occupancy_form(q, r, qv, rv)
  if form is None:
    if search == "occupancy":
      raise ValueError("search='occupancy': the descriptors' valid entries are not one empty "
                       f"value far above an interval of the others (gap >= {OCCUPANCY_GAP:g} x "
                       "the interval); use search='dense' or 'auto'")
    return _nearest_dense(q, r, qv, rv, k, kc, block)
  q_bits, r_bits = _occupancy_bits(q, form[0]), _occupancy_bits(r, form[0])
  d2, idx = _occupancy_knn(q, r, q_bits, r_bits, qv, rv, k, form)
  if not kc:
    return d2, idx
  return (d2, idx) + _occupancy_knn(r, q, r_bits, q_bits, rv, qv, kc, form)


def _nearest_dense(q: np.ndarray, r: np.ndarray, qv: np.ndarray, rv: np.ndarray, k: int, kc: int,
                   block: int) -> tuple[np.ndarray, ...]:
  """Blocked exact search, m >= 1 queries and at least one valid reference.

  Returns:
    (d2 (m, k) float32, idx (m, k) int32): the k nearest valid references of every query
    (inf and an arbitrary index past the valid ones); with kc > 0 also (d2c (n, kc), idxc
    (n, kc) int64): the kc nearest valid queries of every reference, equal distances by lower
    query index.
  """
  m = len(q)
  ref = _pad_rows(r, k)  # top_k needs k columns: pad with invalid references
  rv_pad = _pad_rows(rv, k)
  ref_j, rv_j = jax.device_put(ref), jax.device_put(rv_pad)
  b = max(min(block, m), kc)
  d2 = np.empty((m, k), np.float32)
  idx = np.empty((m, k), np.int32)
  cols_d, cols_i = [], []
  for s in range(0, m, b):
    qb, n_real = _pad_rows(q[s:s + b], b), min(b, m - s)
    if kc:
      qok = _pad_rows(qv[s:s + b], b)
      out = [np.asarray(a) for a in _block_both(qb, qok, ref_j, rv_j, k=k, kc=kc)]
      cols_d.append(out[2][:len(r)])
      cols_i.append(out[3][:len(r)].astype(np.int64) + s)
    else:
      out = [np.asarray(a) for a in _block(qb, ref_j, rv_j, k=k)]
    d2[s:s + n_real], idx[s:s + n_real] = out[0][:n_real], out[1][:n_real]
  if not kc:
    return d2, idx
  # Merge the blocks' candidates: a stable sort keeps equal distances in query order.
  cd, ci = np.concatenate(cols_d, axis=1), np.concatenate(cols_i, axis=1)
  order = np.argsort(cd, axis=1, kind="stable")[:, :kc]
  return d2, idx, np.take_along_axis(cd, order, 1), np.take_along_axis(ci, order, 1)


# ------------------------------------------------------------------------------------------------
# The occupancy search: exact nearest neighbors of descriptors with an "empty" value
# ------------------------------------------------------------------------------------------------

# `_occupancy_form`: the empty value must lie at least OCCUPANCY_GAP times the spread of the other
# entries beyond them, so that the bounds of `_occupancy_knn_kernel` are within a few per cent of
# each other (TOLDI: 99 / 1); below that the dense block is used.
OCCUPANCY_GAP = 50.0
SEARCHES = ("auto", "dense", "occupancy")


@nb.njit(cache=True, nogil=True)
def _occupancy_knn_kernel(a_bits, b_bits, a, b, a_ok, b_ok, k, lower, upper, spread, out_d2,
                          out_idx, start, stop, h, counts, bd, bi):
  """The k nearest valid rows of `b` for the valid rows start..stop-1 of `a` (squared L2, ties:
  lower index). Serial and without the GIL: `_occupancy_knn` runs it on row blocks in threads
  (a `parallel=True` kernel compiles in twice the time on a first run).

  h = the entries where exactly one of two descriptors is empty (popcount of their bit masks'
  XOR). Each such entry adds between `lower` and `upper` to the squared distance, every other
  entry at most `spread`: lower h <= d2 <= upper h + (D - h) spread. The k rows of least h bound
  the k-th distance by U = upper h_k + (D - h_k) spread, so a row with lower h > U is never among
  the k nearest; the others get their exact distance (float64 sums). h (n,), counts (D + 2,),
  bd (k,) and bi (k,) are the caller's scratch (int64, int64, float64, int64): no allocation
  here.
  """
  n, dim = b.shape[0], a.shape[1]
  never = np.int64(1) << 62
  for i in range(start, stop):
    if not a_ok[i]:
      continue
    valid = 0
    for j in range(n):
      h[j] = never
      if b_ok[j]:
        c = 0
        for w in range(a_bits.shape[1]):
          c += popcount(a_bits[i, w] ^ b_bits[j, w])  # type: ignore[call-arg]  # numba intrinsic
        h[j] = c
        valid += 1
    if valid == 0:
      continue
    counts[:] = 0  # h_k, the k-th least h, by counting
    for j in range(n):
      counts[min(h[j], dim + 1)] += 1
    hk, seen = 0, counts[0]
    while seen < min(k, valid):
      hk += 1
      seen += counts[hk]
    bound = (upper * hk + (dim - hk) * spread) * (1.0 + 1e-9)
    bd[:] = np.inf
    bi[:] = 0
    for j in range(n):
      if h[j] == never or lower * h[j] > bound:
        continue
      d2 = 0.0
      for t in range(dim):
        diff = np.float64(a[i, t]) - np.float64(b[j, t])
        d2 += diff * diff
      insert_sorted(bd, bi, k, d2, j)
    for s in range(k):
      out_d2[i, s] = bd[s]
      out_idx[i, s] = bi[s] if bd[s] < np.inf else 0


def _occupancy_form(q: np.ndarray, r: np.ndarray, qv: np.ndarray, rv: np.ndarray
                    ) -> tuple[float, float, float] | None:
  """(empty, lo, hi) when every valid descriptor entry is either `empty` (the largest value) or
  in [lo, hi], with empty - hi >= OCCUPANCY_GAP (hi - lo) and both kinds present; else None.

  Row reductions only (a boolean-mask copy of the entries took most of the time): lo from the
  rows' minima (`empty` is the largest value, so a row's minimum is its least other entry when
  it has one); hi from the rows' maxima after the `empty` entries are moved below every entry
  (x - [x == empty] * far subtracts an exact 0 from the others). None where a valid entry is not
  finite."""
  sides = [(x, v) for x, v in ((q, qv), (r, rv)) if v.any()]
  if not sides:
    return None
  top = [x.max(axis=1)[v] for x, v in sides]  # NaN in a row whose entries hold one
  if not all(np.isfinite(t).all() for t in top):
    return None
  empty = max(float(t.max()) for t in top)
  lo, hi = np.inf, -np.inf
  for x, v in sides:
    low = x.min(axis=1)[v]
    filled = low < empty
    if not filled.any():
      continue
    lo = min(lo, float(low[filled].min()))
    far = 2.0 * (abs(empty) + abs(lo)) + 1.0  # empty - far lies below every entry of x
    if not np.isfinite(np.asarray(far, x.dtype)):
      return None
    top = (x - (x == empty) * x.dtype.type(far)).max(axis=1)[v]
    hi = max(hi, float(top[filled].max()))
  if not np.isfinite(lo) or empty - hi < OCCUPANCY_GAP * (hi - lo) or empty <= hi:
    return None
  return empty, lo, hi


def _occupancy_bits(x: np.ndarray, empty: float) -> np.ndarray:
  """(m, ceil(D / 64)) uint64 masks of the entries equal to `empty`."""
  return pack_rows(x == empty)


def _occupancy_knn(a, b, a_bits, b_bits, a_ok, b_ok, k, form) -> tuple[np.ndarray, np.ndarray]:
  """`_occupancy_knn_kernel` on float32 rows and their `_occupancy_bits`, on the engine's threads
  (`search.grid.num_threads`): (d2 (m, k) float64, idx (m, k) int64), inf and index 0 past the
  valid rows (and for invalid rows of `a`)."""
  empty, lo, hi = form
  lower = (empty - hi) ** 2
  upper = (empty - lo) ** 2
  d2 = np.full((len(a), k), np.inf)
  idx = np.zeros((len(a), k), np.int64)
  args = (a_bits, b_bits, a, b, np.ascontiguousarray(a_ok), np.ascontiguousarray(b_ok), int(k),
          lower, upper, (hi - lo) ** 2, d2, idx)
  threads = max(1, min(num_threads(), len(a) // 64))
  edges = np.linspace(0, len(a), threads + 1).astype(np.int64)

  def block(start: int, stop: int) -> None:
    _occupancy_knn_kernel(*args, start, stop, np.empty(len(b), np.int64),
                          np.empty(a.shape[1] + 2, np.int64), np.empty(k), np.empty(k, np.int64))

  if threads == 1:
    block(0, len(a))
  else:
    with ThreadPoolExecutor(threads) as pool:
      list(pool.map(lambda se: block(*se), zip(edges[:-1], edges[1:])))
  return d2, idx


def _ratio(d1: np.ndarray, d_2: np.ndarray) -> np.ndarray:
  """d1 / d2, 1 where there is no second reference (d2 inf) or d2 is 0."""
  with np.errstate(divide="ignore", invalid="ignore"):
    return np.where(np.isinf(d_2), 1.0, np.where(d_2 > 0, d1 / d_2, 1.0))


def match_descriptors(query: np.ndarray, reference: np.ndarray, query_valid=None,
                      reference_valid=None, *, block: int = 1024, search: str = "auto"
                      ) -> Matches:
  """Nearest and second-nearest reference of every query descriptor (L2), with the ratio score.

  Args:
    query: (m, D) descriptors.
    reference: (n, D) descriptors.
    query_valid (np.ndarray | None): (m,) bool (None: all valid); a row holding NaN or inf is
      invalid too.
    reference_valid (np.ndarray | None): (n,) bool (None: all valid); invalid references (and
      rows holding NaN or inf) are never matched.
    block: queries per jitted call of the dense search (memory: block x n floats).
    search: "auto" (default: the occupancy search for descriptors of its form, such as TOLDI's,
      else the dense one), "dense" or "occupancy" (the module docstring); all exact, they
      differ only in float rounding of the distances.

  Returns:
    `Matches` for the m queries.

  Raises:
    ValueError: non-2-D inputs or different descriptor lengths, an unknown `search`, or
      search="occupancy" on descriptors without its form.
  """
  q, r, qv, rv = _check_inputs(query, reference, query_valid, reference_valid)
  m = len(q)
  nearest = np.full(m, -1, np.int32)
  dist = np.full(m, np.inf, np.float32)
  ratio = np.full(m, np.inf, np.float32)
  if m == 0 or not rv.any():
    return Matches(nearest, dist, ratio)
  _check_search(search)
  unit = _unit(q, r, qv, rv)
  d2, idx = _nearest(_in_units(q, unit), _in_units(r, unit), qv, rv, 2, 0, block, search)
  nearest[:] = idx[:, 0]
  dist[:] = np.sqrt(d2[:, 0])  # float32 (the occupancy search's float64 rounded), in units
  ratio[:] = _ratio(dist, np.sqrt(d2[:, 1]))
  if unit != 1.0:
    dist[:] = _distance(d2[:, 0], unit)
  none = ~qv | ~np.isfinite(d2[:, 0])  # invalid, or no reference at a finite distance
  nearest[none] = -1
  dist[none] = np.inf
  ratio[none] = np.inf
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


def _check_search(search) -> None:
  if not isinstance(search, str) or search not in SEARCHES:
    raise ValueError(f"search: expected one of {SEARCHES}, got {search!r}")


def _option_int(value, name: str, least: int) -> int:
  if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
      or value < least:
    raise ValueError(f"{name}: expected an integer >= {least}, got {value!r}")
  return int(value)


def _check_options(n, mutual, ratio, k, block) -> tuple[int | None, float | None, int]:
  k = _option_int(k, "k", 1)
  _option_int(block, "block", 1)
  n = None if n is None else _option_int(n, "n", 0)
  if not isinstance(mutual, (bool, np.bool_)):
    raise ValueError(f"mutual: expected True or False, got {mutual!r}")
  if ratio is not None:
    try:
      ratio = float(ratio)
    except (TypeError, ValueError):
      raise ValueError(f"ratio: expected a number in (0, 1] or None, got {ratio!r}") from None
    if not 0.0 < ratio <= 1.0:  # NaN fails too
      raise ValueError(f"ratio: expected a number in (0, 1] or None, got {ratio!r}")
    if k != 1:
      raise ValueError(f"ratio: Lowe's ratio test keeps one match per query and needs k=1, got "
                       f"k={k}")
  return n, ratio, k


def select_correspondences(query: np.ndarray, reference: np.ndarray, query_valid=None,
                           reference_valid=None, *, n: int | None = None, mutual: bool = False,
                           ratio: float | None = None, k: int = 1, block: int = 1024,
                           search: str = "auto"
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Correspondences between two descriptor sets (L2), best first.

  Every valid query proposes its k nearest valid references (equal distances: lower reference
  index first). Options filter the proposals:

  * `mutual=True`: keep (i, j) only when i is also among the k nearest valid queries of
    reference j (equal distances: lower query index first); for k=1, the mutual nearest
    neighbors.
  * `ratio=t` (k=1 only): Lowe's ratio test, keep (i, j) when d1 / d2 < t, d1 and d2 the
    distances to the nearest and second-nearest valid references (d1 / d2 = 1 when there is a
    single valid reference or d2 = 0, so such a query never passes).

  With k=1 the correspondences are ordered by ratio d1 / d2, then distance, then query index
  (`top_correspondences`'s order: `select_correspondences(q, r, n=N)` is
  `top_correspondences(match_descriptors(q, r), N)`, up to the float32 rounding of the ratios
  that `Matches` holds); with k > 1 by distance, then query
  index, then reference index.

  Args:
    query: (m, D) descriptors.
    reference: (r, D) descriptors.
    query_valid (np.ndarray | None): (m,) bool (None: all valid); invalid queries (and rows
      holding NaN or inf) propose nothing.
    reference_valid (np.ndarray | None): (r,) bool (None: all valid); invalid references (and
      rows holding NaN or inf) are never matched.
    n: keep at most this many, the best (None: all).
    mutual: keep mutual nearest neighbors only.
    ratio: the ratio-test threshold in (0, 1] (None: no test).
    k: proposals per query (fewer where fewer valid references exist: k is capped at their
      number).
    block: queries per jitted call of the dense search (memory: block x r floats).
    search: "auto" (default), "dense" or "occupancy", as `match_descriptors`.

  Returns:
    (query_idx (c,) int64, reference_idx (c,) int64, score (c,) float32), best first: score is
    the ratio d1 / d2 for k=1, the L2 distance for k > 1.

  Raises:
    ValueError: inputs as `match_descriptors`; k, n or block not integers (k, block >= 1,
      n >= 0), a ratio outside (0, 1], a ratio with k > 1, a non-boolean `mutual`, or a
      `search` as `match_descriptors`.
  """
  q, r, qv, rv = _check_inputs(query, reference, query_valid, reference_valid)
  n, ratio, k = _check_options(n, mutual, ratio, k, block)
  if len(q) == 0 or not rv.any() or not qv.any():
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
  _check_search(search)
  # proposals past the valid references (and, for the mutual check, queries past the valid
  # ones) are never kept: capped, a large k costs no memory (the mutual check's m x k x k)
  kc = min(k, int(qv.sum())) if mutual else 0
  k = min(k, int(rv.sum()))
  unit = _unit(q, r, qv, rv)
  found = _nearest(_in_units(q, unit), _in_units(r, unit), qv, rv, max(k, 2), kc, block,
                   search)
  d2, idx = found[0][:, :k], found[1][:, :k].astype(np.int64)
  ok = np.isfinite(d2) & qv[:, None]
  if mutual:  # i among the k nearest queries of its reference
    back = found[3][np.where(ok, idx, 0)]  # (m, k, kc)
    ok &= (back == np.arange(len(q))[:, None, None]).any(axis=2)
  dist = np.sqrt(d2)
  if k == 1:
    score = _ratio(dist, np.sqrt(found[0][:, 1:2]))  # float64 from the occupancy search
    if ratio is not None:
      ok &= score < ratio
  qi, slot = np.nonzero(ok)
  ri = idx[qi, slot]
  if k == 1:
    score, dist = score[qi, 0], dist[qi, 0]
    order = np.lexsort((qi, dist, score))
  else:
    score = _distance(d2[qi, slot], unit)
    order = np.lexsort((ri, qi, d2[qi, slot]))
  order = order if n is None else order[:n]
  return qi[order].astype(np.int64), ri[order], score[order].astype(np.float32)
