"""`register(source, target)`: the user-facing registration pipeline.

mr from the source, seeded random (or ISS) keypoints on both clouds, LRF-Net frames, TOLDI
descriptors, ratio matching, hypotheses from the compatibility graph of the correspondences
(`lrf_jax.registration.graph`: distances preserved and one-correspondence LRF poses in
agreement; or the RANSACs of `estimators.py`), then point-to-plane ICP
(`lrf_jax.registration.icp_host`) and a verdict (`evidence.py`) that claims success only when the
winner's support is far above chance and above every distinct pose's. It generates and scores
its hypotheses on the host (`lrf_jax.registration.host`), the same arithmetic as the jitted
estimators without a JAX program to load in every fresh process.

References:
  Besl & McKay, "A method for registration of 3-D shapes", TPAMI 1992 (ICP).
  Chen & Medioni, "Object modelling by registration of multiple range images", IVC 1992
  (point-to-plane ICP).
  Leordeanu & Hebert, "A spectral technique for correspondence problems", ICCV 2005; Chen et
  al., "SC2-PCR", CVPR 2022 (compatibility graphs).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from typing import Any, NamedTuple, cast

import numpy as np

from lrf_jax.api import _check_options, _frames_checked
from lrf_jax.descriptors import DESCRIPTORS, _descriptors_checked, select_correspondences
from lrf_jax.frames import METHODS
from lrf_jax.geometry.keypoints import iss_keypoints
from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals
from lrf_jax.geometry.cloud import CloudInput, as_cloud
from lrf_jax.geometry.resolution import (mesh_resolution, pair_resolution, thinning_voxel,
                                         working_resolution)
from lrf_jax.geometry.sampling import voxel_downsample
from lrf_jax.registration import graph, host, icp_host
from lrf_jax.registration.errors import _check_transform, pose_errors
from lrf_jax.registration.estimators import _centred, _finish, _triples, _uncentre
from lrf_jax.registration.evidence import (CHANCE_SHUFFLES, RIVAL_DEG, Evidence, constraint_spectrum, decide, overlap_contrast)
from lrf_jax.registration.icp_host import icp
from lrf_jax.search import engine
from lrf_jax.search.grid import serial_blas
from lrf_jax.checks import validate_radius, validate_seed, validate_viewpoint

# ------------------------------------------------------------------------------------------------
# register: the user-facing pipeline
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Registration:
  """Result of `register`.

  Attributes:
    transform: (4, 4) float64, maps source points onto the target: target ≈ R source + t.
    coarse_transform: (4, 4) the RANSAC estimate before ICP.
    inliers: (C,) bool, which correspondences are inliers of the coarse estimate.
    n_inliers: their number.
    correspondences: (C, 2) int64 (source point index, target point index), best ratio first.
    fitness: fraction of the (ICP's) source points within icp_mr mr of the target after
      `transform`.
    rmse: RMS distance of those points (cloud units).
    mr: the mesh resolution used as the unit (cloud units).
    seconds: wall time of the whole call.
    timings: wall seconds per stage of `register`, keyed "prepare", "frames", "descriptors",
      "matching", "hypotheses", "verification", "icp".
    success: the verdict (a Python bool, `verdict`): True only when the evidence excludes a
      wrong pose (the winner's support far above chance and above every distinct pose's, and
      the aligned clouds overlap). False means "not sure": the correspondences do not single
      out one pose (too few of them agree, or as many agree by chance or with another pose).
      A mirrored or nearly symmetric object may still have a rigid overlap that passes.
    inlier_ratio: n_inliers / number of correspondences.
    chance_inliers: the most inliers a hypothesis reaches on the same correspondences shuffled
      (the chance level of this pair of clouds; `_chance_inliers`).
    overlap_contrast: the chosen hypothesis's overlap over the 99th percentile of all
      hypotheses' (`overlap_contrast`; 0 when verification is off).
    reason: why `success` is what it is, one short sentence (`verdict`).
    overlap: the estimated overlap: the fraction of the ICP's source points within icp_mr mr of
      the target under `transform` (the same number as `fitness`).
    rival_inliers: the most inliers outside the winner's of a hypothesis distinct from the winner
    (`_rival_inliers`).
    estimated: False when no pose hypothesis could be built from the correspondences (the graph
      estimator finds no two of them compatible, e.g. at a tiny `inlier_mr`): `transform` and
      `coarse_transform` are then the identity, not an estimate, `success` is False and
      `reason` says why; `lrf_jax.register_all` makes no edge of such a pair.
    voxel_size: the voxel edge (cloud units) the clouds were thinned with before the work (0:
      every point kept); `correspondences` index the input clouds all the same (each voxel's
      first input point).
    reason_code: what decided `success`, machine-readable (a key of
      `lrf_jax.registration.evidence.REASON_CODES`): "claimed" (the only code of a success),
      "low_overlap", "degenerate", "chance", "rival", "no_hypothesis", "init_only".
    evidence_inliers: the winner's inliers among the evidence correspondences (the default
      matching's, `_evidence_matches`), the count the verdict compares with `chance_inliers`
      and `rival_inliers`; `n_inliers` when no option changed the matching.
    degeneracy: how well the overlap pins the pose down (`evidence.constraint_spectrum`: the
      weakest direction of the point-to-plane constraints over the strongest; below
      `evidence.DEGENERATE_RATIO` the verdict is "degenerate").
  """

  transform: np.ndarray
  coarse_transform: np.ndarray
  inliers: np.ndarray
  n_inliers: int
  correspondences: np.ndarray
  fitness: float
  rmse: float
  mr: float
  seconds: float
  timings: dict = dataclasses.field(default_factory=dict)
  success: bool = False
  inlier_ratio: float = 0.0
  chance_inliers: int = 0
  overlap_contrast: float = 0.0
  reason: str = ""
  overlap: float = 0.0
  rival_inliers: int = 0
  estimated: bool = True
  voxel_size: float = 0.0
  reason_code: str = ""
  evidence_inliers: int = 0
  degeneracy: float = 1.0

  def summary(self, gt: Any = None) -> str:
    """A few lines a person reads: the verdict and its reason, the estimated overlap and RMSE,
    the inliers against what chance and the best distinct pose reach, the errors against a
    ground truth when one is given, and the time.

    Args:
      gt: optional (4, 4) ground-truth source -> target transform; adds the rotation error in
        degrees and the translation error in mr and in the clouds' units (`pose_errors`).

    Returns:
      The text, lines joined by newlines (no trailing newline).
    """
    verdict_word = "success" if self.success else "NOT SURE (do not trust this transform)"
    lines = [f"verdict: {verdict_word}: {self.reason}",
             f"estimated overlap {self.overlap:.1%} (source points near the target after the "
             f"transform), rmse {self.rmse / self.mr:.3f} mr (mr = {self.mr:.6g})"]
    if len(self.correspondences):
      lines.append(f"inliers {self.n_inliers} of {len(self.correspondences)} correspondences "
                   f"(chance level {self.chance_inliers}, best distinct pose "
                   f"{self.rival_inliers})")
    if gt is not None:
      err_r, err_t = pose_errors(self.transform, gt, self.mr)
      lines.append(f"error against the ground truth: {err_r:.3g} deg, {err_t:.3g} mr "
                   f"({err_t * self.mr:.3g} in the clouds' units)")
    stages = ", ".join(f"{k} {v:.2f}" for k, v in self.timings.items() if v >= 0.005)
    lines.append(f"time {self.seconds:.2f} s" + (f" ({stages})" if stages else ""))
    return "\n".join(lines)

  def __repr__(self) -> str:
    """One line: verdict, overlap, inliers and time (the arrays are attributes; `summary()`
    says more)."""
    verdict_word = "success" if self.success else "not sure"
    return (f"Registration({verdict_word}, overlap {self.overlap:.1%}, inliers "
            f"{self.n_inliers}/{len(self.correspondences)}, rmse {self.rmse / self.mr:.3g} mr, "
            f"{self.seconds:.2f} s; .transform, .summary())")


def _as_cloud(x: Any, name: str) -> tuple[np.ndarray, np.ndarray | None]:
  cloud = as_cloud(x, name)
  return cloud.points, cloud.faces


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


def register(source: Any, target: Any, *, mr: float | None = None, radius_mr: float = 15.0,
             n_keypoints: int = 3000, n_correspondences: int = 1000, iterations: int = 1000,
             inlier_mr: float = 5.0, verify: int | None = None, estimator: str = "graph",
             icp_iterations: int = 50, icp_mr: float = 3.0, method: str = "lrf_net_plus",
             descriptor: str = "toldi", params: Any = None, seed: int = 0,
             source_viewpoint: Any = None, target_viewpoint: Any = None,
             init: Any = None, keypoints: str = "random", mutual: bool = False,
             ratio: float | None = None, icp_mode: str = "point_to_plane",
             icp_fine: bool = True, voxel_size: float | None = None) -> Registration:
  """Rigidly register `source` onto `target` with learned LRFs and a compatibility graph.

  Pipeline (every length in mr: the source's mean edge length for a mesh, mean nearest-neighbor
  distance for a cloud, `datasets.mesh_resolution`):

  1. `n_keypoints` per cloud (`keypoints="random"`: seeded random points; `"iss"`: ISS
     keypoints, `lrf_jax.iss_keypoints`, at most `n_keypoints`); LRFs (`method`, default
     lrf_net_plus) and descriptors (`descriptor`, default TOLDI) at r = radius_mr mr;
  2. each source keypoint matched to its nearest target descriptor (`mutual`: mutual nearest
     neighbors only; `ratio`: Lowe's ratio test), the `n_correspondences` of smallest ratio
     d1/d2 kept (`lrf_jax.descriptors.select_correspondences`);
  3. hypotheses: with `estimator="graph"` (default) one per seed of the correspondences'
     compatibility graph (distances preserved within inlier_mr mr AND one-correspondence LRF
     rotations within `GRAPH_ANGLE_DEG`; `graph`), with `"lrf"` ONE per
     correspondence (the pose from its two LRFs), with `"3point"` `iterations` seeded triples;
     each is scored by its inlier count (correspondences within inlier_mr mr);
  4. selection: "graph" takes the most inliers; "lrf" and "3point" re-rank the `verify`
     best-scoring hypotheses (None: all) by their overlap (the fraction of up to 1000 seeded
     source points within icp_mr mr of the target). The winner is refitted by Kabsch on its
     inliers;
  5. point-to-plane ICP (pairs within icp_mr mr, target normals by PCA) on up to `ICP_POINTS`
     seeded source points; with `icp_fine` (default) a second pass at an adaptive gate
     (`fine_distance`: 1.5 x the median residual, 1 mr to icp_mr mr) on up to `ICP_POINTS`
     source points drawn among those within icp_mr mr of the target (`overlap_points`);
  6. the verdict (`evidence.decide`), one rule for every estimator and option: it claims
     success when the winner's inliers are at least `VERDICT_GRAPH_FACTOR` times (+
     `VERDICT_GRAPH_MARGIN`) both what chance alignment reaches on the correspondences
     shuffled and what the best distinct pose explains outside them, ICP pairs enough of the
     source and the overlap leaves no motion free (`evidence.constraint_spectrum`). Whatever
     chose the hypotheses (estimator, ratio, mutual), the evidence is counted on the default
     matching's correspondences with the compatibility graph's hypotheses (plus the
     estimator's own and the graph's on the correspondences outside the winner's inliers, as
     rivals), so no option claims what the default's evidence would not.
     `Registration.reason_code` says which test decided.

  With `init` (a (4, 4) rigid transform) steps 1-4 are skipped: ICP refines `init`, as Open3D's
  `registration_icp` does, and `success` is False (nothing checks `init`; `reason` says so).

  The same inputs and seed give the same transform.

  Args:
    source: (n, 3) array, an `lrf_jax.io.Cloud`, a path to any cloud/mesh `lrf_jax.io`
      reads (PLY, PCD, XYZ/TXT(.gz), NPY), or an object with `.points` (e.g. Open3D's), as
      `compute_frames` takes (`lrf_jax.inputs.as_cloud`).
    target: the same for the target.
    mr: the working resolution in the clouds' units, the unit of every length below (None:
      measured, `geometry.resolution.working_resolution` and `pair_resolution`: the source's
      mean point spacing or mean edge length; on a raw, uneven cloud such as a LiDAR sweep the
      area-weighted median spacing; for a pair whose resolutions differ over 2-fold, the
      coarser one).
    radius_mr: support radius of the LRFs and descriptors, in mr (the paper: 15).
    n_keypoints: keypoints per cloud (fewer when a cloud has fewer points).
    n_correspondences: correspondences kept (and LRF hypotheses).
    iterations: hypotheses of the 3-point estimator.
    inlier_mr: inlier distance of the hypothesis score, in mr.
    verify: hypotheses re-ranked by overlap (None: all of them; 0: none).
    estimator: "graph" (compatibility graph, default), "lrf" (one correspondence per
      hypothesis) or "3point" (classic).
    icp_iterations: ICP iterations (0: no ICP, `transform` = the RANSAC estimate).
    icp_mr: ICP pairing and overlap distance, in mr.
    method: LRF method (a key of `lrf_jax.METHODS`; default "lrf_net_plus", the most repeatable
      shipped one; "lrf_net" is the paper's LRF-Net; mesh methods need mesh inputs).
    descriptor: a key of `lrf_jax.descriptors.DESCRIPTORS`.
    params: learned LRF parameters (None: the method's shipped weights).
    seed: seed of keypoints, neighbor subsamples and sampling.
    source_viewpoint, target_viewpoint: optional (3,) sensor positions of single-view scans, in
      each cloud's own coordinates: estimated normals (and `method="lrf_net_plus"`'s z) are
      oriented towards them (see `compute_frames`). Without them a scan's normals are oriented
      by propagation, which cannot know which side of an open scan is out.
    init: optional (4, 4) initial source -> target transform: refine it by ICP only.
    keypoints: "random" or "iss".
    mutual: keep mutual nearest-neighbor matches only.
    ratio: optional ratio-test threshold in (0, 1].
    icp_mode: "point_to_plane" (default) or "point_to_point" (`icp`).
    icp_fine: run the second ICP pass at the adaptive gate (False: one pass at icp_mr mr, the
      behaviour before it).
    voxel_size: thin the clouds by voxel averaging first (`voxel_downsample`), voxels of this
      edge in cloud units; 0 keeps every point; None (default) thins a cloud at the working
      resolution where its mean spacing is under half of it (a raw sweep's near field, a
      full-density fragment against a coarser one) and keeps clean clouds as they are.

  Returns:
    `Registration`; `transform` maps source points into the target's frame.

  Raises:
    ValueError: a cloud that is not a non-empty (n, 3) array of finite floats, fewer than 10
      points, a non-positive count or distance, a seed that is not a non-negative integer, or
      an unknown estimator/method/descriptor/keypoints, an `init` that is not a (4, 4) rigid
      transform, or a ratio outside (0, 1].
    FileNotFoundError: a path that does not exist.

  Example:
    >>> reg = lrf_jax.register("scan_a.ply", "scan_b.ply")
    >>> aligned = points_a @ reg.transform[:3, :3].T + reg.transform[:3, 3]
  """
  timer = _StageTimer()
  check_register_options(mr=mr, radius_mr=radius_mr, n_keypoints=n_keypoints,
                         n_correspondences=n_correspondences, iterations=iterations,
                         inlier_mr=inlier_mr, verify=verify, estimator=estimator,
                         icp_iterations=icp_iterations, icp_mr=icp_mr, method=method,
                         descriptor=descriptor, seed=seed, source_viewpoint=source_viewpoint,
                         target_viewpoint=target_viewpoint, keypoints=keypoints, mutual=mutual,
                         ratio=ratio, icp_mode=icp_mode, icp_fine=icp_fine,
                         voxel_size=voxel_size)
  if init is not None:
    return _refine_only(source, target, init, mr=mr, icp_iterations=icp_iterations,
                        icp_mr=icp_mr, seed=seed, timer=timer, icp_mode=icp_mode,
                        icp_fine=icp_fine, voxel_size=voxel_size)
  with timer("prepare"):
    setup = _prepare(source, target, mr=mr, radius_mr=radius_mr, n_keypoints=n_keypoints,
                     n_correspondences=n_correspondences, iterations=iterations,
                     inlier_mr=inlier_mr, verify=verify, estimator=estimator,
                     icp_iterations=icp_iterations, icp_mr=icp_mr, method=method,
                     descriptor=descriptor, seed=seed, views=(source_viewpoint,
                                                              target_viewpoint),
                     keypoints=keypoints, mutual=mutual, ratio=ratio, icp_mode=icp_mode,
                     voxel_size=voxel_size)
  with timer("frames"):
    frames = [_side_frames(side, setup, method, params) for side in setup.sides]
  with timer("descriptors"):
    descs = [_side_descriptors(side, f, setup, descriptor) for side, f in zip(setup.sides, frames)]
  with timer("matching"):
    qi, ri = _match(frames, descs, estimator, n_correspondences, radius_mr, mutual, ratio)
    # The evidence: the default matching's correspondences, whatever chose the hypotheses' own.
    own = estimator == "graph" and not mutual and ratio is None
    eqi, eri = (qi, ri) if own else _evidence_matches(frames, descs, n_correspondences)
  (kp_s, (f_s, v_s)), (kp_t, (f_t, v_t)) = zip((s.keypoints for s in setup.sides), frames)
  src_pts, dst_pts = setup.sides[0].points, setup.sides[1].points
  threshold = inlier_mr * setup.mr
  with timer("hypotheses"), serial_blas():
    src, dst, cs, cd = _centred(src_pts[kp_s[qi]], dst_pts[kp_t[ri]])
    rs, ts = _hypotheses(src, dst, f_s[qi], f_t[ri], estimator, iterations, setup.radius, seed,
                         float(threshold))
    if len(rs) == 0:  # no two correspondences agree: no pose to verify
      return _not_estimated(setup, _input_indices(setup, kp_s[qi], kp_t[ri]), estimator,
                            inlier_mr, icp_mr, timer)
    counts = host.count_inliers(rs, ts, src, dst, threshold)
    ev, chance = _evidence_and_chance(
        own, (src, dst, cs, cd, f_s[qi], f_t[ri], rs, ts), (src_pts[kp_s[eqi]], dst_pts[kp_t[eri]],
        f_s[eqi], f_t[eri]), iterations, setup.radius, seed, float(threshold))
  with timer("verification"), serial_blas():
    overlap_distance = icp_mr * setup.mr
    target_grid = engine.Grid(dst_pts, overlap_distance)
    best, fits = _verify(rs, ts, counts, cs, cd, src_pts, target_grid, overlap_distance,
                         0 if estimator == "graph" else verify, setup.rng)
    r, t, mask = host.select_and_refine(rs[best], ts[best], src, dst, threshold)
    res = _finish(*_uncentre(r, t, cs, cd), mask, best, counts[best])
    ev_mask, rival = _evidence_rivals(ev, own, (r, t, mask), (rs, ts, cs, cd), threshold, setup,
                                      iterations, seed, target_grid, overlap_distance)
  final, fitness, rmse, degeneracy, free = _icp_stage(
      setup, res.transform, target_grid, overlap_distance, icp_fine, icp_iterations, icp_mode,
      timer)
  contrast = overlap_contrast(fits)
  evidence = Evidence(n_inliers=int(np.sum(ev_mask)), chance_inliers=chance,
                      rival_inliers=rival, fitness=fitness, contrast=contrast,
                      estimator=estimator, degeneracy=degeneracy, free_direction=free)
  decision = decide(evidence)
  return Registration(transform=final, coarse_transform=res.transform, inliers=res.inliers,
                      n_inliers=res.n_inliers,
                      correspondences=_input_indices(setup, kp_s[qi], kp_t[ri]),
                      voxel_size=setup.voxel_size,
                      fitness=fitness, rmse=rmse, mr=float(setup.mr), seconds=timer.total(),
                      timings=dict(timer.seconds), success=decision.success,
                      inlier_ratio=res.n_inliers / max(len(qi), 1), chance_inliers=chance,
                      overlap_contrast=contrast, reason=decision.reason, overlap=fitness,
                      rival_inliers=rival, reason_code=decision.code,
                      evidence_inliers=evidence.n_inliers, degeneracy=degeneracy)


def _icp_stage(setup: _Setup, coarse: np.ndarray, target_grid: engine.Grid,
               overlap_distance: float, icp_fine: bool, icp_iterations: int, icp_mode: str,
               timer: _StageTimer) -> tuple[np.ndarray, float, float, float, Any]:
  """Stages "icp" (`_refine` of `coarse` on up to `ICP_POINTS` seeded source points) and the
  overlap's constraints (`_overlap_constraints`, timed as "verification"): (transform, fitness,
  rmse, degeneracy, free direction)."""
  src_pts, dst_pts = setup.sides[0].points, setup.sides[1].points
  with timer("icp"):
    icp_src = src_pts
    if len(src_pts) > ICP_POINTS:
      icp_src = src_pts[np.sort(setup.rng.choice(len(src_pts), ICP_POINTS, replace=False))]
    final, fitness, rmse = _refine(icp_src, dst_pts, coarse, overlap_distance, icp_fine,
                                   setup.mr, icp_iterations, target_grid, icp_mode,
                                   pool=src_pts, rng=setup.rng)
  with timer("verification"), serial_blas():
    degeneracy, free = _overlap_constraints(icp_src, dst_pts, target_grid, final,
                                            overlap_distance)
  return final, fitness, rmse, degeneracy, free


def _evidence_and_chance(own: bool, centred: tuple, evidence: tuple, iterations: int,
                         radius: float, seed: int, threshold: float) -> tuple[Any, int]:
  """The evidence set and its chance level: the hypotheses' own correspondences (`centred`:
  src, dst, cs, cd, their frames, rs, ts) when the default matching chose them (`own`), else
  the default matching's (`evidence`: points and frames of both sides, `_evidence_set`)."""
  if own:
    src, dst, cs, cd, fs, ft, rs, ts = centred
    return (_EvidenceSet(src, dst, cs, cd, fs, ft, rs, ts),
            _chance_inliers(src, dst, fs, ft, "graph", iterations, radius, seed, threshold))
  p, q, fp, fq = evidence
  return _evidence_set(p, q, fp, fq, iterations, radius, seed, threshold)


