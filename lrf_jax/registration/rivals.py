"""The counts `register`'s verdict compares (`evidence.decide`): the chance level of the
correspondences, the support of the best distinct pose (also one found among the correspondences
outside the winner's: a second copy of the object), and how well the overlap pins the pose down;
and the hypotheses they are counted over (`pose_hypotheses`).

References:
  Leordeanu & Hebert, "A spectral technique for correspondence problems", ICCV 2005; Chen et
  al., "SC2-PCR", CVPR 2022 (compatibility graphs).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lrf_jax.registration import graph, host, icp_normals
from lrf_jax.registration.estimators import centred, triples
from lrf_jax.registration.evidence import (CHANCE_SHUFFLES, constraint_spectrum,
                                          distinct_from)
from lrf_jax.search import engine

# The rivals of the correspondences outside the winner's (`rest_hypotheses`): those within
# REST_FACTOR x the inlier distance of the winner belong to it and are left out, and are not
# counted for these rivals.
REST_FACTOR = 2.0


# ... and such a rival counts only when its overlap is at least REST_OVERLAP x the winner's
# (`rest_rival`).
REST_OVERLAP = 0.5


# ... and explains at least REST_SHARE x the winner's inliers (a split of the correspondences) ...
# Between the largest share of a right, claimed pose's best such rival on every benchmark set
# (0.46) and the share of a second, exact copy of an object under pooled evidence (0.68).
REST_SHARE = 0.6


# ... of the REST_CANDIDATES such rivals with the most correspondences.
REST_CANDIDATES = 16


# Points of the overlap the degeneracy test (`overlap_constraints`) reads at most.
CONSTRAINT_POINTS = 2000

# estimator="graph" (`graph.graph_hypotheses`): the LRF rotation agreement bound, the
# seeds, the consensus set of each and the seeds' suppression radius in support radii.
GRAPH_ANGLE_DEG = 45.0

GRAPH_SEEDS = 100

GRAPH_CONSENSUS = 30

GRAPH_NMS_RADII = 0.25


def overlap_scores(rotations: np.ndarray, translations: np.ndarray, points: np.ndarray,
                   target: np.ndarray | engine.Grid, distance: float, block: int = 256
                   ) -> np.ndarray:
  """Fraction of `points` within `distance` of the target cloud under each of H poses.

  Args:
    rotations: (H, 3, 3).
    translations: (H, 3).
    points: (P, 3) source points.
    target: (m, 3) target cloud, or an `engine.Grid` of it to reuse (cells >= `distance` are
      fastest), or a scipy `cKDTree` of it (its `.data` is used).
    distance: the overlap distance (cloud units).
    block: poses per batched query.

  Returns:
    (H,) float64 overlap fractions.
  """
  if isinstance(target, engine.Grid):
    grid = target
  else:  # an array, or an object holding its points as `.data` (e.g. a scipy cKDTree)
    grid = engine.Grid(np.asarray(getattr(target, "data", target), np.float64), distance)
  out = np.empty(len(rotations))
  for s in range(0, len(rotations), block):
    r, t = rotations[s:s + block], translations[s:s + block]
    moved = np.einsum("hij,pj->hpi", r, points) + t[:, None, :]
    hit = engine.any_within(grid, moved.reshape(-1, 3), distance)
    out[s:s + block] = hit.reshape(len(r), -1).mean(axis=1)
  return out


def pose_hypotheses(src, dst, f_src, f_dst, estimator: str, iterations: int, radius: float,
                    seed: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
  """Pose hypotheses from correspondences in centred float32 coordinates (src, dst and their
  frames), on the host in float64 (`host`, `graph`), (H, 3, 3) and (H, 3): "lrf" one pose per
  correspondence from its LRFs; "3point" `iterations` seeded triples (the `ransac_3point`
  sampler); "graph" one per seed of the compatibility graph (distances within `threshold`,
  LRF rotations within `GRAPH_ANGLE_DEG`), followed by the seeds' own LRF poses."""
  if estimator == "3point":
    samples = np.asarray(triples(len(src), iterations, seed))
    return host.kabsch_batch(src[samples], dst[samples])
  rs, ts = host.lrf_hypotheses(src, f_src, dst, f_dst, float(radius))
  if estimator == "lrf":
    return rs, ts
  gr, gt, seeds, _ = graph.graph_hypotheses(
      src, dst, rs, distance=threshold, angle_deg=GRAPH_ANGLE_DEG, n_seeds=GRAPH_SEEDS,
      consensus=GRAPH_CONSENSUS, nms=GRAPH_NMS_RADII * radius)
  return np.concatenate([gr, rs[seeds]]), np.concatenate([gt, ts[seeds]])


