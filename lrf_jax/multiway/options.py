"""`MultiwayOptions`: every option of `register_all` and its default, held once.

`MultiwayOptions` holds two groups: `pairs`, the `RegisterOptions` of every pairwise registration
(its `mr`, `seed`, `icp_mr` and `voxel_size` are the whole job's: the candidate pairs, the pose
graph and the joint ICP read them too), and `graph`, the `GraphOptions` of the candidate pairs,
the pose graph and the joint ICP. As for `RegisterOptions`, a field keeps one flat name
(`FIELDS`): `register_all(scans, neighbors=2, n_keypoints=2000)` and
`MultiwayOptions().with_overrides(...)` replace fields of their group, `as_dict()` reads them
back. The per-scan sensor positions are `register_all`'s `viewpoints`, not options: the pair
options' `source_viewpoint` and `target_viewpoint` are not fields here. The multiway command line
derives its flags from the fields (`lrf_jax.cli.options.add_option_flags`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from lrf_jax.multiway.candidates import ALL_PAIRS_MAX
from lrf_jax.registration import options as register_options
from lrf_jax.registration.options import OptionGroup, RegisterOptions, option_field

# An edge whose RMS point residual under the optimised poses exceeds this many mr is rejected.
REJECT_MR = 5.0


def check_counts(**counts: Any) -> None:
  """Raise a ValueError naming the first of `counts` (name: value) that is not a non-negative
  integer (`register_all`'s all_pairs_max, neighbors, loop_candidates, refine_iterations)."""
  for name, val in counts.items():
    if isinstance(val, (bool, np.bool_)) or not isinstance(val, (int, np.integer)) or val < 0:
      raise ValueError(f"{name}: expected a non-negative integer, got {val!r}")


@dataclasses.dataclass(frozen=True)
class GraphOptions(OptionGroup):
  """The candidate pairs, the pose graph and the joint ICP."""

  all_pairs_max: int = option_field(
      ALL_PAIRS_MAX, "register every pair up to this many scans; beyond, neighbors in the given "
      "order plus loop-closure candidates")
  neighbors: int = option_field(
      1, "beyond --all-pairs-max scans, pairs with this many next scans in the given order")
  loop_candidates: int = option_field(
      3, "beyond --all-pairs-max scans, this many loop-closure candidates per scan (D2 "
      "signature)")
  reject_mr: float = option_field(REJECT_MR, "reject edges whose residual exceeds this many mr")
  robust_mr: float = option_field(
      1.0, "scale of the Cauchy loss of the pose graph and the joint ICP, in mr")
  refine: bool = option_field(True, "the joint ICP of every scan after the pose graph")
  refine_iterations: int = option_field(10, "rounds of the joint ICP at most")

  def check(self) -> None:
    """Raise a ValueError naming the first field `register_all` would refuse."""
    for name in ("reject_mr", "robust_mr"):
      val = getattr(self, name)
      if not (isinstance(val, (int, float)) and np.isfinite(val) and val > 0):
        raise ValueError(f"{name}: expected a positive number of mesh resolutions, got {val!r}")
    check_counts(all_pairs_max=self.all_pairs_max, neighbors=self.neighbors,
                 loop_candidates=self.loop_candidates, refine_iterations=self.refine_iterations)
    if not isinstance(self.refine, (bool, np.bool_)):
      raise ValueError(f"refine: expected True or False, got {self.refine!r}")


# The pair options that are not options of a job: each scan's sensor position is `viewpoints`.
PER_SCAN = ("source_viewpoint", "target_viewpoint")
GRAPH_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(GraphOptions))
PAIR_FIELDS: tuple[str, ...] = tuple(f for f in register_options.FIELDS if f not in PER_SCAN)
# Every flat field: the pair options' (those the job shares first), then the graph's.
FIELDS: tuple[str, ...] = PAIR_FIELDS + GRAPH_FIELDS


def option_fields() -> tuple[dataclasses.Field, ...]:
  """Every flat field of `MultiwayOptions` as its group's `dataclasses.Field`, in `FIELDS`
  order."""
  pair = [f for f in register_options.option_fields() if f.name not in PER_SCAN]
  return (*pair, *dataclasses.fields(GraphOptions))


@dataclasses.dataclass(frozen=True, init=False)
class MultiwayOptions:
  """The options of `register_all`: `pairs` (every pairwise registration's, and the job's mr,
  seed, icp_mr and voxel_size) and `graph` (the candidate pairs, pose graph and joint ICP).

  Built from groups, flat fields or both (`MultiwayOptions(neighbors=2, n_keypoints=2000)`);
  checked on construction; a flat field reads as an attribute too (`options.neighbors`).

  Raises:
    TypeError: an unknown field (or a per-scan one), or a group of the wrong class.
    ValueError: naming the first field that `register_all` would refuse.
  """

  pairs: RegisterOptions
  graph: GraphOptions

  def __init__(self, pairs: RegisterOptions | None = None, graph: GraphOptions | None = None,
               **fields: Any) -> None:
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
      hint = "; each scan's sensor position is register_all's viewpoints" if set(
          unknown) & set(PER_SCAN) else ""
      raise TypeError(f"register_all: unknown option {unknown[0]!r}{hint}; expected one of "
                      f"{list(FIELDS)}")
    for name, group, cls in (("pairs", pairs, RegisterOptions), ("graph", graph, GraphOptions)):
      if group is not None and not isinstance(group, cls):
        raise TypeError(f"{name}: expected a {cls.__name__} or None, got "
                        f"{type(group).__name__}")
    graph_kw = {k: v for k, v in fields.items() if k in GRAPH_FIELDS}
    pair_kw = {k: v for k, v in fields.items() if k not in GRAPH_FIELDS}
    graph = GraphOptions() if graph is None else graph
    pairs = register_options.DEFAULTS if pairs is None else pairs
    object.__setattr__(self, "graph", graph.with_overrides(**graph_kw))
    object.__setattr__(self, "pairs", pairs.with_overrides(**pair_kw))

  if not TYPE_CHECKING:  # flat reads for users; the package reads the groups (mypy checks it)
    def __getattr__(self, name: str) -> Any:
      if name in GRAPH_FIELDS:
        return getattr(self.graph, name)
      if name in PAIR_FIELDS:
        return getattr(self.pairs, name)
      raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

  def with_overrides(self, **overrides: Any) -> MultiwayOptions:
    """A checked copy with `overrides` (flat field names, or `pairs` and `graph`) replaced.

    Raises:
      TypeError: a name that is not an option of `register_all`.
      ValueError: a value `register_all` would refuse.
    """
    return dataclasses.replace(self, **overrides) if overrides else self

  def as_dict(self) -> dict[str, Any]:
    """The options as {field: value}, flat, in `FIELDS` order."""
    flat = {**self.pairs.as_dict(), **self.graph.as_dict()}
    return {name: flat[name] for name in FIELDS}


def resolve(options: MultiwayOptions | None, overrides: dict[str, Any]) -> MultiwayOptions:
  """`options` (None: `DEFAULTS`) with `overrides` replaced, checked.

  Raises:
    TypeError: `options` that is not a `MultiwayOptions`, or an unknown override.
    ValueError: a value `register_all` would refuse.
  """
  return register_options.resolve_as(MultiwayOptions, DEFAULTS, options, overrides)


DEFAULTS = MultiwayOptions()