def _evidence_rivals(ev: Any, own: bool, winner: tuple, hypotheses: tuple, threshold: float,
                     setup: _Setup, iterations: int, seed: int, target_grid: engine.Grid,
                     overlap_distance: float) -> tuple[np.ndarray, int]:
  """The winner (its centred (r, t) and inlier mask) in the evidence's centred coordinates, its
  inliers there, and its rivals: the evidence's graph hypotheses, those of the correspondences
  outside the winner's inliers (`_rest_hypotheses`), and the estimator's own (`hypotheses`: rs,
  ts, and the centres cs, cd they are about). Returns (evidence inlier mask, rival inliers)."""
  r, t, mask = winner
  rs, ts, cs, cd = hypotheses
  r_w, t_w = _uncentre(r, t, cs, cd)
  t_e = t_w - ev.cd + r_w @ ev.cs
  ev_mask = mask if own else host.inlier_mask(r_w, t_e, ev.src, ev.dst, threshold)
  pool_r, pool_t = [ev.rs], [ev.ts]
  if not own:
    pool_r.append(np.asarray(rs, np.float64))
    pool_t.append(np.asarray(ts, np.float64) + (cd - ev.cd)
                  - np.einsum("hij,j->hi", np.asarray(rs, np.float64), cs - ev.cs))
  rival = _rival_inliers(np.concatenate(pool_r), np.concatenate(pool_t), ev.src, ev.dst,
                         threshold, r_w, t_e, ev_mask, setup.radius)
  near = host.inlier_mask(r_w, t_e, ev.src, ev.dst, REST_FACTOR * threshold)
  rest_r, rest_t = _rest_hypotheses(ev, near, iterations, setup.radius, seed, float(threshold))
  rival = _rest_rival(rest_r, rest_t, ev, threshold, r_w, t_e, near, setup.radius, rival,
                      setup.sides[0].points, target_grid, overlap_distance, seed,
                      int(np.sum(ev_mask)))
  return ev_mask, rival


