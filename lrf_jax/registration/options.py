"""`RegisterOptions`: every option of `register` and its default, held once, grouped by stage.

`RegisterOptions` holds one frozen dataclass per stage of the pipeline:

  inputs       `InputOptions`      mr, voxel_size, source_viewpoint, target_viewpoint, seed
  detection    `KeypointOptions`   keypoints (the detector), n_keypoints
  description  `DescribeOptions`   method, radius_mr, descriptor, weights
  matching     `MatchOptions`      n_correspondences, mutual, ratio
  hypotheses   `HypothesisOptions` estimator, iterations, inlier_mr, verify
  icp          `IcpOptions`        icp_iterations, icp_mr, icp_mode, icp_fine
  verdict      `VerdictOptions`    effort

Each stage of `stages.py` and `refine.py` reads its group. A field keeps one name everywhere (the
flat name, `FIELDS`), so the flat spelling stays a shortcut: `RegisterOptions(n_keypoints=2000)`,
`options.with_overrides(icp_mr=2.0)` and `register(source, target, n_keypoints=2000)` replace a
field of its group, `options.as_dict()` gives {field: value} and `options.icp_mr` reads one.

`register(source, target, options=None, **overrides)` reads its options from a `RegisterOptions`
(the module's `DEFAULTS` unless one is given) with `overrides` replacing fields; the command lines
(`lrf-register`, its multiway form, `lrf-batch register`) derive their flags, defaults and help
from the fields (`lrf_jax.cli.options.add_register_flags`), so a default changed here changes
everywhere. Every group checks its fields on construction (`check_values`); an instance is a
checked set of options, and it pickles as plain data for the data-set layer.

Lengths are in mr, the working resolution (`lrf_jax.geometry.resolution.registration_resolution`),
unless a field says otherwise.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from lrf_jax.checks import (is_count, is_positive, validate_seed, validate_viewpoint,
                            validate_voxel_size)
from lrf_jax.defaults import DEFAULT_METHOD, RADIUS_MR

ESTIMATORS = ("graph", "lrf", "3point")
KEYPOINTS = ("random", "iss")
ICP_MODES = ("point_to_plane", "point_to_point")
EFFORTS = ("normal", "fast", "high")
DEFAULT_DESCRIPTOR = "toldi"


def option_field(default: Any, help: str, *, flag: str | None = "",
                 choices: tuple | None = None, metavar: Any = None) -> Any:
  """A field of an options group: its default and what a command line shows for it (`flag`:
  the option's name when it is not the field's in kebab case; None: no flag)."""
  return dataclasses.field(default=default, metadata={
      "help": help, "flag": flag, "choices": choices, "metavar": metavar})


class OptionGroup:
  """What every options group shares: its fields checked on construction (`check`) and read
  back as {field: value} (`as_dict`)."""

  def __post_init__(self) -> None:
    self.check()

  def check(self) -> None:
    """Raise a ValueError naming the first field `register` would refuse (`check_values`)."""
    check_values(self.as_dict())

  def as_dict(self) -> dict[str, Any]:
    """The group's fields as {field: value}."""
    return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

  def with_overrides(self, **overrides: Any) -> Any:
    """A checked copy with `overrides` (this group's field names) replaced.

    Raises:
      TypeError: a name that is not a field of this group.
      ValueError: a value `register` would refuse.
    """
    names = [f.name for f in dataclasses.fields(self)]  # type: ignore[arg-type]
    unknown = sorted(set(overrides) - set(names))
    if unknown:
      raise TypeError(f"{type(self).__name__}: unknown option {unknown[0]!r}; expected one of "
                      f"{names}")
    return dataclasses.replace(self, **overrides) if overrides else self  # type: ignore[type-var]


@dataclasses.dataclass(frozen=True)
class InputOptions(OptionGroup):
  """Stage "prepare": the working resolution, thinning, the scans' sensor positions and the
  seed of every draw."""

  mr: float | None = option_field(
      None, "the working resolution in the clouds' units, the unit of every length (default: "
      "measured: the source's point spacing; on a raw, uneven cloud such as a LiDAR sweep the "
      "area-weighted median spacing; never finer than 1/300 of the cloud's extent; for clouds "
      "of different densities the coarser one)")
  voxel_size: float | None = option_field(
      None, "thin both clouds by voxel averaging first, voxels of this edge in the clouds' "
      "units (0: keep every point; default: thin a cloud far denser than the working "
      "resolution, such as a raw LiDAR sweep or a full-density fragment, at it)")
  source_viewpoint: tuple[float, float, float] | None = option_field(
      None, "sensor position of a single-view source scan, in its own coordinates (orients "
      "its normals and lrf_net_plus's z)", metavar=("X", "Y", "Z"))
  target_viewpoint: tuple[float, float, float] | None = option_field(
      None, "sensor position of a single-view target scan", metavar=("X", "Y", "Z"))
  seed: int = option_field(0, "seed of keypoints, neighbor subsamples and sampling")

  def __post_init__(self) -> None:
    self.check()
    for name in ("source_viewpoint", "target_viewpoint"):
      vp = getattr(self, name)
      if vp is not None:  # plain floats: hashable, and cheap to pickle
        object.__setattr__(self, name, tuple(float(v) for v in np.asarray(vp).ravel()))


