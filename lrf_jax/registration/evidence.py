"""Whether `register` believes its result: the evidence it gathered and the thresholds.

One verdict for every estimator and option: the winner must be well supported (inliers far above
what chance alignment and any distinct pose reach, counted on the same correspondences and with
the same hypotheses whatever produced the winner), the aligned clouds must overlap, the
overlap must pin the pose down (no free direction), and the pose returned must be the pose that
support was counted at (not a distinct one); `decide` says which test decided, in words and as a
`REASON_CODES` code.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# The verdict (`decide`). ICP pairs at least VERDICT_GRAPH_FITNESS of the source; the winner's
# inliers reach VERDICT_GRAPH_FACTOR times the best of what chance alignment reaches on the same
# correspondences shuffled and what any distinct pose reaches on the real ones, plus
# VERDICT_GRAPH_MARGIN. The rule is the same for every estimator (it was "graph"'s alone).
VERDICT_GRAPH_FACTOR = 3.0
VERDICT_GRAPH_MARGIN = 3
VERDICT_GRAPH_FITNESS = 0.05
# The rule of estimator="lrf" and "3point" before the verdict was one for all (inliers over
# chance by VERDICT_FACTOR and VERDICT_MARGIN, or an overlap contrast of VERDICT_CONTRAST, and a
# fitness of VERDICT_FITNESS): it claimed blobs and mirror images. No longer read by `decide`;
# kept because 0.7 forwarded these names.
VERDICT_FACTOR = 2.0
VERDICT_MARGIN = 3
VERDICT_CONTRAST = 1.6
VERDICT_FITNESS = 0.2
CHANCE_SHUFFLES = 4
# A hypothesis is distinct from the winner (a rival) when their rotations differ by more than
# RIVAL_DEG degrees or their translations (at the source centroid) by more than the support
# radius.
RIVAL_DEG = 10.0
# The overlap leaves the pose free (`constraint_spectrum`) when the weakest direction of the
# point-to-plane constraints holds less than DEGENERATE_RATIO of the strongest's: a plane slid
# within itself, a sphere or cylinder turned about its centre or axis.
DEGENERATE_RATIO = 0.01
# A "not sure" whose best distinct pose explains at least AMBIGUOUS_SHARE of the winner's inliers
# is ambiguous: `next_step` does not suggest more keypoints for it.
AMBIGUOUS_SHARE = 0.8

# `Registration.reason_code`: what decided the verdict.
REASON_CODES = {
    "claimed": "success: the winner's support is far above chance and every distinct pose's",
    "low_overlap": "not sure: too little of the source lies on the target after ICP",
    "degenerate": "not sure: the overlap leaves a direction of motion free (a plane, a sphere, "
                  "an axis of symmetry)",
    "chance": "not sure: chance alignment of the same correspondences reaches nearly as many",
    "rival": "not sure: a distinct pose explains nearly as many other correspondences",
    "moved": "not sure: ICP moved the pose to a distinct one from the winner whose support was "
             "counted",
    "no_hypothesis": "not sure: no two correspondences agree, so there was no hypothesis",
}


class Evidence(NamedTuple):
  """What `decide` reads (all counts are correspondences within the inlier distance, on the
  evidence correspondences: the default matching's, whatever option chose the hypotheses' own).

  n_inliers: inliers of the refitted winner.
  chance_inliers: the most inliers any hypothesis of the compatibility graph reaches on the
    correspondences shuffled.
  rival_inliers: the most inliers outside the winner's of a hypothesis distinct from the winner
    (`_rival_inliers`).
  fitness: fraction of the ICP's source points within icp_mr mr of the target after ICP.
  contrast: `overlap_contrast` of the verified hypotheses (0 when none were verified; reported,
    not decisive).
  estimator: the estimator that produced the winner.
  degeneracy: `constraint_spectrum`'s ratio of the overlap (1: fully constrained).
  free_direction: the least constrained motion, in words ("" when not computed).
  effort: what the evidence leaves to try (the next step `decide` names): "fast" one pass
    (`effort="normal"` or `"high"` may follow), "normal" one pass of `register_scans` (`"high"`
    may follow), "high" the pooled seeds, or a pass the pooled one follows (nothing).
  from_init: the pose was refined from `register`'s `init`, not chosen among the hypotheses.
  moved_deg: the rotation angle (degrees) between the pose returned and the pose whose
    inliers `n_inliers` counts (the winner refitted on its inliers; 0 for an init, whose
    inliers are counted at the pose returned).
  moved_distance: how far apart the two put the evidence correspondences' source centroid
    (cloud units).
  distinct_distance: the distance beyond which two poses are distinct (the support radius, as
    for rivals; inf: not measured).
  """

  n_inliers: int
  chance_inliers: int
  rival_inliers: int
  fitness: float
  contrast: float
  estimator: str
  degeneracy: float = 1.0
  free_direction: str = ""
  effort: str = "normal"
  from_init: bool = False
  moved_deg: float = 0.0
  moved_distance: float = 0.0
  distinct_distance: float = float("inf")


class Verdict(NamedTuple):
  """`decide`'s answer: `Registration.success`, `.reason` and `.reason_code`."""

  success: bool
  reason: str
  code: str