ESTIMATORS = ("graph", "lrf", "3point")
KEYPOINTS = ("random", "iss")


def _check_rigid(t: Any, name: str) -> np.ndarray:
  """A (4, 4) finite rigid transform: rotation block orthonormal with det +1 (to 1e-4), last
  row (0, 0, 0, 1)."""
  try:
    a = np.asarray(t, np.float64)
  except (TypeError, ValueError):
    raise ValueError(f"{name}: expected a (4, 4) rigid transform, got {type(t).__name__}") from None
  a = _check_transform(a, name)
  r = a[:3, :3]
  if (np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(r) - 1.0) > 1e-4
      or np.abs(a[3] - [0, 0, 0, 1]).max() > 1e-9):
    raise ValueError(f"{name}: expected a rigid transform (orthonormal rotation with det +1, "
                     f"last row 0 0 0 1), got\n{a}")
  return a


def _refine(source: np.ndarray, target: np.ndarray, init: np.ndarray, distance: float,
            fine: bool, mr: float, iterations: int, grid: engine.Grid | None,
            mode: str, pool: np.ndarray | None = None,
            rng: np.random.Generator | None = None) -> tuple[np.ndarray, float, float]:
  """ICP at `distance`; then, with `fine`, again at the gate `fine_distance` of the first pass's
  residuals with the same target normals. Fitness and rmse are those at `distance` of the
  returned pose (what the verdict and `Registration.overlap` read), over `source`.

  With `pool` (the whole source cloud, of which `source` is a seeded subset) the second pass
  pairs up to `ICP_POINTS` points drawn by `rng` among the pool's points that lie within
  `distance` of the target at the first pass's pose (`overlap_points`): on a partial overlap
  all of them can pair, instead of the overlap's share of a uniform subset."""
  if not fine or iterations == 0:
    return icp(source, target, init, max_distance=distance, iterations=iterations,
               target_grid=grid, mode=mode)
  target = np.asarray(target, np.float64)
  grid = grid if grid is not None else engine.Grid(target, distance)
  normals = (icp_host.estimate_target_normals(target, distance, grid)
             if mode == "point_to_plane" else None)
  kw: dict[str, Any] = dict(target_grid=grid, target_normals=normals, mode=mode)
  coarse, _, _ = icp(source, target, init, max_distance=distance, iterations=iterations, **kw)
  gate = fine_distance(source, grid, coarse, distance, mr)
  fine_src = source
  if pool is not None and rng is not None:
    fine_src = overlap_points(pool, grid, coarse, distance, ICP_POINTS, rng, fallback=source)
  tr, _, _ = icp(fine_src, target, coarse, max_distance=gate, iterations=iterations, **kw)
  _, fitness, rmse = icp(source, target, tr, max_distance=distance, iterations=0, **kw)
  return tr, fitness, rmse


