"""`register(source, target)`: the user-facing registration pipeline.

mr from the source, seeded random (or ISS) keypoints on both clouds, LRF-Net frames, TOLDI
descriptors, ratio matching, hypotheses from the compatibility graph of the correspondences
(`lrf_jax.registration.graph`: distances preserved and one-correspondence LRF poses in
agreement; or the RANSACs of `estimators.py`), then point-to-plane ICP (`refine.py`) and a
verdict (`evidence.py`) that claims success only when the winner's support is far above chance
and above every distinct pose's (`rivals.py`). Each step is a stage of `stages.py` with a typed
result; the options are one frozen `RegisterOptions` (`options.py`). It generates and scores its
hypotheses on the host (`lrf_jax.registration.host`), the same arithmetic as the jitted
estimators without a JAX program to load in every fresh process.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from lrf_jax.registration import stages
from lrf_jax.registration.effort import (coarser_options, coarser_pass, escalates, one_pass,
                                         pooled_stages, tried)
from lrf_jax.registration.icp_host import icp
from lrf_jax.registration.options import RegisterOptions, check_register_options, resolve
from lrf_jax.registration.from_init import register_from_init
from lrf_jax.registration.outcome import judged, keypoint_indices
from lrf_jax.registration.refine import icp_subset, refine
from lrf_jax.registration.result import Registration
from lrf_jax.registration.rivals import overlap_scores
from lrf_jax.search.grid import serial_blas

__all__ = ["Registration", "RegisterOptions", "check_register_options", "overlap_scores",
           "register"]


def register(source: Any, target: Any, options: RegisterOptions | None = None, *,
             params: Any = None, init: Any = None, **overrides: Any) -> Registration:
  """Rigidly register `source` onto `target` with learned LRFs and a compatibility graph.

  Pipeline (every length in mr, the pair's working resolution: see `mr` below; on clean clouds
  the source's mean edge length for a mesh, mean nearest-neighbor distance for a cloud):

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
     source points drawn among those within icp_mr mr of the target (`overlap_points`); a
     pair thinned by default (`voxel_size=None`) then gets one ICP pass on its input points
     (`refine.raw_pass`; a pose that moves a point by over `RAW_MAX_SHIFT_MR` mr is refused),
     save a side thinned for being oversampled (`Resolution.capped`): its voxel centroids
     are its working points;
  6. the verdict (`evidence.decide`), one rule for every estimator and option: it claims
     success when the winner's inliers are at least `VERDICT_GRAPH_FACTOR` times (+
     `VERDICT_GRAPH_MARGIN`) both what chance alignment reaches on the correspondences
     shuffled and what the best distinct pose explains outside them, ICP pairs enough of the
     source, the overlap leaves no motion free (`evidence.constraint_spectrum`) and ICP's pose
     is not a distinct pose from the winner whose inliers were counted ("moved"). Whatever
     chose the hypotheses (estimator, ratio, mutual, n_correspondences, the detector, learned
     weights other than the object weights), the evidence is counted on the default
     matching's correspondences (`stages.EVIDENCE_CORRESPONDENCES`; `stages.default_evidence`)
     with the compatibility graph's hypotheses (plus the estimator's own and the graph's on
     the correspondences outside the winner's inliers, as rivals), so no option claims what
     the default's evidence would not.
     `Registration.reason_code` says which test decided.

  `effort="high"` runs steps 1-2 for `effort.EFFORT_SEEDS` seeds (seed, seed + 1, ...) with
  `effort.EFFORT_KEYPOINTS` times the keypoints and pools their correspondences before steps 3-6,
  which run once on the pooled set (`lrf_jax.registration.effort`; the chance level and the
  rivals are counted on the same pooled correspondences): a few times slower, and it claims
  some pairs one pass leaves "not sure". `effort="fast"` is one pass of steps 1-6.
  `effort="normal"` (default) is that pass, and where its verdict is "not sure", `"high"`'s
  pooled pass on the same working clouds (`effort.escalates`), whose result it returns: the
  same as `effort="high"`'s, bit for bit, with `escalated` True and `reason` saying what was
  tried. Where the pooled pass is not sure too and `mr` was measured (not given),
  `effort.coarser_pass` runs one pass of steps 1-6 at `effort.COARSER_MR` x the working
  resolution and returns its pose where it is claimed (`"high"` ends with the same step; so
  does an init's judgement). So it claims a pair when one pass, the pooled evidence or the
  coarser pass claims it, and costs one pass on a pair the first pass claims.

  With `init` (a (4, 4) rigid transform) the pose is `init` refined by step 5 instead of steps
  3-4's winner, and step 6 judges it on the same evidence (`from_init`: steps 1-2 and the
  compatibility graph's hypotheses as rivals): it claims an init where the evidence would have
  claimed the refined pose, and a wrong init is not claimed; where the refined init is "not
  sure", steps 3-6 run again on the hypotheses near it, and their pose is returned where it is
  claimed (with `icp_iterations=0` the init is judged as given only). A rotation block within
  `refine.INIT_PROJECT` of orthonormal is projected to the nearest rotation (a warning gives the
  figure).

  The same inputs and seed give the same transform.

  Args:
    source: (n, 3) array, an `lrf_jax.io.Cloud`, a path to any cloud/mesh `lrf_jax.io`
      reads (PLY, PCD, XYZ/TXT(.gz), NPY), or an object with `.points` (e.g. Open3D's), as
      `compute_frames` takes (`lrf_jax.inputs.as_cloud`).
    target: the same for the target.
    options: a `RegisterOptions` (None: `options.DEFAULTS`, every default below).
    params: learned LRF parameters (None: the shipped weights the `weights` option names).
    init: optional (4, 4) initial source -> target transform: refined by ICP and judged (above).
    **overrides: fields of `RegisterOptions` replacing those of `options` (listed below;
      each stage's table of options is in the docs' Pipeline stages pages).

  Keyword Args:
    mr (float | None): the working resolution in the clouds' units, the unit of every length
      below (None: measured, `geometry.resolution.registration_resolution` and
      `pair_resolution`: the source's mean point spacing or mean edge length; on a raw, uneven
      cloud such as a LiDAR sweep the area-weighted median spacing; for a cloud sampled more
      finely than 1/300 of its extent (a full-density fragment) a coarser fraction of it,
      `resolution.capped_extent_ratio`; for a pair whose
      resolutions differ over 2-fold, or where one is uneven or capped, the coarser one).
    radius_mr (float): support radius of the LRFs and descriptors, in mr (the paper: 15).
    n_keypoints (int): keypoints per cloud (fewer when a cloud has fewer points).
    n_correspondences (int): correspondences kept (and LRF hypotheses).
    iterations (int): hypotheses of the 3-point estimator.
    inlier_mr (float): inlier distance of the hypothesis score, in mr.
    verify (int | None): hypotheses re-ranked by overlap (None: all of them; 0: none).
    estimator (str): "graph" (compatibility graph, default), "lrf" (one correspondence per
      hypothesis) or "3point" (classic).
    icp_iterations (int): ICP iterations (0: no ICP, `transform` = the RANSAC estimate).
    icp_mr (float): ICP pairing and overlap distance, in mr.
    method (str): LRF method (a key of `lrf_jax.METHODS`; default "lrf_net_plus", the most
      repeatable shipped one; "lrf_net" is the paper's LRF-Net; mesh methods need mesh inputs).
    descriptor (str): a key of `lrf_jax.descriptors.DESCRIPTORS`.
    weights (str): the weights of a learned method when `params` is None: "objects" (default),
      "rooms", "streets" or a parameter file's path (`compute_frames`' `weights`).
    seed (int): seed of keypoints, neighbor subsamples and sampling.
    source_viewpoint (tuple[float, float, float] | None): the (3,) sensor position of a
      single-view source scan, in its own coordinates: its estimated normals (and
      `method="lrf_net_plus"`'s z) are oriented towards it (see `compute_frames`). Without it a
      scan's normals are oriented by propagation, which cannot know which side of an open scan
      is out.
    target_viewpoint (tuple[float, float, float] | None): the same for the target scan, in its
      own coordinates.
    keypoints (str): "random" or "iss".
    effort (str): "normal" (default), "fast" or "high" (above).
    mutual (bool): keep mutual nearest-neighbor matches only.
    ratio (float | None): optional ratio-test threshold in (0, 1].
    icp_mode (str): "point_to_plane" (default) or "point_to_point" (`icp`).
    icp_fine (bool): run the second ICP pass at the adaptive gate (False: one pass at icp_mr mr,
      the behaviour before it).
    voxel_size (float | None): thin the clouds by voxel averaging first (`voxel_downsample`),
      voxels of this edge in cloud units; 0 keeps every point; None (default) thins a cloud at
      the working resolution where its mean spacing is under half of it (a raw sweep's near
      field, a full-density fragment against a coarser one) or where the extent set the
      resolution (a full-density fragment), and keeps clean clouds as they are.

  Returns:
    `Registration`; `transform` maps source points into the target's frame.

  Raises:
    TypeError: an override that is not an option of `register`.
    ValueError: a cloud that is not a non-empty (n, 3) array of finite floats, fewer than 10
      points, a non-positive count or distance, a seed that is not a non-negative integer, or
      an unknown estimator/method/descriptor/keypoints, an `init` that is not a (4, 4) rigid
      transform, a ratio outside (0, 1], or `weights` given with `params`.
    FileNotFoundError: a path that does not exist.

  Example:
    >>> reg = lrf_jax.register("scan_a.ply", "scan_b.ply")
    >>> aligned = points_a @ reg.transform[:3, :3].T + reg.transform[:3, 3]
  """
  opts = resolve(options, overrides)
  if params is not None and opts.description.weights != "objects":
    raise ValueError(f"weights: {opts.description.weights!r} given with params; expected one of "
                     "the two (params are the weights themselves)")
  timer = stages.StageTimer()
  if init is not None:
    return register_from_init(source, target, init, opts, params, timer)
  effort = opts.verdict.effort
  if effort == "high":
    pooled = conclude(*pooled_stages(source, target, opts, params, timer), opts, timer,
                      pooled=True)
    return coarser_pass(pooled, None, _coarser_run(source, target, pooled, opts, params, timer),
                        opts, timer)
  prepared, features, matches = one_pass(source, target, opts, params, timer)
  # "normal"'s first pass names no next step: the pooled pass follows it itself
  first = conclude(prepared, features, matches, opts, timer, pooled=effort == "normal")
  if effort == "fast" or not escalates(first.reason_code):
    return first
  note = tried(first.reason_code)
  try:
    pooled = conclude(*pooled_stages(source, target, opts, params, timer, first=prepared), opts,
                      timer, pooled=True)
  except ValueError as e:  # the inputs passed the first pass: the pooled matching found none
    return dataclasses.replace(first, reason=f"{first.reason} ({note}: {e})",
                               seconds=timer.total(), timings=dict(timer.seconds), escalated=True)
  return dataclasses.replace(coarser_pass(pooled, note, _coarser_run(source, target, pooled, opts,
                                                                   params, timer), opts, timer),
                             escalated=True)


def _coarser_run(source: Any, target: Any, pooled: Registration, opts: RegisterOptions,
                 params: Any, timer: stages.StageTimer) -> Callable[[], Registration]:
  """`effort.coarser_pass`'s pass: steps 1-6 once at `effort.COARSER_MR` x `pooled`'s working
  resolution, judged as a last step (naming no further one)."""
  def run() -> Registration:
    wide = coarser_options(opts, pooled.mr)
    return conclude(*one_pass(source, target, wide, params, timer), wide, timer, pooled=True)
  return run


def conclude(prepared: stages.Prepared, features: stages.Features, matches: stages.Matches,
             opts: RegisterOptions, timer: stages.StageTimer, *, pooled: bool = False
             ) -> Registration:
  """The stages after matching: hypotheses, verification, ICP and the verdict, and the
  `Registration` (the identity, not estimated, when no hypothesis could be built). `pooled`:
  the correspondences are `effort.pool`'s, or a pooled pass follows (the verdict names no
  further effort as its next step)."""
  with timer("hypotheses"), serial_blas():
    hyps = stages.hypothesize(prepared, features, matches, opts.hypotheses)
  if hyps is None:  # no two correspondences agree: no pose to verify
    return _not_estimated(prepared, stages.input_indices(prepared, *keypoint_indices(prepared, matches)),
                          opts, timer)
  with timer("verification"), serial_blas():
    verified = stages.verify(prepared, hyps, opts.hypotheses, opts.icp.icp_mr, matches.own)
  refined = refine(prepared, verified, opts.icp, timer)
  return judged(prepared, matches, hyps, verified, refined, opts, timer,
                "high" if pooled else opts.verdict.effort)


def _not_estimated(prepared: stages.Prepared, correspondences: np.ndarray, opts: RegisterOptions,
                   timer: stages.StageTimer) -> Registration:
  """`register`'s result when no hypothesis could be built: the identity, not sure, and why
  (its overlap and rmse are the identity's, measured as for an estimate)."""
  with timer("icp"):
    src_pts, dst_pts = prepared.sides[0].points, prepared.sides[1].points
    _, fitness, rmse = icp(icp_subset(src_pts, prepared.rng), dst_pts, np.eye(4),
                           max_distance=opts.icp.icp_mr * prepared.mr, iterations=0)
  n, estimator = len(correspondences), opts.hypotheses.estimator
  if estimator != "graph":
    why = f"the {estimator} estimator built none from {n} correspondences"
  elif n < 2:
    why = f"the graph estimator needs two compatible correspondences, and there is {n}"
  else:
    why = (f"no two of the {n} correspondences are compatible within inlier_mr = "
           f"{opts.hypotheses.inlier_mr:g} mr")
  return Registration(transform=np.eye(4), coarse_transform=np.eye(4),
                      inliers=np.zeros(n, bool), n_inliers=0,
                      correspondences=np.asarray(correspondences, np.int64), fitness=fitness,
                      rmse=rmse, mr=float(prepared.mr), seconds=timer.total(),
                      timings=dict(timer.seconds), success=False,
                      reason=(f"no pose hypothesis: {why}; the transform is the identity, not an "
                              "estimate"),
                      overlap=fitness, estimated=False, reason_code="no_hypothesis")