@dataclasses.dataclass(frozen=True)
class KeypointOptions(OptionGroup):
  """Stage "prepare": the keypoints drawn on each cloud."""

  keypoints: str = option_field("random", "keypoint detector: seeded random points or ISS",
                           choices=KEYPOINTS)
  n_keypoints: int = option_field(3000, "keypoints per cloud (fewer when a cloud has fewer points)")


@dataclasses.dataclass(frozen=True)
class DescribeOptions(OptionGroup):
  """Stage "describe": the keypoints' LRFs and descriptors."""

  radius_mr: float = option_field(RADIUS_MR, "support radius of the frames and descriptors, in mr")
  method: str = option_field(
      DEFAULT_METHOD, "LRF method, a key of lrf_jax.METHODS (lrf_net_plus: the most "
      "repeatable; lrf_net is the paper's LRF-Net; mesh methods need mesh inputs)")
  descriptor: str = option_field(DEFAULT_DESCRIPTOR,
                            "descriptor, a key of lrf_jax.descriptors.DESCRIPTORS")
  weights: str = option_field(
      "objects", "weights of a learned LRF method: objects (the paper's training data), rooms "
      "(RGB-D room fragments), streets (LiDAR sweeps), or a parameter file's path; weights "
      "other than objects choose the pose, the verdict counts on the object weights' "
      "description",
      metavar="KIND|PATH")


@dataclasses.dataclass(frozen=True)
class MatchOptions(OptionGroup):
  """Stage "match": the correspondences kept from the descriptors' nearest neighbors."""

  n_correspondences: int = option_field(1000, "correspondences kept after matching")
  mutual: bool = option_field(False, "keep mutual nearest matches only")
  ratio: float | None = option_field(None, "Lowe's ratio-test threshold in (0, 1] (default: none)")


@dataclasses.dataclass(frozen=True)
class HypothesisOptions(OptionGroup):
  """Stages "hypotheses" and "verify": the pose hypotheses, their score and their re-ranking."""

  iterations: int = option_field(1000, "hypotheses of the 3-point estimator")
  inlier_mr: float = option_field(5.0, "inlier distance of the hypothesis score, in mr")
  verify: int | None = option_field(
      None, "hypotheses of the lrf and 3point estimators re-ranked by overlap (default: all; "
      "0: none)")
  estimator: str = option_field(
      "graph", "compatibility graph (graph), one correspondence per hypothesis (lrf) or "
      "classic 3-point RANSAC", choices=ESTIMATORS)


@dataclasses.dataclass(frozen=True)
class IcpOptions(OptionGroup):
  """Stage "icp": the refinement of the winner (`icp_mr` is also the overlap distance of the
  verification and the verdict)."""

  icp_iterations: int = option_field(50, "ICP iterations (0: none)")
  icp_mr: float = option_field(3.0, "ICP pairing and overlap distance, in mr")
  icp_mode: str = option_field("point_to_plane", "ICP variant", choices=ICP_MODES)
  icp_fine: bool = option_field(True, "a second ICP pass at an adaptive gate (1 mr to icp_mr mr)")


@dataclasses.dataclass(frozen=True)
class VerdictOptions(OptionGroup):
  """The effort spent before the verdict."""

  effort: str = option_field(
      "normal", "fast: one pass; high: more keypoints per cloud and several seeds, their "
      "correspondences pooled before the same hypotheses and verdict (a few times slower), "
      "then, where still not sure and no mr was given, one pass at twice the working "
      "resolution; normal: one pass, and high's passes on a pair the first leaves not sure "
      "(many scans: high's pooled pass on the not sure pairs between the first pose graph's "
      "components)",
      choices=EFFORTS)


# The groups of `RegisterOptions`: attribute -> class, in the pipeline's order.
GROUPS: dict[str, type] = {
    "inputs": InputOptions, "detection": KeypointOptions, "description": DescribeOptions,
    "matching": MatchOptions, "hypotheses": HypothesisOptions, "icp": IcpOptions,
    "verdict": VerdictOptions}
# Every flat field, in the groups' order, and the group that holds it.
FIELDS: tuple[str, ...] = tuple(f.name for cls in GROUPS.values()
                                for f in dataclasses.fields(cls))