def overlap_points(points: np.ndarray, grid: engine.Grid, transform: np.ndarray,
                   distance: float, count: int, rng: np.random.Generator,
                   fallback: np.ndarray) -> np.ndarray:
  """Up to `count` of `points` (sorted by index, drawn by `rng`) whose image under `transform`
  has a grid point within `distance`: the source's part of the overlap, for `register`'s second
  ICP pass. `fallback` where fewer than `icp_host.MIN_PAIRS` points lie there.

  Args:
    points: (n, 3) source points (float64).
    grid: an `engine.Grid` of the target.
    transform: (4, 4) source -> target.
    distance: the overlap distance (cloud units).
    count: at most this many points.
    rng: the generator that draws them.
    fallback: (m, 3) returned when the overlap is too small.

  Returns:
    (k, 3) float64 points, k <= count.
  """
  moved = points @ transform[:3, :3].T + transform[:3, 3]
  near = np.flatnonzero(np.isfinite(engine.knn(grid, moved, 1, distance)[0][:, 0]))
  if len(near) < icp_host.MIN_PAIRS:
    return fallback
  if len(near) > count:
    near = np.sort(rng.choice(near, count, replace=False))
  return points[near]


def fine_distance(source: np.ndarray, grid: engine.Grid, transform: np.ndarray,
                  distance: float, mr: float) -> float:
  """The pairing distance of `register`'s second ICP pass (cloud units).

  `ICP_FINE_FACTOR` times the median distance from the moved source points to their nearest
  target point, over the pairs closer than `distance`; clipped to [ICP_FINE_MIN_MR mr,
  `distance`]. An adaptive gate in the spirit of Zhang's ICP (1994): a precise laser scan (median
  residual about 0.6 mr) is refined at 1 mr, a noisy RGB-D fragment (about 1.1 mr) at about
  1.7 mr, so the boundary of the overlap and the far tail of the noise stop pulling the pose.

  Args:
    source: (n, 3) source points (float64).
    grid: an `engine.Grid` of the target.
    transform: (4, 4) the first pass's source -> target transform.
    distance: the first pass's pairing distance (cloud units).
    mr: the mesh resolution (cloud units).

  Returns:
    The gate; `distance` when no pair is closer than `distance`.
  """
  moved = source @ transform[:3, :3].T + transform[:3, 3]
  d = engine.knn(grid, moved, 1, distance)[0][:, 0]
  d = d[np.isfinite(d)]
  if len(d) == 0:
    return float(distance)
  lo = min(ICP_FINE_MIN_MR * mr, distance)
  return float(np.clip(ICP_FINE_FACTOR * np.median(d), lo, distance))


