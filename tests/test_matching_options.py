"""Correspondence selection (`select_correspondences`): top-k, mutual nearest neighbors and
Lowe's ratio test against a brute-force numpy reference."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lrf_jax.descriptors.matching import (_occupancy_form, match_descriptors,
                                          select_correspondences, top_correspondences)


def reference_select(q, r, qv=None, rv=None, *, n=None, mutual=False, ratio=None, k=1):
  """The definition, brute force in float64 with stable sorts (lower index first on ties)."""
  q, r = np.asarray(q, np.float64), np.asarray(r, np.float64)
  qv = np.ones(len(q), bool) if qv is None else np.asarray(qv, bool)
  rv = np.ones(len(r), bool) if rv is None else np.asarray(rv, bool)
  d2 = ((q[:, None, :] - r[None, :, :]) ** 2).sum(-1)
  d2[:, ~rv] = np.inf
  d2_back = d2.copy()
  d2_back[~qv, :] = np.inf

  def nearest(row, kk):
    order = np.argsort(row, kind="stable")[:kk]
    return [int(j) for j in order if np.isfinite(row[j])]

  rows = []
  for i in np.flatnonzero(qv):
    near = nearest(d2[i], max(k, 2))
    if not near:
      continue
    d1 = np.sqrt(d2[i, near[0]])
    if len(near) < 2:
      rt = 1.0
    else:
      dd = np.sqrt(d2[i, near[1]])
      rt = d1 / dd if dd > 0 else 1.0
    if ratio is not None and not rt < ratio:
      continue
    for j in near[:k]:
      if mutual and i not in nearest(d2_back[:, j], k):
        continue
      dist = np.sqrt(d2[i, j])
      key = (rt, dist, i) if k == 1 else (dist, i, j)
      rows.append((key, i, j, rt if k == 1 else dist))
  rows.sort(key=lambda t: t[0])
  rows = rows if n is None else rows[:n]
  return (np.array([t[1] for t in rows], np.int64), np.array([t[2] for t in rows], np.int64),
          np.array([t[3] for t in rows], np.float64))


def _check(q, r, qv=None, rv=None, block=1024, rtol=1e-5, search="auto", **opts):
  qi, ri, score = select_correspondences(q, r, qv, rv, block=block, search=search, **opts)
  eqi, eri, escore = reference_select(q, r, qv, rv, **opts)
  assert qi.dtype == np.int64 and ri.dtype == np.int64 and score.dtype == np.float32
  np.testing.assert_array_equal(qi, eqi, err_msg=str(opts))
  np.testing.assert_array_equal(ri, eri, err_msg=str(opts))
  np.testing.assert_allclose(score, escore, rtol=rtol, atol=1e-6, err_msg=str(opts))
  return qi


OPTIONS = [dict(mutual=m, ratio=t, k=1, n=n) for m, t, n in
           itertools.product([False, True], [None, 0.9], [None, 25])]
OPTIONS += [dict(mutual=m, k=kk, n=n) for m, kk, n in
            itertools.product([False, True], [2, 5], [None, 40])]


@pytest.mark.parametrize("opts", OPTIONS, ids=str)
def test_random_descriptors_with_invalid_rows(opts):
  rng = np.random.default_rng(0)
  q, r = rng.normal(size=(150, 12)), rng.normal(size=(190, 12))
  qv, rv = rng.random(150) > 0.15, rng.random(190) > 0.15
  assert len(_check(q, r, qv, rv, **opts)) > 0
  assert len(_check(q, r, qv, rv, block=37, **opts)) > 0  # several blocks, a ragged last one


@pytest.mark.parametrize("opts", OPTIONS, ids=str)
def test_ties_between_equal_descriptors(opts):
  """Small integer descriptors: exact float32 distances, many exact ties, duplicate rows."""
  rng = np.random.default_rng(1)
  q = rng.integers(0, 3, (90, 5)).astype(np.float32)
  r = rng.integers(0, 3, (70, 5)).astype(np.float32)
  r[10:20] = r[0]  # duplicated references
  q[30:40] = q[5]  # duplicated queries
  qv, rv = rng.random(90) > 0.1, rng.random(70) > 0.1
  _check(q, r, qv, rv, **opts)
  _check(q, r, qv, rv, block=8, **opts)  # ties across blocks of the mutual search


def test_k_larger_than_the_valid_references():
  rng = np.random.default_rng(2)
  q, r = rng.normal(size=(20, 6)), rng.normal(size=(7, 6))
  rv = np.array([True, False, True, True, False, False, True])
  qi, ri, _ = select_correspondences(q, r, None, rv, k=10)
  assert len(qi) == 20 * 4 and set(ri.tolist()) <= {0, 2, 3, 6}
  _check(q, r, None, rv, k=10)
  _check(q, r, None, rv, k=10, mutual=True)
  _check(q[:3], r, None, rv, k=6, mutual=True)  # fewer queries than k
  _check(q, r[:1], k=1)  # a single reference: ratio 1
  assert len(select_correspondences(q, r[:1], ratio=1.0)[0]) == 0


def test_n_caps_and_larger_n_keeps_all():
  rng = np.random.default_rng(3)
  q, r = rng.normal(size=(60, 8)), rng.normal(size=(80, 8))
  every = select_correspondences(q, r, k=3)
  assert len(every[0]) == 180
  for a, b in zip(select_correspondences(q, r, k=3, n=10 ** 6), every):
    np.testing.assert_array_equal(a, b)
  for a, b in zip(select_correspondences(q, r, k=3, n=17), every):
    np.testing.assert_array_equal(a, b[:17])
  assert all(len(a) == 0 for a in select_correspondences(q, r, n=0))


def test_k1_equals_top_correspondences():
  rng = np.random.default_rng(4)
  q, r = rng.normal(size=(300, 16)), rng.normal(size=(250, 16))
  qv, rv = rng.random(300) > 0.2, rng.random(250) > 0.2
  m = match_descriptors(q, r, qv, rv)
  for n in (1, 50, 1000):
    qi, ri, score = select_correspondences(q, r, qv, rv, n=n)
    eqi, eri = top_correspondences(m, n)
    np.testing.assert_array_equal(qi, eqi)
    np.testing.assert_array_equal(ri, eri)
    np.testing.assert_array_equal(score, m.ratio[qi])


def test_filters_are_subsets():
  rng = np.random.default_rng(5)
  q, r = rng.normal(size=(200, 10)), rng.normal(size=(200, 10))
  r[:100] = q[:100] + 0.05 * rng.normal(size=(100, 10))  # 100 true matches
  pairs = lambda out: set(zip(out[0].tolist(), out[1].tolist()))
  every = pairs(select_correspondences(q, r))
  mutual = pairs(select_correspondences(q, r, mutual=True))
  lowe = pairs(select_correspondences(q, r, ratio=0.8))
  assert mutual < every and lowe < every
  assert {(i, i) for i in range(100)} <= mutual & lowe
  assert pairs(select_correspondences(q, r, mutual=True, ratio=0.8)) == mutual & lowe


def test_nothing_to_match():
  q = np.zeros((4, 3))
  for out in (select_correspondences(q, q, None, np.zeros(4, bool)),
              select_correspondences(q, q, np.zeros(4, bool), None, mutual=True),
              select_correspondences(np.zeros((0, 3)), q, k=3)):
    assert [len(a) for a in out] == [0, 0, 0]
    assert out[0].dtype == np.int64 and out[2].dtype == np.float32


def _occupancy_like(rng, m, dim=70, empty=100.0, levels=None):
  """Descriptors of TOLDI's form: entries in [0, 1] (or `levels` values in it: exact ties) or
  `empty`, empty entries clustered towards the end of each row as a depth image's rim."""
  x = (rng.random((m, dim)) if levels is None
       else rng.integers(0, levels, (m, dim)) / (levels - 1)).astype(np.float32)
  rim = rng.integers(dim // 3, dim, m)
  x[np.arange(dim)[None, :] >= rim[:, None]] = empty
  x[rng.random((m, dim)) < 0.1] = empty
  return x


@pytest.mark.parametrize("opts", OPTIONS, ids=str)
@pytest.mark.parametrize("search", ["occupancy", "auto"])
def test_occupancy_descriptors_search(opts, search):
  """Descriptors with an empty value: the occupancy search (auto's choice) gives the brute-force
  reference's matches (its bounds may not drop a true neighbor). The dense search's float32
  expansion |q|^2 + |r|^2 - 2 q.r rounds at ~1e-7 |q|^2 and swaps near ties on such data, which
  is why auto does not use it there."""
  rng = np.random.default_rng(6)
  q, r = _occupancy_like(rng, 160), _occupancy_like(rng, 140)
  r[:60] = np.where(q[:60] == 100, 100, np.clip(q[:60] + 0.02 * rng.normal(size=(60, 70)), 0, 1))
  qv, rv = rng.random(160) > 0.15, rng.random(140) > 0.15
  assert _occupancy_form(q, r, qv, rv)[0] == 100.0
  assert len(_check(q, r, qv, rv, search=search, **opts)) > 0


@pytest.mark.parametrize("opts", OPTIONS, ids=str)
def test_occupancy_search_ties(opts):
  """Exact ties (depths on a 3-level grid, duplicated rows): lower index first, as the
  reference's stable sort."""
  rng = np.random.default_rng(7)
  q, r = _occupancy_like(rng, 90, dim=20, levels=3), _occupancy_like(rng, 70, dim=20, levels=3)
  r[10:20] = r[0]
  q[30:40] = q[5]
  qv, rv = rng.random(90) > 0.1, rng.random(70) > 0.1
  _check(q, r, qv, rv, search="occupancy", **opts)


def test_occupancy_form_is_detected_only_where_it_holds():
  rng = np.random.default_rng(8)
  q, r = _occupancy_like(rng, 30), _occupancy_like(rng, 20)
  ok_q, ok_r = np.ones(30, bool), np.ones(20, bool)
  form = _occupancy_form(q, r, ok_q, ok_r)
  assert form[0] == 100.0 and 0.0 <= form[1] < form[2] <= 1.0
  odd = q.copy()
  odd[:5] = -5.0  # invalid rows are not looked at
  assert _occupancy_form(odd, r, np.arange(30) >= 5, ok_r) == _occupancy_form(q[5:], r, ok_q[5:],
                                                                             ok_r)
  near = q.copy()
  near[0, 0] = 60.0  # an entry between the interval and the empty value
  assert _occupancy_form(near, r, ok_q, ok_r) is None
  g = rng.normal(size=(30, 70))
  assert _occupancy_form(g, g, ok_q, ok_q) is None
  full = np.full((30, 70), 100.0)
  assert _occupancy_form(full, full, ok_q, ok_q) is None  # nothing but the empty value
  with pytest.raises(ValueError, match="occupancy.*dense"):
    select_correspondences(g, g, search="occupancy")
  np.testing.assert_array_equal(match_descriptors(g, g[::-1], search="auto").nearest,
                                np.arange(29, -1, -1))


def test_toldi_descriptors_occupancy_equals_the_reference():
  """TOLDI descriptors of a procedural surface: the default (occupancy) search gives the float64
  brute-force matches, ratios included."""
  from lrf_jax.descriptors import compute_descriptors
  rng = np.random.default_rng(9)
  uv = rng.uniform(-1, 1, (3000, 2))
  pts = np.column_stack([uv, 0.3 * np.sin(3 * uv[:, 0]) * np.cos(2 * uv[:, 1])])
  other = pts + 0.002 * rng.normal(size=pts.shape)
  kp = rng.choice(3000, 150, replace=False)
  frames = np.broadcast_to(np.eye(3, dtype=np.float32), (150, 3, 3))
  desc = [compute_descriptors(p, kp, 0.25, frames, np.ones(150, bool), "toldi")
          for p in (pts, other)]
  (dq, vq), (dr, vr) = [(np.asarray(d), np.asarray(v)) for d, v in desc]
  assert _occupancy_form(dq, dr, vq, vr) is not None
  for opts in (dict(n=100), dict(mutual=True), dict(k=3)):
    _check(dq, dr, vq, vr, **opts)


@pytest.mark.parametrize("kwargs, match", [
    (dict(search="fast"), "search"), (dict(search=None), "search"),
    (dict(k=0), "k"), (dict(k=1.5), "k"), (dict(k=True), "k"),
    (dict(n=-1), "n"), (dict(n=2.0), "n"),
    (dict(ratio=0.0), "ratio"), (dict(ratio=1.5), "ratio"), (dict(ratio=float("nan")), "ratio"),
    (dict(ratio="low"), "ratio"), (dict(ratio=0.8, k=2), "ratio.*k=1"),
    (dict(mutual="yes"), "mutual"), (dict(block=0), "block"),
])
def test_bad_options_raise(kwargs, match):
  q = np.zeros((5, 4))
  with pytest.raises(ValueError, match=match):
    select_correspondences(q, q, **kwargs)


def test_bad_inputs_raise():
  with pytest.raises(ValueError, match="same D"):
    select_correspondences(np.zeros((3, 4)), np.zeros((3, 5)))
  with pytest.raises(ValueError, match="valid flags"):
    select_correspondences(np.zeros((3, 4)), np.zeros((3, 4)), np.ones(2, bool))


def _form_reference(q, r, qv, rv):
  """`_occupancy_form` by its definition, on copies of the valid entries (a valid entry that is
  not finite is neither empty nor in an interval)."""
  rows = [x[v] for x, v in ((q, qv), (r, rv)) if v.any()]
  if not rows or not all(np.isfinite(x).all() for x in rows):
    return None
  empty = max(float(x.max()) for x in rows)
  filled = [f for f in (x[x != empty] for x in rows) if f.size]
  if not filled or not np.isfinite(empty):
    return None
  lo, hi = min(float(f.min()) for f in filled), max(float(f.max()) for f in filled)
  if not np.isfinite(lo) or empty - hi < 50.0 * (hi - lo) or empty <= hi:
    return None
  return empty, lo, hi


@pytest.mark.parametrize("seed", range(6))
def test_occupancy_form_matches_its_definition(seed):
  rng = np.random.default_rng(seed)
  q = rng.uniform(-0.5, 1.0, (40, 24)).astype(np.float32)
  r = rng.uniform(0.0, 1.0, (30, 24)).astype(np.float32)
  for x in (q, r):
    x[rng.random(x.shape) < 0.6] = 100.0
  q[3] = 100.0                       # a row with no other entry
  r[4, 0] = np.nan                   # NaN in a row that may be invalid
  qv, rv = rng.random(40) < 0.8, rng.random(30) < 0.7
  cases = [(q, r, qv, rv), (q, r, qv, rv & (np.arange(30) != 4)), (q * 1e30, r, qv, rv),
           (q, r, np.zeros(40, bool), rv), (np.full_like(q, 100.0), r[:, :24] * 0 + 100.0, qv,
                                             rv), (q - 200.0, r, qv, rv)]
  for c in cases:
    assert _occupancy_form(*c) == _form_reference(*c)


@pytest.mark.parametrize("opts", OPTIONS, ids=str)
@pytest.mark.parametrize("form", ["dense", "occupancy"])
def test_non_finite_rows_never_match_and_never_capture(opts, form):
  """One reference row holding NaN or inf was the nearest neighbor of every query (NaN
  distances), and a NaN query matched with ratio 1.0. A row holding NaN or inf is invalid:
  the result is the reference's on the other rows, on both searches."""
  rng = np.random.default_rng(8)
  if form == "dense":
    q, r = rng.normal(size=(120, 12)).astype(np.float32), rng.normal(size=(100, 12)).astype(
        np.float32)
  else:
    q, r = _occupancy_like(rng, 120), _occupancy_like(rng, 100)
  qv, rv = rng.random(120) > 0.1, rng.random(100) > 0.1
  r[5] = np.nan
  r[6, 2] = np.inf
  r[7, 0] = -np.inf
  q[8] = np.nan
  q[9, 3] = np.inf
  fq, fr = np.isfinite(q).all(axis=1), np.isfinite(r).all(axis=1)
  clean_q, clean_r = np.where(fq[:, None], q, 0), np.where(fr[:, None], r, 0)
  for search in ("dense", "auto"):
    qi, ri, score = select_correspondences(q, r, qv, rv, search=search, **opts)
    eqi, eri, escore = reference_select(clean_q, clean_r, qv & fq, rv & fr, **opts)
    np.testing.assert_array_equal(qi, eqi)
    np.testing.assert_array_equal(ri, eri)
    np.testing.assert_allclose(score, escore, rtol=1e-5, atol=1e-6)
    assert not set(ri.tolist()) & {5, 6, 7} and not set(qi.tolist()) & {8, 9}
  m = match_descriptors(q, r, qv, rv)
  assert (m.nearest[[8, 9]] == -1).all() and np.isinf(m.distance[[8, 9]]).all()
  assert np.isinf(m.ratio[[8, 9]]).all() and not np.isin(m.nearest, [5, 6, 7]).any()


@pytest.mark.parametrize("opts", OPTIONS, ids=str)
@pytest.mark.parametrize("form", ["dense", "occupancy"])
def test_a_common_scale_does_not_change_the_matches(opts, form):
  """Descriptors scaled by 1e19 (float32 squares overflow: every distance NaN) or 1e-20 (squares
  underflow to 0: every distance a tie) matched differently from the same descriptors at scale
  1. The search runs in a power-of-two unit of their size: at a power-of-two scale the result
  is bit-identical (distances scaled), at any other scale it is the reference's."""
  rng = np.random.default_rng(9)
  if form == "dense":
    q = rng.normal(size=(140, 12)).astype(np.float32)
    r = np.concatenate([q[:70] + 0.1 * rng.normal(size=(70, 12)), rng.normal(size=(60, 12))]
                       ).astype(np.float32)
  else:
    q, r = _occupancy_like(rng, 140), _occupancy_like(rng, 130)
    r[:70] = np.where(q[:70] == 100, 100, np.clip(q[:70] + 0.02 * rng.normal(size=(70, 70)), 0,
                                                   1))
  qv, rv = rng.random(140) > 0.1, rng.random(130) > 0.1
  for search in ("dense", "auto"):
    base = select_correspondences(q, r, qv, rv, search=search, **opts)
    assert len(base[0]) > 0
    for e in (63, -66, 100, -100):
      s = np.float32(2.0 ** e)
      qi, ri, score = select_correspondences(q * s, r * s, qv, rv, search=search, **opts)
      np.testing.assert_array_equal(qi, base[0])
      np.testing.assert_array_equal(ri, base[1])
      np.testing.assert_array_equal(score, base[2] if opts["k"] == 1 else base[2] * s)
    if form == "occupancy" and search == "dense":
      continue  # its float32 expansion swaps near ties on such data at any scale (see above)
    for s in (1, 1e19, 1e-20, 1e30, 1e-30):  # ratios of close matches: float32 expansion
      _check((q * s).astype(np.float32), (r * s).astype(np.float32), qv, rv, search=search,
             rtol=1e-4, **opts)
  m, ms = match_descriptors(q, r, qv, rv), match_descriptors(q * 2.0 ** 63, r * 2.0 ** 63, qv, rv)
  np.testing.assert_array_equal(ms.nearest, m.nearest)
  np.testing.assert_array_equal(ms.ratio, m.ratio)
  np.testing.assert_array_equal(ms.distance, m.distance * np.float32(2.0 ** 63))


def test_mutual_k_above_the_reference_count_is_capped():
  """`select_correspondences(k=K, mutual=True)` held m x K x K integers (and K padded
  references) for any K: K = 10**6 on 20 queries asked for 160 TB. K is capped at the valid
  references (the mutual check's queries at the valid queries), the result unchanged."""
  rng = np.random.default_rng(10)
  q, r = rng.normal(size=(20, 6)), rng.normal(size=(9, 6))
  rv = np.arange(9) != 4
  for mutual in (False, True):
    big = select_correspondences(q, r, None, rv, k=10**6, mutual=mutual)
    small = select_correspondences(q, r, None, rv, k=20, mutual=mutual)
    for a, b in zip(big, small):
      np.testing.assert_array_equal(a, b)
    _check(q, r, None, rv, k=20, mutual=mutual)
    _check(q[:3], r, None, rv, k=10**6, mutual=mutual)
