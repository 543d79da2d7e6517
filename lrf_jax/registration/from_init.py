"""`register(..., init=T)`: ICP from a given pose, then the verdict on the default evidence.

`T` is refined as `register` refines its winner (`refine.refine`: ICP, two passes, the input
points' pass of a thinned pair) and judged on the evidence `register` gathers without an init:
the default matching's correspondences (one pass; pooled seeds with `effort="high"`, and after
a "not sure" with the default `"normal"`), the compatibility graph's hypotheses on them, their
chance level and the rivals of the refined pose (`stages.judge_pose`), under the one rule of
`evidence.decide`. So an init is claimed where that evidence singles out the refined pose, and a
wrong init is not: the right pose, among the graph's hypotheses, is its rival, or the wrong
pose's support stays at the chance level.

Where the refined init is "not sure" (ICP stopped short of the evidence's pose, or the init is
a few degrees off the pose the correspondences pin down), the search of steps 3-4 is run again
limited to its neighbourhood (`stages.verify_near`: the best hypothesis not distinct from it,
refitted, refined and judged as `register`'s own winner, "moved" test included), and that pose
is returned where it is claimed. Where the pooled evidence leaves it not sure, the same runs
once more at twice the working resolution (`effort.coarser_pass`), as `register` does without
an init. It is held to the rule every winner is held to (its support
at least `VERDICT_GRAPH_FACTOR` times chance's and every distinct pose's, the pose `register`
picks without an init among them), so a wrong init does not lend a wrong pose any support.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from lrf_jax.registration import stages
from lrf_jax.registration.effort import (coarser_options, coarser_pass, escalates, one_pass,
                                         pooled_stages, tried)
from lrf_jax.registration.estimators import finish_result
from lrf_jax.registration.evidence import Evidence, Verdict, decide, distinct, poses_apart
from lrf_jax.registration.options import RegisterOptions
from lrf_jax.registration.outcome import judged
from lrf_jax.registration.refine import Refined, check_init, refine
from lrf_jax.registration.result import Registration
from lrf_jax.search import engine
from lrf_jax.search.grid import serial_blas


def register_from_init(source: Any, target: Any, init: Any, opts: RegisterOptions, params: Any,
                       timer: stages.StageTimer, *, last: bool = False) -> Registration:
  """`register(source, target, init=init, ...)` (module docstring): `init` checked
  (`refine.check_init`: a rotation block within `refine.INIT_PROJECT` of orthonormal is
  projected), the evidence gathered, ICP from `init`, the verdict on the refined pose.
  `last`: this is `effort.coarser_pass`'s pass (one pass, judged as a last step: its verdict
  names no further one).

  Returns:
    `Registration` whose `coarse_transform` is the (projected) init and `transform` the refined
    pose; `success` as `register`'s verdict would judge that pose.

  Raises:
    ValueError: an init that is not a (4, 4) rigid transform (with the figure), and every error
      of `register`.
  """
  pose = check_init(init, "init")
  effort = opts.verdict.effort
  if effort == "high":
    passes = pooled_stages(source, target, opts, params, timer)
  else:
    passes = one_pass(source, target, opts, params, timer)
  prepared = passes[0]
  distance = opts.icp.icp_mr * prepared.mr
  start = stages.Verified(finish_result(pose[:3, :3], pose[:3, 3], np.zeros(0, bool), 0, 0),
                          np.zeros(0), np.zeros(0, bool), 0,
                          engine.Grid(prepared.sides[1].points, distance), distance)
  refined = refine(prepared, start, opts.icp, timer)
  with timer("hypotheses"), serial_blas():
    hyps = stages.hypothesize(prepared, passes[1], passes[2], opts.hypotheses)
  kept = "" if hyps is None else kept_init(prepared, passes[2], pose, refined.transform,
                                           opts.hypotheses.inlier_mr, hyps.chance)
  if kept:  # ICP slid away from what the init explains: the init itself, measured unmoved
    refined = refine(prepared, start, dataclasses.replace(opts.icp, icp_iterations=0), timer)
    refined = refined._replace(kept=kept)
  gathered = "high" if effort == "high" or last else effort
  first = _judged(prepared, passes[2], hyps, refined, pose, opts, timer, gathered)
  first = _or_near(first, prepared, passes[2], hyps, pose, opts, timer, gathered)
  if effort == "high":
    return coarser_pass(first, None, _coarser_run(source, target, pose, first, opts, params,
                                                  timer), opts, timer)
  if effort != "normal" or not escalates(first.reason_code):
    return first
  pooled = pooled_stages(source, target, opts, params, timer, first=prepared)
  with timer("hypotheses"), serial_blas():
    pooled_hyps = stages.hypothesize(*pooled, opts.hypotheses)
  again = _judged(pooled[0], pooled[2], pooled_hyps, refined, pose, opts, timer, "high")
  again = _or_near(again, pooled[0], pooled[2], pooled_hyps, pose, opts, timer, "high")
  note = tried(first.reason_code)
  return dataclasses.replace(coarser_pass(again, note, _coarser_run(source, target, pose, again,
                                                                    opts, params, timer),
                                          opts, timer), escalated=True)


def _coarser_run(source: Any, target: Any, pose: np.ndarray, pooled: Registration,
                 opts: RegisterOptions, params: Any, timer: stages.StageTimer
                 ) -> Callable[[], Registration]:
  """`effort.coarser_pass`'s pass with an init: `register_from_init`'s one pass (ICP from
  `pose`, the verdict, the search near it) at `effort.COARSER_MR` x `pooled`'s working
  resolution."""
  def run() -> Registration:
    wide = coarser_options(opts, pooled.mr).with_overrides(effort="fast")
    return register_from_init(source, target, pose, wide, params, timer, last=True)
  return run


def _or_near(judged_init: Registration, prepared: stages.Prepared, matches: stages.Matches,
             hyps: Any, init: np.ndarray, opts: RegisterOptions,
             timer: stages.StageTimer, gathered: str) -> Registration:
  """`judged_init` (the refined init, judged at itself) where it is claimed; else, where that is
  claimed, the pose `register` finds when its search is limited to the neighbourhood of the
  refined init (`stages.verify_near`: the best hypothesis not distinct from it, or the pose
  itself, refitted on its inliers; then ICP from the refit and the verdict with its "moved"
  test, as for `register`'s own winner). `hyps`: this evidence's `stages.hypothesize` (None:
  there are none). `init` is reported as the coarse transform either way. With
  `icp_iterations=0` (no refinement asked for) the init is judged as given, and only so."""
  if judged_init.success or opts.icp.icp_iterations == 0 or hyps is None:
    return judged_init
  with timer("verification"), serial_blas():
    verified = stages.verify_near(prepared, hyps, judged_init.transform, opts.hypotheses,
                                  opts.icp.icp_mr, matches.own)
  if verified.coarse.n_inliers < 3:  # nothing to refit on
    return judged_init
  near = judged(prepared, matches, hyps, verified, refine(prepared, verified, opts.icp, timer),
                opts, timer, gathered)
  if not near.success:
    return judged_init
  return dataclasses.replace(near, coarse_transform=init,
                             reason=f"refined from init and the hypotheses near it: "
                                    f"{near.reason}")


def explained(prepared: stages.Prepared, matches: stages.Matches, pose: np.ndarray,
              inlier_mr: float) -> int:
  """How many of the matched keypoint pairs `pose` brings within `inlier_mr` mr of each other
  (the hypotheses' inlier distance): the correspondences a pose explains."""
  s, t = prepared.sides
  a = s.points[s.keypoints[matches.source]] @ pose[:3, :3].T + pose[:3, 3]
  b = t.points[t.keypoints[matches.target]]
  return int(np.sum(np.linalg.norm(a - b, axis=1) <= inlier_mr * prepared.mr))


def kept_init(prepared: stages.Prepared, matches: stages.Matches, init: np.ndarray,
              refined: np.ndarray, inlier_mr: float, chance: int) -> str:
  """The note saying that the init is kept as given, or "" where ICP's pose stands.

  An init is independent of the correspondences, so they can judge ICP's move: on an overlap
  that constrains the pose in every direction ICP keeps or gains what the init explains
  (`explained`); where it does not (a floor and a wall, along which ICP slides), ICP's pose
  explains fewer of them, or moves to a pose `evidence.distinct` from the init (as a rival is;
  `evidence.poses_apart` at the source centroid) that explains no more of them, and the init stays. Where the init explains no more
  than `chance` (the most a hypothesis explains on shuffled correspondences) they say nothing of
  it, and ICP's pose stands. (The pipeline's own coarse pose is fitted to those correspondences,
  so this test would favour it: it applies to inits only.)
  """
  before = explained(prepared, matches, init, inlier_mr)
  after = explained(prepared, matches, refined, inlier_mr)
  if before <= chance or after > before:
    return ""
  if after < before:
    return (f"init kept as given: ICP from it explains {after} of the correspondences, the "
            f"init {before}")
  deg, distance = poses_apart(refined, init, prepared.sides[0].points.mean(axis=0))
  if not distinct(deg, distance, prepared.radius):
    return ""
  return (f"init kept as given: ICP from it moved {deg:.1f} deg and {distance:.3g} to a distinct "
          f"pose that explains {after} of the correspondences, as many as the init")


def _judged(prepared: stages.Prepared, matches: stages.Matches, hyps: Any, refined: Refined,
            pose: np.ndarray, opts: RegisterOptions, timer: stages.StageTimer,
            gathered: str) -> Registration:
  """The verdict on the refined pose from the evidence of one pass or the pooled seeds
  (`gathered`: "fast"/"normal" one pass, "high" pooled; `hyps`: its `stages.hypothesize`, None
  where there are none), and the `Registration`."""
  s, t = prepared.sides
  correspondences = stages.input_indices(prepared, s.keypoints[matches.source],
                                         t.keypoints[matches.target])
  n = len(matches.source)
  mask, chance, rival, ev_inliers = np.zeros(n, bool), 0, 0, 0
  if hyps is None:
    decision = Verdict(False, f"not sure: no two of the {n} correspondences agree, so nothing "
                              "witnesses the pose refined from init", "no_hypothesis")
  else:
    with timer("verification"), serial_blas():
      mask, ev_mask, rival = stages.judge_pose(prepared, hyps, refined.transform,
                                               opts.hypotheses, opts.icp.icp_mr, matches.own)
    chance, ev_inliers = hyps.chance, int(np.sum(ev_mask))
    decision = decide(Evidence(n_inliers=ev_inliers, chance_inliers=chance, rival_inliers=rival,
                               fitness=refined.fitness, contrast=0.0,
                               estimator=opts.hypotheses.estimator,
                               degeneracy=refined.degeneracy,
                               free_direction=refined.free_direction, effort=gathered,
                               from_init=True))
  return Registration(transform=refined.transform, coarse_transform=pose, inliers=mask,
                      n_inliers=int(mask.sum()), correspondences=correspondences,
                      voxel_size=prepared.voxel_size, fitness=refined.fitness,
                      rmse=refined.rmse, mr=float(prepared.mr), seconds=timer.total(),
                      timings=dict(timer.seconds), success=decision.success,
                      inlier_ratio=int(mask.sum()) / max(n, 1), chance_inliers=chance,
                      reason=f"{refined.kept or 'refined from init'}: {decision.reason}",
                      overlap=refined.fitness,
                      rival_inliers=rival, reason_code=decision.code,
                      evidence_inliers=ev_inliers, degeneracy=refined.degeneracy)
