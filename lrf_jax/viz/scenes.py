"""What the viewer shows, as plain data (no viser): a multiway model (every scan at its pose,
one colour each, the graph's edges with their verdicts) or registered pairs (a source, a target
and the transform between them), each cloud thinned for display.

`model_scene` builds a model from `register_all`'s result and its scans, `pair_scene` a pair
from two clouds and a transform; `lrf_jax.viz.folders` builds both from output folders.
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any
from collections.abc import Sequence

import numpy as np

if TYPE_CHECKING:
  from lrf_jax.multiway.result import MultiwayResult

__all__ = ["EDGE_COLOURS", "EDGE_KINDS", "MAX_POINTS", "PAIR_COLOURS", "ModelScene",
           "PairScene", "Thinning", "as_points", "edge_kind", "model_scene", "pair_scene",
           "registration_verdict", "thin", "thinning_note"]

# Points shown per scan at most (a seeded sample of a larger scan; `thin`).
MAX_POINTS = 200_000
# The three kinds of a multiway edge and their colours (uint8 RGB; none is a scan colour).
EDGE_KINDS = ("accepted", "accepted, not sure", "rejected")
EDGE_COLOURS = {"accepted": (0, 200, 90), "accepted, not sure": (250, 200, 0),
                "rejected": (235, 0, 60)}
# A pair's clouds: the target, the source where it is (before) and moved by the transform.
PAIR_COLOURS = {"target": (31, 119, 180), "source (registered)": (255, 127, 14),
                "source (before)": (148, 103, 189)}


@dataclasses.dataclass(frozen=True)
class Thinning:
  """How many points a cloud had and how many are shown (`thin`)."""
  name: str
  had: int
  shown: int


def thin(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
  """At most `max_points` of `points` (a seeded sample without replacement, in the cloud's
  order); `points` itself when it has no more."""
  if len(points) <= max_points:
    return points
  rng = np.random.default_rng(seed)
  keep = np.sort(rng.choice(len(points), size=max_points, replace=False))
  return points[keep]


def thinning_note(thinned: Sequence[Thinning], max_points: int) -> str | None:
  """The one line that says which clouds were thinned for display (None: none was)."""
  if not thinned:
    return None
  shown = ", ".join(f"{t.name} {t.had:,} -> {t.shown:,}" for t in thinned[:5])
  more = f" and {len(thinned) - 5} more" if len(thinned) > 5 else ""
  return (f"note: thinned for display to at most {max_points:,} points a cloud (a seeded "
          f"sample; the files are unchanged): {shown}{more}")


def as_points(cloud: Any, label: str) -> np.ndarray:
  """A cloud given as a path (any format `lrf_jax.io.read_cloud` reads), a `Cloud` or object
  with `.points`, or an (n, 3) array, as (n, 3) float64.

  Raises:
    FileNotFoundError: a missing file.
    ValueError: an unreadable file, or not (n, 3) finite numbers (the message names `label`).
  """
  from lrf_jax.io.reader import read_cloud
  from lrf_jax.io.validation import check_points
  if isinstance(cloud, (str, os.PathLike)):
    return read_cloud(cloud).points
  points = getattr(cloud, "points", cloud)
  return check_points(np.asarray(points, np.float64), label)


@dataclasses.dataclass(frozen=True)
class ModelScene:
  """A multiway model ready to show.

  Attributes:
    names: (n,) every scan's name.
    points: (n,) each scan's points in the model's frame (thinned), None for a scan left out.
    colours: (n, 3) uint8, one colour per scan (merged.ply's, `scan_colours`).
    edges: (source, target, kind) of every edge whose two scans are in the model, kind one of
      `EDGE_KINDS`.
    edge_counts: how many edges of each kind the graph has (all of them, also those with a
      scan left out).
    thinned: the scans shown thinned.
    title: what the model is (a folder, "register_all's result").
  """
  names: tuple[str, ...]
  points: tuple[np.ndarray | None, ...]
  colours: np.ndarray
  edges: tuple[tuple[int, int, str], ...]
  edge_counts: dict[str, int]
  thinned: tuple[Thinning, ...] = ()
  title: str = ""

  @property
  def left_out(self) -> list[str]:
    """The names of the scans not in the model."""
    return [n for n, p in zip(self.names, self.points) if p is None]

  def centroids(self) -> np.ndarray:
    """(n, 3) each scan's centroid (NaN for a scan left out)."""
    return np.array([np.full(3, np.nan) if p is None else p.mean(axis=0) for p in self.points])


@dataclasses.dataclass(frozen=True)
class PairScene:
  """A source, a target and the transform between them, ready to show.

  Attributes:
    name: the pair's name ("pair", or a batch item's name).
    source: (m, 3) the source's points where they are (thinned).
    target: (k, 3) the target's points (thinned).
    transform: (4, 4) maps the source onto the target; None: none is known.
    verdict: one line on the registration (empty when none is known).
    thinned: the clouds shown thinned.
  """
  name: str
  source: np.ndarray
  target: np.ndarray
  transform: np.ndarray | None
  verdict: str = ""
  thinned: tuple[Thinning, ...] = ()

  def registered(self) -> np.ndarray | None:
    """The source moved by the transform (None without one)."""
    t = self.transform
    return None if t is None else self.source @ t[:3, :3].T + t[:3, 3]


def edge_kind(accepted: bool, verdict: str) -> str:
  """An edge's kind (`EDGE_KINDS`): rejected by the pose graph, or accepted with the pairwise
  verdict "success" or not ("not sure")."""
  if not accepted:
    return "rejected"
  return "accepted" if verdict == "success" else "accepted, not sure"


def model_scene(result: MultiwayResult, scans: Sequence[Any], *,
                max_points: int = MAX_POINTS, seed: int = 0) -> ModelScene:
  """A `register_all` result with its scans (paths, arrays or clouds, as given to it): each
  scan in the model moved by its pose and thinned to `max_points`.

  Raises:
    ValueError: not one scan per name of the result, or a scan that is not a cloud.
    FileNotFoundError: a scan's file is missing.
  """
  from lrf_jax.multiway.figures import scan_colours
  names = tuple(result.names)
  if len(scans) != len(names):
    raise ValueError(f"scans: expected the {len(names)} scans given to register_all, got "
                     f"{len(scans)}")
  points: list[np.ndarray | None] = []
  thinned = []
  for k, (scan, name) in enumerate(zip(scans, names)):
    if not result.in_model[k]:
      points.append(None)
      continue
    p = as_points(scan, f"scans[{k}] ({name})")
    pose = np.asarray(result.poses[k], np.float64)
    shown = thin(p, max_points, seed + k) @ pose[:3, :3].T + pose[:3, 3]
    if len(shown) < len(p):
      thinned.append(Thinning(name, len(p), len(shown)))
    points.append(shown)
  kinds = [edge_kind(e.accepted, e.verdict) for e in result.edges]
  edges = tuple((e.i, e.j, kind) for e, kind in zip(result.edges, kinds)
                if result.in_model[e.i] and result.in_model[e.j])
  return ModelScene(names, tuple(points), scan_colours(len(names)), edges,
                    {k: kinds.count(k) for k in EDGE_KINDS}, tuple(thinned),
                    "register_all's result")


def pair_scene(source: Any, target: Any, transform: Any = None, *, name: str = "pair",
               verdict: str = "", max_points: int = MAX_POINTS, seed: int = 0,
               labels: tuple[str, str] = ("source", "target")) -> PairScene:
  """Two clouds (paths, arrays or clouds) and an optional (4, 4) source->target transform,
  each cloud thinned to `max_points`.

  Raises:
    ValueError: a cloud that is not one, or a transform that is not a finite (4, 4) matrix.
    FileNotFoundError: a cloud's file is missing.
  """
  t = None
  if transform is not None:
    t = np.asarray(transform, np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
      raise ValueError(f"transform: expected a finite (4, 4) matrix, got shape {t.shape}"
                       + ("" if t.shape != (4, 4) else " with NaN or inf"))
  clouds, thinned = [], []
  for k, (cloud, label) in enumerate(zip((source, target), labels)):
    p = as_points(cloud, label)
    shown = thin(p, max_points, seed + k)
    if len(shown) < len(p):
      thinned.append(Thinning(label, len(p), len(shown)))
    clouds.append(shown)
  return PairScene(name, clouds[0], clouds[1], t, verdict, tuple(thinned))


def registration_verdict(registration: Any) -> str:
  """One line on a `Registration`: its verdict and reason."""
  success = bool(getattr(registration, "success", False))
  reason = " ".join(str(getattr(registration, "reason", "")).split())
  estimated = bool(getattr(registration, "estimated", True))
  head = "success" if success else ("no estimate" if not estimated else "not sure")
  return f"{head}: {reason}" if reason else head
