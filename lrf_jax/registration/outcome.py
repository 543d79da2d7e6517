"""The verdict on a pose the stages found and refined (`evidence.decide`), and the
`Registration` that reports it: shared by `register`'s own winner (`pipeline.conclude`) and an
init's refit (`from_init`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from lrf_jax.registration import stages
from lrf_jax.registration.evidence import Evidence, decide, overlap_contrast, poses_apart
from lrf_jax.registration.options import RegisterOptions
from lrf_jax.registration.result import Registration


def keypoint_indices(prepared: stages.Prepared, matches: stages.Matches
                     ) -> tuple[np.ndarray, np.ndarray]:
  """The correspondences' working-cloud point indices (source, target)."""
  s, t = prepared.sides
  return s.keypoints[matches.source], t.keypoints[matches.target]


def judged(prepared: stages.Prepared, matches: stages.Matches, hyps: stages.Hypotheses,
           verified: stages.Verified, refined: Any, opts: RegisterOptions,
           timer: stages.StageTimer, gathered: str) -> Registration:
  """The verdict (`evidence.decide`) on the stages' results, and the `Registration`.
  `gathered`: the effort whose evidence it is ("high": pooled; `Evidence.effort`)."""
  contrast = overlap_contrast(verified.fits)
  moved_deg, moved_distance = poses_apart(refined.transform, verified.coarse.transform,
                                          hyps.evidence.cs)
  evidence = Evidence(n_inliers=int(np.sum(verified.evidence_mask)), chance_inliers=hyps.chance,
                      rival_inliers=verified.rival, fitness=refined.fitness, contrast=contrast,
                      estimator=opts.hypotheses.estimator, degeneracy=refined.degeneracy,
                      free_direction=refined.free_direction, effort=gathered,
                      moved_deg=moved_deg, moved_distance=moved_distance,
                      distinct_distance=float(prepared.radius))
  decision = decide(evidence)
  coarse, n = verified.coarse, len(matches.source)
  return Registration(transform=refined.transform, coarse_transform=coarse.transform,
                      inliers=coarse.inliers, n_inliers=coarse.n_inliers,
                      correspondences=stages.input_indices(prepared,
                                                           *keypoint_indices(prepared, matches)),
                      voxel_size=prepared.voxel_size, fitness=refined.fitness,
                      rmse=refined.rmse, mr=float(prepared.mr), seconds=timer.total(),
                      timings=dict(timer.seconds), success=decision.success,
                      inlier_ratio=coarse.n_inliers / max(n, 1), chance_inliers=hyps.chance,
                      overlap_contrast=contrast, reason=decision.reason, overlap=refined.fitness,
                      rival_inliers=verified.rival, reason_code=decision.code,
                      evidence_inliers=evidence.n_inliers, degeneracy=refined.degeneracy)
