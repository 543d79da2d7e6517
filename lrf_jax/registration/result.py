"""`Registration`: what `register` returns (the transform, the verdict and its evidence)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from lrf_jax.registration.errors import pose_errors


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
    mr: the mesh resolution used as the unit (cloud units): `effort.COARSER_MR` x the measured
      one where the pass at twice the working resolution is returned (`effort.coarser_pass`).
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
      "low_overlap", "degenerate", "moved", "chance", "rival", "no_hypothesis".
    evidence_inliers: the winner's inliers among the evidence correspondences (the default
      matching's, `_evidence_matches`), the count the verdict compares with `chance_inliers`
      and `rival_inliers`; `n_inliers` when no option changed the matching.
    degeneracy: how well the overlap pins the pose down (`evidence.constraint_spectrum`: the
      weakest direction of the point-to-plane constraints over the strongest; below
      `evidence.DEGENERATE_RATIO` the verdict is "degenerate").
    escalated: True when `effort="normal"`'s first pass was "not sure" and this is the pooled
      pass that followed, or the pass at twice the working resolution after it
      (`effort="high"`'s result; `reason` names every pass).
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
  escalated: bool = False

  def summary(self, gt: Any = None) -> str:
    """A few lines a person reads: the verdict and its reason, the estimated overlap and RMSE
    (and the voxel edge the clouds were thinned at, if they were), the inliers against what
    chance and the best distinct pose reach, the errors against a
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
             f"transform), rmse {self.rmse / self.mr:.3f} mr (mr = {self.mr:.6g})"
             + (f"; thinned at voxels of {self.voxel_size:.4g} first (voxel_size=0 keeps "
                "every point)" if self.voxel_size > 0 else "")]
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