# The second ICP pass (`fine_distance`): its gate in median residuals and its floor in mr.
ICP_FINE_FACTOR = 1.5
ICP_FINE_MIN_MR = 1.0


def _refine_only(source, target, init, *, mr, icp_iterations, icp_mr, seed, timer, icp_mode,
                 icp_fine=True, voxel_size=None
                 ) -> Registration:
  """`register(..., init=T)`: ICP from T and nothing else (no keypoints, frames or matching).

  The verdict is False with a reason that says so: ICP converges to the nearest local
  optimum, and nothing here can exclude a wrong `init`.
  """
  with timer("prepare"):
    init = _check_rigid(init, "init")
    src_pts, src_faces = _as_cloud(source, "source")
    dst_pts, _ = _as_cloud(target, "target")
    for name, pts in (("source", src_pts), ("target", dst_pts)):
      if len(pts) < 10:
        raise ValueError(f"{name}: expected a cloud of at least 10 points, got {len(pts)}")
    if not _is_positive(icp_mr):
      raise ValueError(f"icp_mr: expected a positive number of mesh resolutions, got {icp_mr!r}")
    if not _is_count(icp_iterations, 0):
      raise ValueError(f"icp_iterations: expected a non-negative integer, got {icp_iterations!r}")
    seed = validate_seed(seed)
    dst_faces = None  # ICP reads the target's points only
    mr, thinned, voxel = _working_clouds((src_pts, src_faces), (dst_pts, dst_faces), mr,
                                         voxel_size)
    src_pts, dst_pts = thinned[0][0], thinned[1][0]
    rng = np.random.default_rng(seed)
  with timer("icp"):
    distance = icp_mr * mr
    icp_src = src_pts
    if len(src_pts) > ICP_POINTS:
      icp_src = src_pts[np.sort(rng.choice(len(src_pts), ICP_POINTS, replace=False))]
    final, fitness, rmse = _refine(icp_src, dst_pts, init, distance, icp_fine, mr,
                                   icp_iterations, None, icp_mode, pool=src_pts, rng=rng)
  return Registration(transform=final, coarse_transform=init, inliers=np.zeros(0, bool),
                      n_inliers=0, correspondences=np.zeros((0, 2), np.int64), fitness=fitness,
                      rmse=rmse, mr=float(mr), seconds=timer.total(),
                      timings=dict(timer.seconds), success=False,
                      reason=("not verified: refined from init only (ICP keeps the nearest "
                              f"optimum); {fitness:.0%} of the source lies on the target"),
                      overlap=fitness, voxel_size=voxel, reason_code="init_only")

def _not_estimated(setup: _Setup, correspondences: np.ndarray, estimator: str, inlier_mr: float,
                   icp_mr: float, timer: _StageTimer) -> Registration:
  """`register`'s result when no hypothesis could be built: the identity, not sure, and why
  (its overlap and rmse are the identity's, measured as for an estimate)."""
  with timer("icp"):
    src_pts, dst_pts = setup.sides[0].points, setup.sides[1].points
    icp_src = src_pts
    if len(src_pts) > ICP_POINTS:
      icp_src = src_pts[np.sort(setup.rng.choice(len(src_pts), ICP_POINTS, replace=False))]
    _, fitness, rmse = icp(icp_src, dst_pts, np.eye(4), max_distance=icp_mr * setup.mr,
                           iterations=0)
  n = len(correspondences)
  if estimator != "graph":
    why = f"the {estimator} estimator built none from {n} correspondences"
  elif n < 2:
    why = f"the graph estimator needs two compatible correspondences, and there is {n}"
  else:
    why = f"no two of the {n} correspondences are compatible within inlier_mr = {inlier_mr:g} mr"
  return Registration(transform=np.eye(4), coarse_transform=np.eye(4),
                      inliers=np.zeros(n, bool), n_inliers=0,
                      correspondences=np.asarray(correspondences, np.int64), fitness=fitness,
                      rmse=rmse, mr=float(setup.mr), seconds=timer.total(),
                      timings=dict(timer.seconds), success=False,
                      reason=(f"no pose hypothesis: {why}; the transform is the identity, not an "
                              "estimate"),
                      overlap=fitness, estimated=False, reason_code="no_hypothesis")


# Source points ICP pairs per iteration (a seeded subset of larger clouds; in the second pass,
# of the part within the overlap distance, `overlap_points`); fitness and rmse are measured on
# the first subset.
ICP_POINTS = 5000




class _EvidenceSet(NamedTuple):
  """The correspondences the verdict counts on (centred float32, as `_centred` gives them) and
  the compatibility graph's hypotheses on them (centred coordinates)."""

  src: np.ndarray
  dst: np.ndarray
  cs: np.ndarray
  cd: np.ndarray
  f_src: np.ndarray
  f_dst: np.ndarray
  rs: np.ndarray
  ts: np.ndarray


def _evidence_matches(frames, descs, n_correspondences: int) -> tuple[np.ndarray, np.ndarray]:
  """The default matching (`_match` for estimator "graph", no mutual or ratio test): the
  correspondences the verdict counts on whatever option chose the hypotheses'; none when there
  is none with two valid frames."""
  try:
    return _match(frames, descs, "graph", n_correspondences, 0.0)
  except ValueError:
    return np.zeros(0, np.int64), np.zeros(0, np.int64)


