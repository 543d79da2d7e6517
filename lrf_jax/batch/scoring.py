"""A registration job scored against ground truth: each pair's transform against its `gt`
(a PAIRS.tsv column), right when both errors are within the criteria, and the job's counts of
right, claimed and false claims (claimed and not right).

The rotation error is the angle of R_estᵀ R_gt in degrees; the translation error the distance
between the two translations, in the clouds' units. A ground truth is read like an init: a 4 x 4
text file (or a .npy), its rotation block projected to the nearest rotation when within
`lrf_jax.registration.refine.INIT_PROJECT` of orthonormal (published ground truths are printed
with a few digits), refused beyond.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any
from collections.abc import Iterable

import numpy as np

__all__ = ["SCORE_COLUMNS", "Criteria", "Scoring", "counts", "errors", "parse_criteria"]

SCORE_COLUMNS = ("rotation_error_deg", "translation_error", "right")


@dataclasses.dataclass(frozen=True)
class Criteria:
  """When a transform is right: rotation error at most `max_rotation_deg` degrees and
  translation error at most `max_translation` (the clouds' units)."""
  max_rotation_deg: float
  max_translation: float

  def __post_init__(self) -> None:
    for name in ("max_rotation_deg", "max_translation"):
      val = getattr(self, name)
      if isinstance(val, bool) or not isinstance(val, (int, float)) or not np.isfinite(val) \
          or val <= 0:
        raise ValueError(f"criteria: {name}: expected a positive number, got {val!r}")


def parse_criteria(text: str) -> Criteria:
  """`DEG,DIST` (e.g. "15,0.3") as `Criteria`.

  Raises:
    ValueError: not two positive numbers separated by a comma.
  """
  parts = str(text).split(",")
  try:
    deg, dist = (float(p) for p in parts)
  except ValueError:
    raise ValueError(f"criteria: expected DEG,DIST (two positive numbers, e.g. 15,0.3), got "
                     f"{text!r}") from None
  return Criteria(deg, dist)


def errors(transform: Any, gt: np.ndarray) -> tuple[float, float]:
  """(rotation error in degrees, translation error in the clouds' units) of a (4, 4) estimate
  against a (4, 4) ground truth."""
  from lrf_jax.registration.errors import rotation_error_deg
  t = np.asarray(transform, np.float64)
  return (rotation_error_deg(t[:3, :3], gt[:3, :3]),
          float(np.linalg.norm(t[:3, 3] - gt[:3, 3])))


class Scoring:
  """The ground truths of a job's pairs (name -> path) and the criteria (None: errors only, no
  `right`). `row(name, row, rec)` adds `SCORE_COLUMNS` to a results.tsv row."""

  def __init__(self, gts: dict[str, str | None], criteria: Criteria | None):
    self.gts, self.criteria = gts, criteria
    self._read: dict[str, np.ndarray | str] = {}

  def _gt(self, path: str) -> np.ndarray | str:
    """The ground truth at `path`, or why it cannot be one (read once)."""
    if path not in self._read:
      from lrf_jax.batch.scan_frames import read_transform
      from lrf_jax.registration.refine import INIT_PROJECT
      try:
        with warnings.catch_warnings():
          warnings.simplefilter("ignore")
          self._read[path] = read_transform(path, "gt", project=INIT_PROJECT)
      except (ValueError, OSError) as e:
        self._read[path] = str(e)
    return self._read[path]

  def row(self, name: str, row: dict[str, Any], rec: dict[str, Any]) -> dict[str, Any]:
    """`row` with its scores: empty where the pair has no ground truth or no transform; a
    ground truth that cannot be read leaves them empty and says why in `error`."""
    out = dict(row, rotation_error_deg="", translation_error="", right="")
    path = self.gts.get(name)
    if path is None:
      return out
    gt = self._gt(path)
    if isinstance(gt, str):
      out["error"] = "; ".join(e for e in (row.get("error"), gt) if e)
      return out
    if rec.get("status") != "done" or rec.get("transform") is None:
      return out
    rot, trans = errors(rec["transform"], gt)
    out.update(rotation_error_deg=f"{rot:.6g}", translation_error=f"{trans:.6g}")
    if self.criteria is not None:
      right = rot <= self.criteria.max_rotation_deg and trans <= self.criteria.max_translation
      out["right"] = str(right)
    return out


def counts(rows: Iterable[dict[str, Any]]) -> dict[str, int]:
  """A job's counts from its results.tsv rows: "pairs", "done", "claimed" (success), "scored"
  (a `right` value), "right" and "false_claims" (claimed and not right)."""
  rows = list(rows)
  return dict(pairs=len(rows), done=sum(r.get("status") == "done" for r in rows),
              claimed=sum(r.get("success") == "True" for r in rows),
              scored=sum(r.get("right") in ("True", "False") for r in rows),
              right=sum(r.get("right") == "True" for r in rows),
              false_claims=sum(r.get("success") == "True" and r.get("right") == "False"
                               for r in rows))