def overlap_contrast(fits: np.ndarray) -> float:
  """Best overlap score over the 99th percentile of all hypotheses' (0 without scores): a real
  overlap is found by few hypotheses and stands out; chance alignment (blobs, a mirror image, two
  objects) is as good as many other poses."""
  fits = np.asarray(fits, np.float64)
  if fits.size == 0:
    return 0.0
  return float(fits.max() / max(np.percentile(fits, 99), 1e-12))


def constraint_spectrum(points: np.ndarray, normals: np.ndarray) -> tuple[float, str]:
  """How well point-to-plane pairs pin a rigid motion down: the 6 x 6 normal matrix of the
  point-to-plane residuals (rows [(p - c) x n / L, n], c the points' centroid, L their RMS
  distance from it, so rotations and translations weigh alike), its smallest eigenvalue over its
  largest, and the eigenvector of the smallest in words.

  Args:
    points: (k, 3) points of the overlap (in any one frame).
    normals: (k, 3) unit surface normals there (NaN rows are skipped).

  Returns:
    (ratio, direction): ratio in [0, 1] (0: a motion that no pair resists; 1 with fewer than 6
    usable pairs: nothing to say), and e.g. "translation along (0.00, 0.00, 1.00)" or
    "rotation about (0.00, 1.00, 0.00)" (the dominant half of the eigenvector).
  """
  p = np.asarray(points, np.float64)
  n = np.asarray(normals, np.float64)
  ok = np.all(np.isfinite(n), axis=1) & np.all(np.isfinite(p), axis=1)
  p, n = p[ok], n[ok]
  if len(p) < 6:
    return 1.0, ""
  c = p.mean(axis=0)
  lever = float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1))))
  if lever <= 0:
    return 0.0, "rotation about any axis"
  rows = np.concatenate([np.cross(p - c, n) / lever, n], axis=1)
  h = rows.T @ rows / len(rows)
  w, v = np.linalg.eigh(h)
  if w[-1] <= 0:
    return 0.0, "any motion"
  vec = v[:, 0]
  rot, trans = vec[:3], vec[3:]
  kind, axis = (("translation along", trans) if np.linalg.norm(trans) >= np.linalg.norm(rot)
                else ("rotation about", rot))
  axis = axis / max(float(np.linalg.norm(axis)), 1e-30)
  axis = axis * (1.0 if axis[np.argmax(np.abs(axis))] >= 0 else -1.0)
  words = f"{kind} ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f})"
  return float(max(w[0], 0.0) / w[-1]), words


def poses_apart(a: np.ndarray, b: np.ndarray, point: np.ndarray) -> tuple[float, float]:
  """How far apart two poses are, as the rival test measures it: the angle of a's rotation
  relative to b's (degrees) and the distance between where they put `point` (cloud units).

  Args:
    a, b: (4, 4) rigid transforms.
    point: (3,) a point of the source (the evidence correspondences' centroid).
  """
  a = np.asarray(a, np.float64)
  b = np.asarray(b, np.float64)
  p = np.asarray(point, np.float64)
  cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
  deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
  return deg, float(np.linalg.norm((a[:3, :3] - b[:3, :3]) @ p + a[:3, 3] - b[:3, 3]))


def distinct(deg: float, distance: float, radius: float) -> bool:
  """Whether two poses `poses_apart` measured `deg` degrees and `distance` apart are distinct,
  as a rival is from the winner: more than RIVAL_DEG degrees or `radius` (the support radius,
  cloud units) apart."""
  return deg > RIVAL_DEG or distance > radius


def distinct_from(rs: np.ndarray, ts: np.ndarray, r: np.ndarray, t: np.ndarray, radius: float,
                  point: np.ndarray | None = None) -> np.ndarray:
  """`distinct`, vectorised: whether each pose (rs[h], ts[h]) is distinct from (r, t), its
  rotation more than RIVAL_DEG degrees from `r` or the two poses more than `radius` apart at
  `point` (the same coordinates as the poses; None: the origin, the centroid of centred
  coordinates).

  Args:
    rs, ts: (H, 3, 3) rotations and (H, 3) translations.
    r, t: (3, 3) and (3,), the pose compared with.
    radius: the support radius, in the poses' units.
    point: (3,) where the translations are compared, or None.

  Returns:
    (H,) bool.
  """
  rs = np.asarray(rs, np.float64).reshape(-1, 3, 3)
  r = np.asarray(r, np.float64)
  cos = (np.einsum("hij,ij->h", rs, r) - 1.0) / 2.0
  gap = np.asarray(ts, np.float64).reshape(-1, 3) - np.asarray(t, np.float64)
  if point is not None:
    gap = gap + np.einsum("hij,j->hi", rs - r, np.asarray(point, np.float64))
  return (cos < np.cos(np.radians(RIVAL_DEG))) | (np.linalg.norm(gap, axis=1) > radius)