GROUP_OF: dict[str, str] = {f.name: group for group, cls in GROUPS.items()
                            for f in dataclasses.fields(cls)}


def option_fields() -> tuple[dataclasses.Field, ...]:
  """Every flat field of `RegisterOptions` as its group's `dataclasses.Field` (name, type,
  default and the command line's metadata: help, flag, choices, metavar), in `FIELDS` order."""
  return tuple(f for cls in GROUPS.values() for f in dataclasses.fields(cls))


@dataclasses.dataclass(frozen=True, init=False)
class RegisterOptions:
  """The options of `register` (every keyword but the clouds, `params` and `init`), one group
  per stage.

  Built from groups, flat fields or both: `RegisterOptions(icp=IcpOptions(icp_mr=2.0))`,
  `RegisterOptions(icp_mr=2.0)` (a flat field replaces the one of its group, given or default).
  Every field is checked on construction (`check_values`); use `with_overrides` or
  `dataclasses.replace` (groups or flat fields) for a changed copy (checked again). A flat field
  reads as an attribute too (`options.icp_mr`, the same as `options.icp.icp_mr`).

  Raises:
    TypeError: an unknown field, or a group of the wrong class.
    ValueError: naming the first field that `register` would refuse.
  """

  inputs: InputOptions
  detection: KeypointOptions
  description: DescribeOptions
  matching: MatchOptions
  hypotheses: HypothesisOptions
  icp: IcpOptions
  verdict: VerdictOptions

  def __init__(self, inputs: InputOptions | None = None,
               detection: KeypointOptions | None = None,
               description: DescribeOptions | None = None, matching: MatchOptions | None = None,
               hypotheses: HypothesisOptions | None = None, icp: IcpOptions | None = None,
               verdict: VerdictOptions | None = None, **fields: Any) -> None:
    given = dict(inputs=inputs, detection=detection, description=description,
                 matching=matching, hypotheses=hypotheses, icp=icp, verdict=verdict)
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
      raise TypeError(f"register: unknown option {unknown[0]!r}; expected one of {list(FIELDS)}")
    for name, group in given.items():
      if group is not None and not isinstance(group, GROUPS[name]):
        raise TypeError(f"{name}: expected a {GROUPS[name].__name__} or None, got "
                        f"{type(group).__name__}")
    groups = {name: group if group is not None else _DEFAULT_GROUPS[name]
              for name, group in given.items()}
    if fields:  # every field checked in one order: the message names the first refused
      values = {k: v for g in groups.values() for k, v in g.as_dict().items()}
      check_values({**values, **fields})
      for name in GROUPS:
        mine = {k: v for k, v in fields.items() if GROUP_OF[k] == name}
        if mine:
          groups[name] = dataclasses.replace(groups[name], **mine)
    for name, group in groups.items():
      object.__setattr__(self, name, group)

  if not TYPE_CHECKING:  # flat reads for users; the package reads the groups (mypy checks it)
    def __getattr__(self, name: str) -> Any:
      group = GROUP_OF.get(name)
      if group is None:
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
      return getattr(getattr(self, group), name)

  def with_overrides(self, **overrides: Any) -> RegisterOptions:
    """A checked copy with `overrides` (flat field names or group names) replaced.

    Raises:
      TypeError: a name that is not an option of `register`.
      ValueError: a value `register` would refuse.
    """
    unknown = sorted(set(overrides) - set(FIELDS) - set(GROUPS))
    if unknown:
      raise TypeError(f"register: unknown option {unknown[0]!r}; expected one of {list(FIELDS)}")
    return dataclasses.replace(self, **overrides) if overrides else self

  def as_dict(self) -> dict[str, Any]:
    """The options as {field: value}, flat (plain data: numbers, strings, booleans, None,
    tuples), in `FIELDS` order."""
    return {name: getattr(getattr(self, GROUP_OF[name]), name) for name in FIELDS}


def check_values(values: dict[str, Any]) -> None:
  """Raise a ValueError naming the first of `values` ({flat field: value}, any subset of
  `FIELDS`) that `register` would refuse; the message reads "<field>: expected ..., got ..."."""
  for name in ("radius_mr", "inlier_mr", "icp_mr"):
    if name in values and not is_positive(values[name]):
      raise ValueError(f"{name}: expected a positive number of mesh resolutions, got "
                       f"{values[name]!r}")
  for name in ("n_keypoints", "n_correspondences", "iterations"):
    if name in values and not is_count(values[name], 1):
      raise ValueError(f"{name}: expected a positive integer, got {values[name]!r}")
  for name in ("icp_iterations", "verify"):
    if name not in values:
      continue
    val = values[name]
    if not ((val is None and name == "verify") or is_count(val, 0)):
      raise ValueError(f"{name}: expected a non-negative integer, got {val!r}")
  if "seed" in values:
    validate_seed(values["seed"])
  if "voxel_size" in values:
    check_voxel_size(values["voxel_size"])
  _check_names(values)
  for name in ("mutual", "ratio", "icp_fine"):
    if name not in values:
      continue
    val = values[name]
    if name == "ratio" and not (val is None or (is_positive(val) and val <= 1)):
      raise ValueError(f"ratio: expected None or a ratio-test threshold in (0, 1], got {val!r}")
    if name != "ratio" and not isinstance(val, (bool, np.bool_)):
      raise ValueError(f"{name}: expected True or False, got {val!r}")
  for name in ("source_viewpoint", "target_viewpoint"):
    if name in values:
      validate_viewpoint(values[name], name)
  mr = values.get("mr")
  if mr is not None and not is_positive(mr):
    raise ValueError(f"mr: expected a positive mesh resolution, got {mr!r}")


