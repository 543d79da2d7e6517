"""Whether `register` believes its result: the evidence it gathered and the thresholds.

The winner must be well supported (inliers far above what chance alignment and any distinct pose
reach) and ICP must pair enough of the source; `verdict` says which test decided.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# The verdict (`verdict`). ICP pairs at least VERDICT_FITNESS of the source (VERDICT_GRAPH_FITNESS
# for estimator="graph", whose evidence does not need the overlap to be large).
# estimator="graph": the winner's inliers reach VERDICT_GRAPH_FACTOR times the best of what
# chance alignment reaches on the same correspondences shuffled and what any distinct pose
# reaches on the real ones, plus VERDICT_GRAPH_MARGIN. "lrf" and "3point": the inliers beat
# chance by VERDICT_FACTOR and VERDICT_MARGIN, or the overlap stands out from the other
# hypotheses' by VERDICT_CONTRAST.
VERDICT_FACTOR = 2.0
VERDICT_MARGIN = 3
VERDICT_CONTRAST = 1.6
VERDICT_FITNESS = 0.2
VERDICT_GRAPH_FACTOR = 3.0
VERDICT_GRAPH_MARGIN = 3
VERDICT_GRAPH_FITNESS = 0.05
CHANCE_SHUFFLES = 4
# A hypothesis is distinct from the winner (a rival) when their rotations differ by more than
# RIVAL_DEG degrees or their translations (at the source centroid) by more than the support
# radius.
RIVAL_DEG = 10.0


class Evidence(NamedTuple):
  """What `verdict` decides on (all counts are correspondences within the inlier distance).

  n_inliers: inliers of the refitted winner.
  chance_inliers: the most inliers any hypothesis reaches on the correspondences shuffled.
  rival_inliers: the most inliers outside the winner's of a hypothesis distinct from the winner
    (`_rival_inliers`).
  fitness: fraction of the ICP's source points within icp_mr mr of the target after ICP.
  contrast: `overlap_contrast` of the verified hypotheses (0 when none were verified).
  estimator: the estimator that produced them.
  """

  n_inliers: int
  chance_inliers: int
  rival_inliers: int
  fitness: float
  contrast: float
  estimator: str


def overlap_contrast(fits: np.ndarray) -> float:
  """Best overlap score over the 99th percentile of all hypotheses' (0 without scores): a real
  overlap is found by few hypotheses and stands out; chance alignment (blobs, a mirror image, two
  objects) is as good as many other poses."""
  fits = np.asarray(fits, np.float64)
  if fits.size == 0:
    return 0.0
  return float(fits.max() / max(np.percentile(fits, 99), 1e-12))


def verdict(evidence: Evidence) -> tuple[bool, str]:
  """`Registration.success` and `.reason` from the evidence (module constants `VERDICT_*`).

  Returns:
    (success, reason): reason is a short sentence saying what decided.
  """
  e = evidence
  floor = VERDICT_GRAPH_FITNESS if e.estimator == "graph" else VERDICT_FITNESS
  if e.fitness < floor:
    return False, (f"not sure: only {e.fitness:.0%} of the source lies on the target after "
                   f"ICP (needs {floor:.0%})")
  if e.estimator == "graph":
    level = max(e.chance_inliers, e.rival_inliers)
    need = VERDICT_GRAPH_FACTOR * level + VERDICT_GRAPH_MARGIN
    if e.n_inliers >= need:
      return True, (f"{e.n_inliers} consistent correspondences; chance gives "
                    f"{e.chance_inliers}, the best distinct pose {e.rival_inliers}")
    which = "a distinct pose" if e.rival_inliers >= e.chance_inliers else "chance"
    return False, (f"not sure: {e.n_inliers} consistent correspondences, {which} gives {level} "
                   f"(needs {need:g})")
  if e.n_inliers >= VERDICT_FACTOR * e.chance_inliers + VERDICT_MARGIN:
    return True, f"{e.n_inliers} inliers; chance gives {e.chance_inliers}"
  if e.contrast >= VERDICT_CONTRAST:
    return True, (f"the overlap stands out from the other hypotheses' (the best is "
                  f"{e.contrast:.2f}x their 99th percentile)")
  return False, (f"not sure: {e.n_inliers} inliers, chance gives {e.chance_inliers}, and the "
                 f"best overlap is only {e.contrast:.2f}x the other hypotheses' 99th "
                 f"percentile (needs {VERDICT_CONTRAST:g}x)")