def exact_number(value: float) -> str:
  """`value` in full: an integer-valued number without a decimal point or an exponent
  ("1200003"), any other its shortest exact form (`repr`)."""
  x = float(value)
  return str(int(x)) if x.is_integer() else repr(x)


def shown_apart(value: float, floor: float, kind: str) -> tuple[str, str]:
  """`value` and the threshold `floor` it was compared with, printed with as many digits as it
  takes for the two to read differently (whenever they differ): kind "%" as percentages (one
  decimal more at a time from none: 0.0496 and 0.05 read "4.96%" and "5.00%"), "g" with
  significant digits (two at least, trailing zeros dropped: 0.009996 and 0.01 read "0.009996"
  and "0.01").

  Returns:
    (value, floor) as text.
  """
  if kind == "%":
    fmt = [f"{{:.{d}%}}" for d in range(18)]
  else:
    fmt = [f"{{:.{d}g}}" for d in range(2, 19)]
  for f in fmt:
    a, b = f.format(value), f.format(floor)
    if a != b:
      break
  return a, b


def decide(evidence: Evidence) -> Verdict:
  """`Registration.success`, `.reason` and `.reason_code` from the evidence (module constants).

  In order: "low_overlap" (ICP pairs under VERDICT_GRAPH_FITNESS of the source),
  "degenerate" (the overlap leaves a motion free, `constraint_spectrum` under
  DEGENERATE_RATIO), "moved" (the pose returned and the pose the inliers were counted at are
  `distinct`, as a rival is: the support is then another pose's), then "claimed" when the
  inliers reach VERDICT_GRAPH_FACTOR x the larger of chance and the best distinct pose +
  VERDICT_GRAPH_MARGIN, else "rival" or "chance" (whichever is larger; "rival" on a tie). The
  same rule for every estimator.
  """
  e = evidence
  floor = VERDICT_GRAPH_FITNESS
  if e.fitness < floor:
    shown, needed = shown_apart(e.fitness, floor, "%")
    return Verdict(False, f"not sure: only {shown} of the source lies on the target after ICP "
                          f"(needs {needed})", "low_overlap")
  if e.degeneracy < DEGENERATE_RATIO:
    free = f" ({e.free_direction})" if e.free_direction else ""
    shown, needed = shown_apart(e.degeneracy, DEGENERATE_RATIO, "g")
    return Verdict(False, f"not sure: the overlap leaves a motion free{free}; its weakest "
                          f"direction holds {shown} of the strongest's (needs {needed})",
                   "degenerate")
  if distinct(e.moved_deg, e.moved_distance, e.distinct_distance):
    return Verdict(False, f"not sure: the {e.n_inliers} consistent correspondences support a pose "
                          f"{e.moved_deg:.1f} deg and {e.moved_distance:.3g} from the one returned, "
                          f"a distinct pose (beyond {RIVAL_DEG:g} deg or "
                          f"{e.distinct_distance:.3g})", "moved")
  level = max(e.chance_inliers, e.rival_inliers)
  need = VERDICT_GRAPH_FACTOR * level + VERDICT_GRAPH_MARGIN
  if e.n_inliers >= need:
    return Verdict(True, f"{e.n_inliers} consistent correspondences; chance gives "
                         f"{e.chance_inliers}, the best distinct pose {e.rival_inliers}",
                   "claimed")
  rival = e.rival_inliers >= e.chance_inliers
  which = "a distinct pose" if rival else "chance"
  step = next_step(e)
  return Verdict(False, f"not sure: {e.n_inliers} consistent correspondences, {which} gives "
                        f"{level} (needs {exact_number(need)})" + (f"; {step}" if step else ""),
                 "rival" if rival else "chance")


def next_step(evidence: Evidence) -> str:
  """What may settle a "not sure" for lack of support (`decide`'s "chance" and "rival"), or ""
  where nothing `register` can do would: more keypoints and pooled seeds, then a pass at twice
  the working resolution (`effort="high"`, or the default `"normal"` after `"fast"`) unless
  they were used or a distinct pose explains nearly as many correspondences as the winner (at
  least AMBIGUOUS_SHARE of them: two copies of an object, which more correspondences find
  again). An init is not named: it is judged on the same evidence (`register(..., init=T)`),
  so it settles nothing the evidence left open."""
  if (evidence.effort == "high"
      or evidence.rival_inliers >= AMBIGUOUS_SHARE * evidence.n_inliers):
    return ""
  more = "effort='normal' or 'high'" if evidence.effort == "fast" else "effort='high'"
  return (f"{more} (more keypoints, pooled seeds, then a coarser pass where mr is measured) "
          "may settle it")


def verdict(evidence: Evidence) -> tuple[bool, str]:
  """`decide`'s success and reason (without the code).

  Returns:
    (success, reason): reason is a short sentence saying what decided.
  """
  d = decide(evidence)
  return d.success, d.reason
