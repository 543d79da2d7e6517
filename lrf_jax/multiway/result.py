"""What `register_all` returns: the scans' poses and every candidate pair's edge."""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["MultiwayEdge", "MultiwayResult"]


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
    work: what the pairwise stage did: "scans_described" (each at most once),
      "pairs_registered" (this call) and "pairs_resumed" (read from `state_dir`).
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