def _evidence_set(p, q, f_p, f_q, iterations, radius, seed, threshold
                  ) -> tuple[_EvidenceSet, int]:
  """The evidence of an option's winner: the default matching's correspondences (p, q world
  points with their frames), the compatibility graph's hypotheses on them and its chance level
  (`_chance_inliers`), as the default computes them."""
  if len(p) == 0:
    z = np.zeros((0, 3))
    e3 = np.zeros((0, 3, 3), np.float32)
    return _EvidenceSet(z.astype(np.float32), z.astype(np.float32), np.zeros(3), np.zeros(3),
                        e3, e3, np.zeros((0, 3, 3)), z), 0
  src, dst, cs, cd = _centred(p, q)
  rs, ts = _hypotheses(src, dst, f_p, f_q, "graph", iterations, radius, seed, threshold)
  chance = _chance_inliers(src, dst, f_p, f_q, "graph", iterations, radius, seed, threshold)
  return _EvidenceSet(src, dst, cs, cd, f_p, f_q, np.asarray(rs, np.float64),
                      np.asarray(ts, np.float64)), chance


def _rest_hypotheses(ev: _EvidenceSet, winner_mask, iterations, radius, seed, threshold
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
  return _hypotheses(ev.src[rest], ev.dst[rest], ev.f_src[rest], ev.f_dst[rest], "graph",
                     iterations, radius, seed, threshold)


def _rest_rival(rs, ts, ev: _EvidenceSet, threshold, r, t, near, radius, rival, src_pts,
                target_grid, distance, seed, n_winner) -> int:
  """`rival`, or more: the most correspondences outside `near` (the winner's within
  `REST_FACTOR` x the inlier distance) that a hypothesis of `_rest_hypotheses` (rs, ts) distinct
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
  cos = (np.einsum("hij,ij->h", rs, r) - 1.0) / 2.0
  far = (cos < np.cos(np.radians(RIVAL_DEG))) | (np.linalg.norm(ts - t, axis=1) > radius)
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


def _overlap_constraints(source, target, grid, transform, distance) -> tuple[float, str]:
  """`constraint_spectrum` of the overlap under `transform`: the `source` points within
  `distance` of the target, with the target's PCA normals at their nearest points (radius as
  `icp_host.estimate_target_normals`, computed at those points only)."""
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
  radius = icp_host.NORMAL_RADIUS_RATIO * float(distance)
  if spacing > 0:
    radius = min(radius, icp_host.NORMAL_RADIUS_SPACING * spacing)
  count, _, cov = engine.ball_stats(grid, near, radius)
  _, vec = np.linalg.eigh(cov)
  normals = np.where((count >= 3)[:, None], vec[:, :, 0], np.nan)
  return constraint_spectrum(near, normals)


def _rival_inliers(rs, ts, src, dst, threshold, r, t, winner_mask, radius) -> int:
  """The support of the best alternative explanation: over the hypotheses (centred
  coordinates) distinct from the pose (r, t) (rotation apart by more than RIVAL_DEG or
  translation at the centroid by more than `radius`), the most inliers that are NOT inliers of
  the winner (`winner_mask`). A pose that merely re-uses the winner's correspondences (a rotation
  about their cluster) adds no evidence against it; one that explains other correspondences
  does."""
  rs = np.asarray(rs, np.float64)
  cos = (np.einsum("hij,ij->h", rs, np.asarray(r, np.float64)) - 1.0) / 2.0
  far = (cos < np.cos(np.radians(RIVAL_DEG))) | (
      np.linalg.norm(np.asarray(ts, np.float64) - t, axis=1) > radius)
  if not far.any():
    return 0
  masks = host.inlier_masks(rs[far], np.asarray(ts, np.float64)[far], src, dst, threshold)
  return int(np.max(np.sum(masks & ~np.asarray(winner_mask, bool), axis=1)))


def _chance_inliers(src, dst, f_src, f_dst, estimator, iterations, radius, seed,
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
    rs, ts = _hypotheses(src, d, f_src, fd, estimator, iterations, radius, seed, threshold)
    if len(rs):
      best = max(best, int(np.max(host.count_inliers(rs, ts, src, d, threshold))))
  return best


class _StageTimer:
  """Wall seconds per named stage (`with timer("frames"): ...`)."""

  def __init__(self):
    self.seconds: dict[str, float] = {}
    self._t0 = time.perf_counter()

  @contextlib.contextmanager
  def __call__(self, name: str):
    t = time.perf_counter()
    try:
      yield
    finally:
      self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t

  def total(self) -> float:
    return time.perf_counter() - self._t0


class _Side(NamedTuple):
  points: np.ndarray           # (n, 3) float64
  faces: np.ndarray | None
  viewpoint: np.ndarray | None
  keypoints: np.ndarray        # (k,) sorted indices
  normals: np.ndarray | None   # estimated towards the viewpoint when a method or SHOT needs them
  input_index: np.ndarray | None  # each working point's input point (thinned clouds), or None


class _Setup(NamedTuple):
  """`register`'s checked inputs: what its stages pass inward without checking them again."""

  sides: tuple[_Side, _Side]
  mr: float
  radius: float                # the support radius (cloud units), `validate_radius`'s range
  rng: np.random.Generator
  seed: int                    # `validate_seed`'s
  voxel_size: float            # the clouds' thinning voxel (0: none)


def _prepare(source: Any, target: Any, *, mr, radius_mr, n_keypoints, n_correspondences,
             iterations, inlier_mr, verify, estimator, icp_iterations, icp_mr, method,
             descriptor, seed, views, keypoints="random", mutual=False, ratio=None,
             icp_mode="point_to_plane", voxel_size=None) -> _Setup:
  """Stage "prepare": read and check the inputs, measure mr, pick keypoints, estimate normals.

  Where `register` checks its inputs (`icp_fine` aside): the later stages hand the checked clouds,
  keypoints, radius and seed to the inner functions of `compute_frames` and
  `compute_descriptors` (`_frames_checked`, `_descriptors_checked`), which do not check them
  again."""

  src_pts, src_faces = _as_cloud(source, "source")
  dst_pts, dst_faces = _as_cloud(target, "target")
  for name, pts in (("source", src_pts), ("target", dst_pts)):
    if len(pts) < 10:
      raise ValueError(f"{name}: expected a cloud of at least 10 points, got {len(pts)}")
  check_register_options(mr=mr, radius_mr=radius_mr, n_keypoints=n_keypoints,
                         n_correspondences=n_correspondences, iterations=iterations,
                         inlier_mr=inlier_mr, verify=verify, estimator=estimator,
                         icp_iterations=icp_iterations, icp_mr=icp_mr, method=method,
                         descriptor=descriptor, seed=seed, source_viewpoint=views[0],
                         target_viewpoint=views[1], keypoints=keypoints, mutual=mutual,
                         ratio=ratio, icp_mode=icp_mode)
  seed = validate_seed(seed)
  spec = METHODS[method]
  if spec.needs_mesh and (src_faces is None or dst_faces is None):
    raise ValueError(f"method {method!r} needs triangle meshes on both sides")
  checked = [validate_viewpoint(vp, name)
             for name, vp in zip(("source_viewpoint", "target_viewpoint"), views)]
  mr, thinned, voxel = _working_clouds((src_pts, src_faces), (dst_pts, dst_faces), mr,
                                       voxel_size)
  radius = radius_mr * mr
  rng = np.random.default_rng(seed)
  sides = []
  for (pts, faces, index), vp in zip(thinned, checked):
    if keypoints == "iss":
      kp = iss_keypoints(pts, mr=mr, max_keypoints=int(n_keypoints))
    else:
      kp = np.sort(rng.choice(len(pts), min(int(n_keypoints), len(pts)), replace=False))
    normals = None
    if vp is not None and (spec.needs_normals or descriptor == "shot"):
      normals = estimate_normals(pts, NORMAL_RADIUS_RATIO * radius, faces, vp)
    sides.append(_Side(pts, faces, vp, kp, normals, index))
  # checked last, where `compute_frames` checked it: the same ValueError after the same steps
  radius = validate_radius(radius)
  return _Setup(cast("tuple[_Side, _Side]", tuple(sides)), float(mr), radius, rng, seed, voxel)


