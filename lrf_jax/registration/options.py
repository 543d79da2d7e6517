"""`RegisterOptions`: every option of `register` and its default, held once.

`register(source, target, options=None, **overrides)` reads its options from a frozen
`RegisterOptions` (the module's `DEFAULTS` unless one is given) with `overrides` replacing
fields; the command lines (`lrf-register`, its multiway form, `lrf-batch register`) derive their
flags, defaults and help from the fields (`lrf_jax.cli.options.add_register_flags`), so a default
changed here changes everywhere. The constructor checks every field (`check`); an instance is a
checked set of options, and it pickles as plain data for the data-set layer.

Lengths are in mr, the working resolution (`lrf_jax.geometry.resolution.registration_resolution`),
unless a field says otherwise.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from lrf_jax.checks import (is_count, is_positive, validate_seed, validate_viewpoint,
                            validate_voxel_size)
from lrf_jax.defaults import DEFAULT_METHOD, RADIUS_MR

ESTIMATORS = ("graph", "lrf", "3point")
KEYPOINTS = ("random", "iss")
ICP_MODES = ("point_to_plane", "point_to_point")
EFFORTS = ("normal", "high")
DEFAULT_DESCRIPTOR = "toldi"


def _option(default: Any, help: str, *, flag: str | None = "", choices: tuple | None = None,
            metavar: Any = None) -> Any:
  """A field of `RegisterOptions`: its default and what a command line shows for it (`flag`:
  the option's name when it is not the field's in kebab case; None: no flag)."""
  return dataclasses.field(default=default, metadata={
      "help": help, "flag": flag, "choices": choices, "metavar": metavar})


@dataclasses.dataclass(frozen=True)
class RegisterOptions:
  """The options of `register` (every keyword but the clouds, `params` and `init`).

  Built only through its constructor, which checks every field (`check`); use
  `dataclasses.replace` or `with_overrides` for a changed copy (checked again).

  Raises:
    ValueError: naming the first field that `register` would refuse.
  """

  mr: float | None = _option(
      None, "the working resolution in the clouds' units, the unit of every length (default: "
      "measured: the source's point spacing; on a raw, uneven cloud such as a LiDAR sweep the "
      "area-weighted median spacing; never finer than 1/300 of the cloud's extent; for clouds "
      "of different densities the coarser one)")
  voxel_size: float | None = _option(
      None, "thin both clouds by voxel averaging first, voxels of this edge in the clouds' "
      "units (0: keep every point; default: thin a cloud far denser than the working "
      "resolution, such as a raw LiDAR sweep or a full-density fragment, at it)")
  radius_mr: float = _option(RADIUS_MR, "support radius of the frames and descriptors, in mr")
  keypoints: str = _option("random", "keypoint detector: seeded random points or ISS",
                           choices=KEYPOINTS)
  n_keypoints: int = _option(3000, "keypoints per cloud (fewer when a cloud has fewer points)")
  n_correspondences: int = _option(1000, "correspondences kept after matching")
  iterations: int = _option(1000, "hypotheses of the 3-point estimator")
  inlier_mr: float = _option(5.0, "inlier distance of the hypothesis score, in mr")
  verify: int | None = _option(
      None, "hypotheses of the lrf and 3point estimators re-ranked by overlap (default: all; "
      "0: none)")
  estimator: str = _option(
      "graph", "compatibility graph (graph), one correspondence per hypothesis (lrf) or "
      "classic 3-point RANSAC", choices=ESTIMATORS)
  icp_iterations: int = _option(50, "ICP iterations (0: none)")
  icp_mr: float = _option(3.0, "ICP pairing and overlap distance, in mr")
  icp_mode: str = _option("point_to_plane", "ICP variant", choices=ICP_MODES)
  icp_fine: bool = _option(True, "a second ICP pass at an adaptive gate (1 mr to icp_mr mr)")
  method: str = _option(
      DEFAULT_METHOD, "LRF method, a key of lrf_jax.METHODS (lrf_net_plus: the most "
      "repeatable; lrf_net is the paper's LRF-Net; mesh methods need mesh inputs)")
  descriptor: str = _option(DEFAULT_DESCRIPTOR, "descriptor, a key of lrf_jax.descriptors.DESCRIPTORS")
  mutual: bool = _option(False, "keep mutual nearest matches only")
  ratio: float | None = _option(None, "Lowe's ratio-test threshold in (0, 1] (default: none)")
  seed: int = _option(0, "seed of keypoints, neighbor subsamples and sampling")
  source_viewpoint: tuple[float, float, float] | None = _option(
      None, "sensor position of a single-view source scan, in its own coordinates (orients "
      "its normals and lrf_net_plus's z)", metavar=("X", "Y", "Z"))
  target_viewpoint: tuple[float, float, float] | None = _option(
      None, "sensor position of a single-view target scan", metavar=("X", "Y", "Z"))
  effort: str = _option(
      "normal", "high: more keypoints per cloud and several seeds, their correspondences "
      "pooled before the same hypotheses and verdict (a few times slower; may settle a 'not "
      "sure')", choices=EFFORTS)

  def __post_init__(self) -> None:
    self.check()
    for name in ("source_viewpoint", "target_viewpoint"):
      vp = getattr(self, name)
      if vp is not None:  # plain floats: hashable, and cheap to pickle
        object.__setattr__(self, name, tuple(float(v) for v in np.asarray(vp).ravel()))

  def check(self) -> None:
    """Raise a ValueError naming the first field `register` would refuse (the message reads
    "<field>: expected ..., got ...")."""
    for name in ("radius_mr", "inlier_mr", "icp_mr"):
      val = getattr(self, name)
      if not is_positive(val):
        raise ValueError(f"{name}: expected a positive number of mesh resolutions, got {val!r}")
    for name in ("n_keypoints", "n_correspondences", "iterations"):
      if not is_count(getattr(self, name), 1):
        raise ValueError(f"{name}: expected a positive integer, got {getattr(self, name)!r}")
    for name in ("icp_iterations", "verify"):
      val = getattr(self, name)
      if not ((val is None and name == "verify") or is_count(val, 0)):
        raise ValueError(f"{name}: expected a non-negative integer, got {val!r}")
    validate_seed(self.seed)
    check_voxel_size(self.voxel_size)
    self._check_names()
    for name in ("mutual", "ratio", "icp_fine"):
      val = getattr(self, name)
      if name == "ratio" and not (val is None or (is_positive(val) and val <= 1)):
        raise ValueError(f"ratio: expected None or a ratio-test threshold in (0, 1], got {val!r}")
      if name != "ratio" and not isinstance(val, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, got {val!r}")
    for name in ("source_viewpoint", "target_viewpoint"):
      validate_viewpoint(getattr(self, name), name)
    if self.mr is not None and not is_positive(self.mr):
      raise ValueError(f"mr: expected a positive mesh resolution, got {self.mr!r}")

  def _check_names(self) -> None:
    """The names; the method and descriptor registries are read (loading every method) only
    for names other than the defaults, which are registered (a test checks it)."""
    if self.estimator not in ESTIMATORS:
      raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {self.estimator!r}")
    if (self.method, self.descriptor) != (DEFAULT_METHOD, DEFAULT_DESCRIPTOR):
      self._check_registered()
    if self.icp_mode not in ICP_MODES:
      raise ValueError(f"icp_mode: expected 'point_to_plane' or 'point_to_point', got "
                       f"{self.icp_mode!r}")
    if self.keypoints not in KEYPOINTS:
      raise ValueError(f"keypoints: expected one of {KEYPOINTS}, got {self.keypoints!r}")
    if self.effort not in EFFORTS:
      raise ValueError(f"effort: expected one of {EFFORTS}, got {self.effort!r}")

  def _check_registered(self) -> None:
    from lrf_jax.descriptors import DESCRIPTORS
    from lrf_jax.frames import METHODS
    if not isinstance(self.method, str) or self.method not in METHODS:
      raise ValueError(f"method: unknown LRF method {self.method!r}; expected one of "
                       f"{sorted(METHODS)}")
    if not isinstance(self.descriptor, str) or self.descriptor not in DESCRIPTORS:
      raise ValueError(f"descriptor: unknown descriptor {self.descriptor!r}; expected one of "
                       f"{sorted(DESCRIPTORS)}")

  def with_overrides(self, **overrides: Any) -> RegisterOptions:
    """A checked copy with `overrides` (field names) replaced.

    Raises:
      TypeError: a name that is not an option of `register`.
      ValueError: a value `register` would refuse.
    """
    unknown = sorted(set(overrides) - set(FIELDS))
    if unknown:
      raise TypeError(f"register: unknown option {unknown[0]!r}; expected one of {list(FIELDS)}")
    return dataclasses.replace(self, **overrides) if overrides else self

  def as_dict(self) -> dict[str, Any]:
    """The options as {field: value} (plain data: numbers, strings, booleans, None, tuples)."""
    return {name: getattr(self, name) for name in FIELDS}


FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(RegisterOptions))


def resolve(options: RegisterOptions | None, overrides: dict[str, Any]) -> RegisterOptions:
  """`options` (None: `DEFAULTS`) with `overrides` replaced, checked.

  Raises:
    TypeError: `options` that is not a `RegisterOptions`, or an unknown override.
    ValueError: a value `register` would refuse.
  """
  if options is None:
    options = DEFAULTS
  elif not isinstance(options, RegisterOptions):
    raise TypeError(f"options: expected a RegisterOptions or None, got {type(options).__name__}")
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

# The options `register` uses when given none: every default, once.
DEFAULTS = RegisterOptions()