def _check_names(values: dict[str, Any]) -> None:
  """The names among `values`; the method and descriptor registries are read (loading every
  method) only for names other than the defaults, which are registered (a test checks it)."""
  estimator = values.get("estimator", ESTIMATORS[0])
  if estimator not in ESTIMATORS:
    raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
  if (values.get("method", DEFAULT_METHOD), values.get("descriptor", DEFAULT_DESCRIPTOR),
      values.get("weights", "objects")) != (DEFAULT_METHOD, DEFAULT_DESCRIPTOR, "objects"):
    _check_registered(values)
  icp_mode = values.get("icp_mode", ICP_MODES[0])
  if icp_mode not in ICP_MODES:
    raise ValueError(f"icp_mode: expected 'point_to_plane' or 'point_to_point', got "
                     f"{icp_mode!r}")
  keypoints = values.get("keypoints", KEYPOINTS[0])
  if keypoints not in KEYPOINTS:
    raise ValueError(f"keypoints: expected one of {KEYPOINTS}, got {keypoints!r}")
  effort = values.get("effort", EFFORTS[0])
  if effort not in EFFORTS:
    raise ValueError(f"effort: expected one of {EFFORTS}, got {effort!r}")


def _check_registered(values: dict[str, Any]) -> None:
  from lrf_jax.descriptors import DESCRIPTORS
  from lrf_jax.frames import METHODS
  method = values.get("method", DEFAULT_METHOD)
  if not isinstance(method, str) or method not in METHODS:
    raise ValueError(f"method: unknown LRF method {method!r}; expected one of "
                     f"{sorted(METHODS)}")
  weights = values.get("weights", "objects")
  if weights != "objects":
    from lrf_jax.frames.weights import learned_weights_file
    learned_weights_file(METHODS[method], weights)  # a kind shipped for it, or a file
  descriptor = values.get("descriptor", DEFAULT_DESCRIPTOR)
  if not isinstance(descriptor, str) or descriptor not in DESCRIPTORS:
    raise ValueError(f"descriptor: unknown descriptor {descriptor!r}; expected one of "
                     f"{sorted(DESCRIPTORS)}")


def resolve(options: RegisterOptions | None, overrides: dict[str, Any]) -> RegisterOptions:
  """`options` (None: `DEFAULTS`) with `overrides` replaced, checked.

  Raises:
    TypeError: `options` that is not a `RegisterOptions`, or an unknown override.
    ValueError: a value `register` would refuse.
  """
  return resolve_as(RegisterOptions, DEFAULTS, options, overrides)


def resolve_as(cls: type, defaults: Any, options: Any, overrides: dict[str, Any]) -> Any:
  """`options` of class `cls` (None: `defaults`) with `overrides` replaced by its
  `with_overrides` (checked): the one rule of `resolve` for every options class.

  Raises:
    TypeError: `options` that is neither None nor a `cls`, or an unknown override.
    ValueError: a value the options' check refuses.
  """
  if options is None:
    options = defaults
  elif not isinstance(options, cls):
    raise TypeError(f"options: expected a {cls.__name__} or None, got {type(options).__name__}")
  return options.with_overrides(**overrides)


def check_register_options(**options: Any) -> RegisterOptions:
  """`RegisterOptions` of `DEFAULTS` with `options` replaced: a ValueError naming the first
  option `register` would refuse, before any cloud is read (`register_all`, the command lines).
  """
  return resolve(None, options)


def check_voxel_size(voxel_size: Any) -> None:
  """ValueError unless `voxel_size` is None, 0 or a positive voxel edge
  (`checks.validate_voxel_size`)."""
  validate_voxel_size(voxel_size)


# Each group's defaults, the groups a `RegisterOptions` not given them holds.
_DEFAULT_GROUPS: dict[str, Any] = {name: cls() for name, cls in GROUPS.items()}
# The options `register` uses when given none: every default, once.
DEFAULTS = RegisterOptions()