class EvidenceSet(NamedTuple):
  """The correspondences the verdict counts on (centred float32, as `centred` gives them) and
  the compatibility graph's hypotheses on them (centred coordinates)."""

  src: np.ndarray
  dst: np.ndarray
  cs: np.ndarray
  cd: np.ndarray
  f_src: np.ndarray
  f_dst: np.ndarray
  rs: np.ndarray
  ts: np.ndarray


def evidence_set(p, q, f_p, f_q, iterations, radius, seed, threshold
                 ) -> tuple[EvidenceSet, int]:
  """The evidence of an option's winner: the default matching's correspondences (p, q world
  points with their frames), the compatibility graph's hypotheses on them and its chance level
  (`chance_inliers`), as the default computes them."""
  if len(p) == 0:
    z = np.zeros((0, 3))
    e3 = np.zeros((0, 3, 3), np.float32)
    return EvidenceSet(z.astype(np.float32), z.astype(np.float32), np.zeros(3), np.zeros(3),
                       e3, e3, np.zeros((0, 3, 3)), z), 0
  src, dst, cs, cd = centred(p, q)
  rs, ts = pose_hypotheses(src, dst, f_p, f_q, "graph", iterations, radius, seed, threshold)
  chance = chance_inliers(src, dst, f_p, f_q, "graph", iterations, radius, seed, threshold)
  return EvidenceSet(src, dst, cs, cd, f_p, f_q, np.asarray(rs, np.float64),
                     np.asarray(ts, np.float64)), chance


def rest_hypotheses(ev: EvidenceSet, winner_mask, iterations, radius, seed, threshold
                    ) -> tuple[np.ndarray, np.ndarray]:
  """The compatibility graph's hypotheses on the evidence correspondences outside `winner_mask`
  (`register` passes the winner's inliers at `REST_FACTOR` times the inlier distance: the
  correspondences just beyond it are the winner's too, and a pose turned about them would count
  them as a rival): the best other explanation of the rest. Where one source region is matched
  into two places (two identical objects side by side, a repeated structure) the winner's seeds
  suppress the second place's (seeds are spread over source points), and its correspondences
  are a minority of the spectral score; without the winner's they seed their own pose, which the
  rival count then sees. Centred coordinates, (H, 3, 3) and (H, 3)."""
  rest = ~np.asarray(winner_mask, bool)
  if rest.sum() < 2:
    return np.zeros((0, 3, 3)), np.zeros((0, 3))
  return pose_hypotheses(ev.src[rest], ev.dst[rest], ev.f_src[rest], ev.f_dst[rest], "graph",
                         iterations, radius, seed, threshold)


def rest_rival(rs, ts, ev: EvidenceSet, threshold, r, t, near, radius, rival, src_pts,
                target_grid, distance, seed, n_winner) -> int:
  """`rival`, or more: the most correspondences outside `near` (the winner's within
  `REST_FACTOR` x the inlier distance) that a hypothesis of `rest_hypotheses` (rs, ts) distinct
  from the winner (r, t) explains, counted only for a split of the correspondences: at least
  `REST_SHARE` x the winner's `n_winner` inliers, and a pose that also puts the source onto the
  target (an overlap, `overlap_scores` of 1000 seeded source points, of at least `REST_OVERLAP`
  x the winner's). A second copy of the object is supported and overlaps as well as the first;
  a pose that lines up some floor or wall matches of a room overlaps little, and the
  sensor-fixed ring pattern of a LiDAR's ground (an identity pose) has fewer matches than the
  motion. (Evidence coordinates, centred.)"""
  rs = np.asarray(rs, np.float64)
  ts = np.asarray(ts, np.float64)
  if len(rs) == 0:
    return rival
  far = distinct_from(rs, ts, r, t, radius)
  masks = host.inlier_masks(rs[far], ts[far], ev.src, ev.dst, threshold)
  counts = np.sum(masks & ~np.asarray(near, bool), axis=1)
  more = (counts > rival) & (counts >= REST_SHARE * n_winner)
  if not more.any():
    return rival
  cand_r, counts = rs[far][more], counts[more]
  top = np.argsort(-counts, kind="stable")[:REST_CANDIDATES]  # the best few decide
  cand_r, counts = cand_r[top], counts[top]
  cand_t_c = ts[far][more][top]
  cand_t = cand_t_c + ev.cd - np.einsum("hij,j->hi", cand_r, ev.cs)
  rng = np.random.default_rng([seed, 11])  # its own stream: ICP's draws stay as they were
  sub = src_pts[np.sort(rng.choice(len(src_pts), min(1000, len(src_pts)), replace=False))]
  fits = overlap_scores(np.concatenate([r[None], cand_r]),
                        np.concatenate([(t + ev.cd - r @ ev.cs)[None], cand_t]), sub,
                        target_grid, distance)
  ok = fits[1:] >= REST_OVERLAP * fits[0]
  return max(rival, int(counts[ok].max())) if ok.any() else rival