def _working_clouds(source: tuple, target: tuple, mr: Any, voxel_size: Any
                    ) -> tuple[float, list[tuple[np.ndarray, Any, np.ndarray | None]], float]:
  """The working resolution of a pair and the clouds `register` works on: (mr, [(points,
  faces, index into the input points or None) for source and target], the thinning voxel edge
  or 0).

  `mr` None: `pair_resolution` of the two `working_resolution`s. `voxel_size` None: a cloud (not
  a mesh) whose mean spacing is under half the working resolution (`thinning_voxel`) is thinned
  by the voxel whose centroids come out spaced mr apart (a voxel of mr leaves them closer, about
  0.7 mr: the voxel is scaled by mr over the spacing that gives, measured); 0: none is; a
  positive number: both clouds are thinned at it (meshes included, which lose their faces).
  """
  _check_voxel_size(voxel_size)
  resolutions = [working_resolution(p, f, name=n)
                 for (p, f), n in zip((source, target), ("source", "target"))]
  if mr is None:
    mr = pair_resolution(*resolutions)
  elif not _is_positive(mr):
    raise ValueError(f"mr: expected a positive mesh resolution, got {mr!r}")
  out, used = [], 0.0
  for (pts, faces), res in zip((source, target), resolutions):
    voxel = (float(voxel_size) if voxel_size is not None
             else (None if faces is not None else thinning_voxel(res, float(mr))))
    if voxel and voxel_size is None:  # the voxel whose centroids are spaced mr apart
      spacing = mesh_resolution(np.asarray(voxel_downsample(pts, voxel)))[0]
      voxel = voxel * float(mr) / spacing if spacing > 0 else voxel
    if voxel:
      thin, index = voxel_downsample(pts, voxel, return_index=True)
      out.append((thin, None, index))
      used = voxel
    else:
      out.append((pts, faces, None))
  return float(mr), out, used


def _check_voxel_size(voxel_size: Any) -> None:
  if not (voxel_size is None or _is_positive(voxel_size) or
          (not isinstance(voxel_size, (bool, str)) and voxel_size == 0)):
    raise ValueError(f"voxel_size: expected None, 0 or a positive voxel edge in the clouds' "
                     f"units, got {voxel_size!r}")


