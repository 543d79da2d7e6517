"""What `register_all` returns: the scans' poses and every candidate pair's edge."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np

__all__ = ["MultiwayEdge", "MultiwayResult"]

# `MultiwayResult.summary` gives its reason for this many scans left out, names the others.
SUMMARY_LEFT_OUT = 10


@dataclasses.dataclass(frozen=True)
class MultiwayEdge:
  """One candidate pair and what became of it.

  Attributes:
    i: the source scan (moved).
    j: the target scan.
    transform: (4, 4) float64, the pairwise estimate mapping scan i into scan j's frame (NaN
      when the pair could not be registered).
    verdict: "success", "not sure" (`Registration.success` False) or "error" (no estimate: the
      registration raised a ValueError or built no hypothesis, `Registration.estimated`).
    reason: the pairwise verdict's reason, or the error message.
    reason_code: the pairwise verdict's `Registration.reason_code` ("claimed", "rival", ...;
      "error" when the pair could not be registered; "" when `pairwise` gives none).
    n_inliers: coarse inliers of the pairwise estimate.
    overlap: its estimated overlap (fraction of scan i on scan j after ICP).
    rmse: its ICP RMS distance, cloud units.
    residual_mr: RMS disagreement of the edge with the final poses at its overlap points, in mr
      (inf when its two scans are not both in the model).
    accepted: whether the pose graph kept it.
  """

  i: int
  j: int
  transform: np.ndarray
  verdict: str
  reason: str
  n_inliers: int
  overlap: float
  rmse: float
  residual_mr: float
  accepted: bool
  reason_code: str = ""

  @property
  def outcome(self) -> str:
    """What became of the pair: "accepted" (a "success" edge the graph kept),
    "accepted_not_sure" (a "not sure" edge the graph backed and kept), "rejected" (a "success"
    edge the graph rejected: it contradicts the other edges), "unused" (a "not sure" edge the
    graph did not use) or "error" (no estimate)."""
    if self.verdict == "error":
      return "error"
    if self.accepted:
      return "accepted" if self.verdict == "success" else "accepted_not_sure"
    return "rejected" if self.verdict == "success" else "unused"


@dataclasses.dataclass(frozen=True)
class MultiwayResult:
  """What `register_all` returns.

  Attributes:
    names: (n,) scan names (file stems, or "scan<k>").
    poses: (n, 4, 4) float64; pose k maps scan k into the reference scan's frame; NaN for the
      scans left out.
    in_model: (n,) bool, the scans in the model.
    reference: index of the reference scan (the first scan of the model).
    edges: every candidate pair, in the order registered.
    mr: the mesh resolution used as the unit (cloud units).
    seconds: wall time of the call.
    timings: seconds per stage: "load", "pairwise", "graph", "refine".
    confident: (n,) bool, the scans in the model linked to the reference by accepted "success"
      edges alone; a scan in the model whose placement rests on a "not sure" edge is False
      (`placed_not_sure`). None: every scan in the model counts as confident.
    work: what the pairwise stage did, its passes summed (the default's second pass,
      `effort="high"` on the "not sure" pairs between the first graph's components, describes
      each of their scans once more and registers those pairs again): "scans_described" (each
      at most once a pass), "pairs_registered" (registrations this call) and "pairs_resumed"
      (registrations read from `state_dir`).
  """

  names: tuple[str, ...]
  poses: np.ndarray
  in_model: np.ndarray
  reference: int
  edges: tuple[MultiwayEdge, ...]
  mr: float
  seconds: float
  timings: dict = dataclasses.field(default_factory=dict)
  confident: np.ndarray | None = None
  work: dict = dataclasses.field(default_factory=dict)

  @property
  def left_out(self) -> list[str]:
    """Names of the scans not in the model."""
    return [n for n, m in zip(self.names, self.in_model) if not m]

  @property
  def placed_not_sure(self) -> list[str]:
    """Names of the scans in the model placed only through "not sure" edges (their link to the
    reference rests on at least one): check them."""
    if self.confident is None:
      return []
    return [n for n, m, c in zip(self.names, self.in_model, self.confident) if m and not c]

  def summary(self) -> str:
    """A few lines a person reads: the scans placed (and those whose place rests on a "not
    sure" edge), each scan left out and why, what became of the pairs (accepted, accepted
    although "not sure", rejected, unused, errors), the residuals of the accepted edges under
    the final poses when there are any, the work of the pairwise stage and the time.

    Returns:
      The text, lines joined by newlines (no trailing newline).
    """
    n, placed = len(self.names), int(np.sum(self.in_model))
    lines = [f"{placed} of {n} scans placed, in the frame of {self.names[self.reference]} "
             f"(mr = {self.mr:.6g})"]
    if self.placed_not_sure:
      lines.append(f"placed only through \"not sure\" edges (check them; edges.tsv's placement): "
                   f"{', '.join(self.placed_not_sure)}")
    left = [k for k in range(n) if not self.in_model[k]]
    for k in left[:SUMMARY_LEFT_OUT]:
      lines.append(f"left out: {self.names[k]}: {self._why_left_out(k)}")
    if len(left) > SUMMARY_LEFT_OUT:
      lines.append(f"left out: {len(left) - SUMMARY_LEFT_OUT} more "
                   f"({', '.join(self.names[k] for k in left[SUMMARY_LEFT_OUT:])})")
    count = Counter(e.outcome for e in self.edges)
    lines.append(f"edges: {count['accepted'] + count['accepted_not_sure']} of "
                 f"{len(self.edges)} pairs accepted ({count['accepted']} \"success\", "
                 f"{count['accepted_not_sure']} \"not sure\" that the graph backs); rejected: "
                 f"{count['rejected']} \"success\" (they contradict the others), "
                 f"{count['unused']} \"not sure\" (unused); {count['error']} pairs could not "
                 "be registered")
    kept = [e for e in self.edges if e.accepted and np.isfinite(e.residual_mr)]
    if kept:
      worst = max(kept, key=lambda e: e.residual_mr)
      lines.append(f"residuals of the accepted edges under the final poses: median "
                   f"{np.median([e.residual_mr for e in kept]):.3g} mr, largest "
                   f"{worst.residual_mr:.3g} mr ({self.names[worst.i]} - {self.names[worst.j]})")
    if self.work:
      lines.append(f"{self.work.get('pairs_registered', 0)} pairs registered, "
                   f"{self.work.get('pairs_resumed', 0)} read from earlier runs' records; "
                   f"{self.work.get('scans_described', 0)} scans described")
    stages = ", ".join(f"{k} {v:.2f}" for k, v in self.timings.items() if v >= 0.005)
    lines.append(f"time {self.seconds:.2f} s" + (f" ({stages})" if stages else ""))
    return "\n".join(lines)

  def _why_left_out(self, k: int) -> str:
    """Why scan k is not in the model, from its edges."""
    mine = [e for e in self.edges if k in (e.i, e.j)]
    if not mine:
      return "no pair with it was registered"
    group = sorted({self.names[e.j if e.i == k else e.i] for e in mine if e.accepted})
    if group:
      return (f"its accepted edges join it only to scans left out too ({', '.join(group)}): "
              "a group not linked to the model")
    count = Counter(e.outcome for e in mine)
    parts = [f"{count['rejected']} \"success\" edges rejected (they contradict the model)",
             f"{count['unused']} \"not sure\" edges the graph did not back",
             f"{count['error']} pairs could not be registered"]
    return "no accepted edge: " + ", ".join(p for p in parts if not p.startswith("0 "))

  def __repr__(self) -> str:
    """One line: scans placed, edges accepted and time (the arrays are attributes; `summary()`
    says more)."""
    return (f"MultiwayResult({int(np.sum(self.in_model))}/{len(self.names)} scans placed, "
            f"{sum(e.accepted for e in self.edges)}/{len(self.edges)} edges accepted, "
            f"{self.seconds:.2f} s; .poses, .summary())")