def overlap_constraints(source, target, grid, transform, distance) -> tuple[float, str]:
  """`constraint_spectrum` of the overlap under `transform`: the `source` points within
  `distance` of the target, with the target's PCA normals at their nearest points (radius
  `icp_normals.normal_radius` over those points' spacing, computed at those points only)."""
  source = np.asarray(source, np.float64)
  source = source[::max(1, -(-len(source) // CONSTRAINT_POINTS))]  # an even, deterministic subset
  moved = source @ transform[:3, :3].T + transform[:3, 3]
  d, idx = engine.knn(grid, moved, 1, distance)
  ok = np.isfinite(d[:, 0])
  if ok.sum() < 6:
    return 1.0, ""
  near = np.asarray(target, np.float64)[np.unique(idx[ok, 0])]
  gaps = engine.knn(grid, near, 2)[0][:, 1]
  spacing = float(np.mean(gaps[np.isfinite(gaps)])) if np.isfinite(gaps).any() else 0.0
  radius = icp_normals.normal_radius(near, distance, grid, spacing=spacing)
  count, _, cov = engine.ball_stats(grid, near, radius)
  _, vec = np.linalg.eigh(cov)
  normals = np.where((count >= 3)[:, None], vec[:, :, 0], np.nan)
  return constraint_spectrum(near, normals)


def rival_inliers(rs, ts, src, dst, threshold, r, t, winner_mask, radius) -> int:
  """The support of the best alternative explanation: over the hypotheses (centred
  coordinates) distinct from the pose (r, t) (rotation apart by more than RIVAL_DEG or
  translation at the centroid by more than `radius`), the most inliers that are NOT inliers of
  the winner (`winner_mask`). A pose that merely re-uses the winner's correspondences (a rotation
  about their cluster) adds no evidence against it; one that explains other correspondences
  does."""
  rs = np.asarray(rs, np.float64)
  far = distinct_from(rs, ts, r, t, radius)
  if not far.any():
    return 0
  masks = host.inlier_masks(rs[far], np.asarray(ts, np.float64)[far], src, dst, threshold)
  return int(np.max(np.sum(masks & ~np.asarray(winner_mask, bool), axis=1)))


def chance_inliers(src, dst, f_src, f_dst, estimator, iterations, radius, seed,
                    threshold) -> int:
  """The most inliers any hypothesis reaches when the correspondences are shuffled (the target
  side permuted, `CHANCE_SHUFFLES` seeded times): what the clouds' shapes give by chance alone.

  Two unrelated blobs or a mirrored cloud reach about as many inliers by chance as with their
  real matches; a true overlap reaches several times more.
  """
  rng = np.random.default_rng([seed, 7])
  best = 0
  for _ in range(CHANCE_SHUFFLES):
    perm = rng.permutation(len(src))
    d, fd = np.asarray(dst)[perm], np.asarray(f_dst)[perm]
    rs, ts = pose_hypotheses(src, d, f_src, fd, estimator, iterations, radius, seed, threshold)
    if len(rs):
      best = max(best, int(np.max(host.count_inliers(rs, ts, src, d, threshold))))
  return best