def _input_indices(setup: _Setup, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
  """(C, 2) int64 correspondences as input point indices (a thinned side's working points map
  to their voxel's first input point)."""
  cols = [idx if side.input_index is None else side.input_index[idx]
          for side, idx in zip(setup.sides, (src, dst))]
  return np.stack(cols, axis=1).astype(np.int64)


def check_register_options(*, mr: Any = None, radius_mr: Any = 15.0, n_keypoints: Any = 3000,
                           n_correspondences: Any = 1000, iterations: Any = 1000,
                           inlier_mr: Any = 5.0, verify: Any = None, estimator: Any = "graph",
                           icp_iterations: Any = 50, icp_mr: Any = 3.0,
                           method: Any = "lrf_net_plus", descriptor: Any = "toldi",
                           seed: Any = 0, source_viewpoint: Any = None,
                           target_viewpoint: Any = None, keypoints: Any = "random",
                           mutual: Any = False, ratio: Any = None,
                           icp_mode: Any = "point_to_plane", icp_fine: Any = True,
                           voxel_size: Any = None) -> None:
  """Raise a ValueError naming the first of `register`'s options (every keyword but the clouds,
  `params` and `init`) that `register` would refuse; the defaults are `register`'s.

  `register` calls it before reading the clouds (also with `init`, where most options are not
  used), and `register_all` and `lrf-register` before any pair is registered."""
  for name, val in (("radius_mr", radius_mr), ("inlier_mr", inlier_mr), ("icp_mr", icp_mr)):
    if not _is_positive(val):
      raise ValueError(f"{name}: expected a positive number of mesh resolutions, got {val!r}")
  for name, val in (("n_keypoints", n_keypoints), ("n_correspondences", n_correspondences),
                    ("iterations", iterations)):
    if not _is_count(val, 1):
      raise ValueError(f"{name}: expected a positive integer, got {val!r}")
  for name, val in (("icp_iterations", icp_iterations), ("verify", verify)):
    if not ((val is None and name == "verify") or _is_count(val, 0)):
      raise ValueError(f"{name}: expected a non-negative integer, got {val!r}")
  validate_seed(seed)
  _check_voxel_size(voxel_size)
  if estimator not in ESTIMATORS:
    raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
  if not isinstance(method, str) or method not in METHODS:
    raise ValueError(f"method: unknown LRF method {method!r}; expected one of {sorted(METHODS)}")
  if not isinstance(descriptor, str) or descriptor not in DESCRIPTORS:
    raise ValueError(f"descriptor: unknown descriptor {descriptor!r}; expected one of "
                     f"{sorted(DESCRIPTORS)}")
  if icp_mode not in ("point_to_plane", "point_to_point"):
    raise ValueError(f"icp_mode: expected 'point_to_plane' or 'point_to_point', got {icp_mode!r}")
  if keypoints not in KEYPOINTS:
    raise ValueError(f"keypoints: expected one of {KEYPOINTS}, got {keypoints!r}")
  if not isinstance(mutual, (bool, np.bool_)):
    raise ValueError(f"mutual: expected True or False, got {mutual!r}")
  if ratio is not None and not (_is_positive(ratio) and ratio <= 1):
    raise ValueError(f"ratio: expected None or a ratio-test threshold in (0, 1], got {ratio!r}")
  if not isinstance(icp_fine, (bool, np.bool_)):
    raise ValueError(f"icp_fine: expected True or False, got {icp_fine!r}")
  for name, vp in (("source_viewpoint", source_viewpoint), ("target_viewpoint", target_viewpoint)):
    validate_viewpoint(vp, name)
  if mr is not None and not _is_positive(mr):
    raise ValueError(f"mr: expected a positive mesh resolution, got {mr!r}")


def _is_positive(val: Any) -> bool:
  """A positive finite number (False for strings, bools, None, lists: no TypeError)."""
  if isinstance(val, (str, bytes, bool, np.bool_)):
    return False
  try:
    return bool(np.isfinite(val) and val > 0)
  except (TypeError, ValueError):
    return False


def _is_count(val: Any, minimum: int) -> bool:
  """An integer-valued number >= minimum (1000.0 counts; strings, bools, None and 2.5 do not)."""
  if isinstance(val, (str, bytes, bool, np.bool_)):
    return False
  try:
    return bool(int(val) == val and val >= minimum)
  except (TypeError, ValueError, OverflowError):
    return False


def _side_frames(side: _Side, setup: _Setup, method: str, params: Any
                 ) -> tuple[np.ndarray, np.ndarray]:
  """Stage "frames": the LRFs of one side's keypoints. A viewpoint-aware method (lrf_net_plus)
  given neither a viewpoint nor a mesh takes its z sign from each patch (`oriented_sign=False`)
  rather than from normals oriented over the whole cloud: that orientation costs about a second
  per cloud and, measured on the registration benchmark, does not register more pairs."""

  spec = METHODS[method]
  options: dict[str, Any] = ({"oriented_sign": False}
             if spec.uses_viewpoint and side.viewpoint is None and side.faces is None else {})
  _check_options(method, options, spec)  # options of register's own choosing: checked here
  cloud = CloudInput(side.points, side.faces, None if spec.uses_viewpoint else side.normals)
  # two arrays (no return_confidence); numpy from the host kernels, so no JAX is imported
  frames, valid = _frames_checked(
      method, cloud, side.keypoints, setup.radius, params=params, seed=setup.seed,
      viewpoint=side.viewpoint, options=options)
  return np.asarray(frames), np.asarray(valid)


def _side_descriptors(side: _Side, frames: tuple[np.ndarray, np.ndarray], setup: _Setup,
                      descriptor: str) -> tuple[np.ndarray, np.ndarray]:
  """Stage "descriptors": one side's descriptors on its frames ((m, 3, 3) float32 and (m,) bool,
  as `_side_frames` gives them)."""

  desc, ok = _descriptors_checked(descriptor, side.points, side.keypoints, setup.radius,
                                  frames[0], frames[1], faces=side.faces, seed=setup.seed,
                                  normals=side.normals)
  return np.asarray(desc), np.asarray(ok)


def _match(frames, descs, estimator: str, n_correspondences: int, radius_mr: float,
           mutual: bool = False, ratio: float | None = None) -> tuple[np.ndarray, np.ndarray]:
  """Stage "matching": nearest descriptors (mutual ones only with `mutual`, those passing the
  ratio test with `ratio`), the `n_correspondences` of smallest ratio d1/d2."""

  (_, v_s), (_, v_t) = frames
  (d_s, ok_s), (d_t, ok_t) = descs
  need_frames = estimator != "3point"
  qi, ri, _ = select_correspondences(d_s, d_t, ok_s & (v_s | ~need_frames),
                                     ok_t & (v_t | ~need_frames), n=n_correspondences,
                                     mutual=mutual, ratio=ratio)
  if len(qi) < (1 if need_frames else 3):
    raise ValueError(f"register: only {len(qi)} descriptor matches (valid frames: source "
                     f"{int(v_s.sum())}, target {int(v_t.sum())}); the clouds are too small or "
                     f"too sparse for r = {radius_mr} mr")
  return qi, ri


def _hypotheses(src, dst, f_src, f_dst, estimator: str, iterations: int, radius: float,
                seed: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
  """Stage "hypotheses" from the centred float32 coordinates, host float64
  (`host`, `graph`), (H, 3, 3) and (H, 3): "lrf" one pose per
  correspondence from its LRFs; "3point" `iterations` seeded triples (the `ransac_3point`
  sampler); "graph" one per seed of the compatibility graph (distances within `threshold`,
  LRF rotations within `GRAPH_ANGLE_DEG`), followed by the seeds' own LRF poses."""
  if estimator == "3point":
    samples = np.asarray(_triples(len(src), iterations, seed))
    return host.kabsch_batch(src[samples], dst[samples])
  rs, ts = host.lrf_hypotheses(src, f_src, dst, f_dst, float(radius))
  if estimator == "lrf":
    return rs, ts
  gr, gt, seeds, _ = graph.graph_hypotheses(
      src, dst, rs, distance=threshold, angle_deg=GRAPH_ANGLE_DEG, n_seeds=GRAPH_SEEDS,
      consensus=GRAPH_CONSENSUS, nms=GRAPH_NMS_RADII * radius)
  return np.concatenate([gr, rs[seeds]]), np.concatenate([gt, ts[seeds]])


# The rivals of the correspondences outside the winner's (`_rest_hypotheses`): those within
# REST_FACTOR x the inlier distance of the winner belong to it and are left out, and are not
# counted for these rivals.
REST_FACTOR = 2.0
# ... and such a rival counts only when its overlap is at least REST_OVERLAP x the winner's
# (`_rest_rival`).
REST_OVERLAP = 0.5
# ... and explains at least REST_SHARE x the winner's inliers (a split of the correspondences) ...
REST_SHARE = 0.8
# ... of the REST_CANDIDATES such rivals with the most correspondences.
REST_CANDIDATES = 16
# Points of the overlap the degeneracy test (`_overlap_constraints`) reads at most.
CONSTRAINT_POINTS = 2000
# estimator="graph" (`graph.graph_hypotheses`): the LRF rotation agreement bound, the
# seeds, the consensus set of each and the seeds' suppression radius in support radii.
GRAPH_ANGLE_DEG = 45.0
GRAPH_SEEDS = 100
GRAPH_CONSENSUS = 30
GRAPH_NMS_RADII = 0.25




def _verify(rs, ts, counts, cs, cd, src_pts, target_grid, distance, verify, rng
            ) -> tuple[int, np.ndarray]:
  """Stage "verification": the hypothesis of best overlap among the `verify` best-scoring ones
  (None: all; 0: the inlier count alone decides)."""
  order = np.argsort(-counts, kind="stable")
  best = int(order[0])
  fits = np.zeros(0)
  if verify is None or verify > 0:
    cand = order if verify is None else order[:int(verify)]
    sub = src_pts[np.sort(rng.choice(len(src_pts), min(1000, len(src_pts)), replace=False))]
    r_c = np.asarray(rs, np.float64)[cand]
    t_c = np.asarray(ts, np.float64)[cand] + cd - np.einsum("hij,j->hi", r_c, cs)
    fits = overlap_scores(r_c, t_c, sub, target_grid, distance)
    best = int(cand[int(np.argmax(fits))])  # first maximum: the higher inlier count
  return best, fits
