"""Registration from features computed once per scan: `describe_scan` then `register_scans`.

`register(source, target)` prepares and describes both clouds for every pair it is given. A set
of scans (`register_all`) registers each scan against several others at one working resolution;
here each scan is described once (`describe_scan`: its working cloud, keypoints, normals, LRFs
and descriptors) and every pair is registered from the two scans' features (`register_scans`:
matching, hypotheses, verification, ICP and the verdict, the stages of `register` after
"describe", unchanged).

What differs from `register` on the same pair: the resolution is given (the set's, not the
pair's), and each scan draws its keypoints from its own generator seeded with the seed (seed + k
for the k-th seed of `effort="high"`), so a scan's features depend on the scan, the options and
the seed alone, never on the scan it is paired with (`register` draws the target's keypoints
after the source's from one generator). The stages after matching draw from a generator seeded
with the seed, as `register`'s draw from what is left of its own. And `effort="normal"` is one
pass per pair here, as `"fast"` is (a scan is described once for all its pairs; `"high"`
describes it with the pooled seeds for every pair); `register_all`'s default then registers
again, with `"high"`, the "not sure" pairs between the components of its first pose graph.
"""

from __future__ import annotations

from typing import Any, NamedTuple, cast

import numpy as np

from lrf_jax.checks import derived_seed, validate_radius, validate_seed, validate_viewpoint
from lrf_jax.frames import METHODS
from lrf_jax.geometry.cloud import as_cloud
from lrf_jax.registration import stages
from lrf_jax.registration.effort import EFFORT_SEEDS, high_effort_options, pool
from lrf_jax.registration.options import (DescribeOptions, KeypointOptions, RegisterOptions,
                                          resolve)
from lrf_jax.registration.pipeline import conclude
from lrf_jax.registration.result import Registration

__all__ = ["DESCRIBE_FIELDS", "ScanFeatures", "SideRun", "describe_scan", "register_scans"]

# The options a scan's features depend on: two scans' features can be paired only when these
# (and the resolution) are the same.
DESCRIBE_FIELDS = ("method", "descriptor", "weights", "radius_mr", "n_keypoints", "keypoints",
                   "effort", "seed", "voxel_size")


class SideRun(NamedTuple):
  """One seed's keypoints of a scan and what `stages.describe` computed at them: frames (k, 3, 3)
  float32 with valid (k,) bool, descriptors (k, D) float32 with valid (k,) bool."""

  side: stages.Side
  frames: tuple[np.ndarray, np.ndarray]
  descriptors: tuple[np.ndarray, np.ndarray]


class ScanFeatures(NamedTuple):
  """A scan described once for every pair it is in.

  Attributes:
    mr: the working resolution the features were computed at (cloud units).
    voxel: the scan's thinning voxel edge (0: not thinned).
    runs: one `SideRun` per seed (one; `EFFORT_SEEDS` with `effort="high"`).
    evidence: with keypoints other than random ones, or learned weights other than the object
      weights, the default detector's (seeded random keypoints) per seed, described with the
      object weights (`stages.evidence_description`), which the verdict counts on
      (`stages.default_evidence`); else ().
    options: the values of `DESCRIBE_FIELDS` the features were computed with.
  """

  mr: float
  voxel: float
  runs: tuple[SideRun, ...]
  evidence: tuple[SideRun, ...]
  options: tuple[Any, ...]


def _describe_options(opts: RegisterOptions) -> tuple[Any, ...]:
  flat = opts.as_dict()
  return tuple(flat[f] for f in DESCRIBE_FIELDS)


def _run(side: stages.Side, mr: float, radius: float, seed: int, description: DescribeOptions,
         params: Any) -> SideRun:
  """`stages.describe` of one side (a one-sided `Prepared`)."""
  prepared = stages.Prepared(cast(Any, (side,)), mr, radius, np.random.default_rng(seed), seed,
                             0.0)
  features = stages.describe(prepared, description, params, stages.StageTimer())
  return SideRun(side, features.frames[0], features.descriptors[0])


def describe_scan(scan: Any, options: RegisterOptions | None = None, *, mr: float,
                  viewpoint: Any = None, params: Any = None, name: str = "scan",
                  **overrides: Any) -> ScanFeatures:
  """A scan's features for `register_scans`, at the working resolution `mr`.

  The scan is thinned as `register` thins a cloud at that resolution
  (`stages.working_cloud`, `voxel_size`), then for each seed (the option's; with
  `effort="high"` also seed + 1, ..., with `effort.EFFORT_KEYPOINTS` x the keypoints) its
  keypoints are drawn from a generator of that seed alone (`stages.draw_keypoints`), with
  normals towards `viewpoint` where the method or descriptor needs them, and described
  (`stages.describe`: LRFs, Eq. (1)-(6) of the paper for the learned methods, and
  descriptors at r = radius_mr mr).

  Args:
    scan: a path, (n, 3) array, `Cloud` or `CheckedCloud` (at least 10 points).
    options: `RegisterOptions` (None: the defaults); `overrides` replace fields.
    mr: the working resolution (cloud units, > 0): the same for every scan paired.
    viewpoint: optional (3,) sensor position in the scan's frame.
    params: learned LRF parameters (None: the method's shipped weights).
    name: the scan's name in error messages.

  Returns:
    `ScanFeatures`.

  Raises:
    ValueError: a bad cloud, option, resolution or viewpoint (naming it).
  """
  opts = resolve(options, overrides)
  if not (isinstance(mr, (int, float)) and np.isfinite(mr) and mr > 0):
    raise ValueError(f"mr: expected a positive working resolution, got {mr!r}")
  cloud = as_cloud(scan, name)
  if len(cloud.points) < 10:
    raise ValueError(f"{name}: expected a cloud of at least 10 points, got {len(cloud.points)}")
  description = opts.description
  if METHODS[description.method].needs_mesh and cloud.faces is None:
    raise ValueError(f"{name}: method {description.method!r} needs a triangle mesh")
  view = validate_viewpoint(viewpoint, "viewpoint")
  seed = validate_seed(opts.inputs.seed)
  mr = float(mr)
  working, index, voxel = stages.working_cloud(cloud, mr, opts.inputs.voxel_size, name=name)
  radius = validate_radius(description.radius_mr * mr)
  high = opts.verdict.effort == "high"
  detection = (high_effort_options(opts) if high else opts).detection
  seeds = [derived_seed(seed, k) for k in range(EFFORT_SEEDS if high else 1)]
  base = stages.prepare_side(working, index, view, mr, radius, detection, description,
                             np.random.default_rng(seeds[0]))
  described = stages.evidence_description(description, params)
  runs, evidence = [], []
  for s in seeds:
    side = base if s == seeds[0] else _redraw(base, mr, detection, s)
    runs.append(_run(side, mr, radius, s, description, params))
    if detection.keypoints != "random" or described is not None:  # the verdict's evidence
      plain = detection.with_overrides(keypoints="random")
      evidence.append(_run(_redraw(base, mr, plain, s), mr, radius, s,
                           description if described is None else described,
                           params if described is None else None))
  return ScanFeatures(mr, voxel, tuple(runs), tuple(evidence), _describe_options(opts))


def _redraw(side: stages.Side, mr: float, detection: KeypointOptions, seed: int) -> stages.Side:
  """`side` with its keypoints drawn again from a generator of `seed` (`stages.reseed`)."""
  kp = stages.draw_keypoints(side.points, mr, detection, np.random.default_rng(seed))
  return side._replace(keypoints=np.asarray(kp, np.int64))


def register_scans(source: ScanFeatures, target: ScanFeatures,
                   options: RegisterOptions | None = None, **overrides: Any) -> Registration:
  """Register two described scans: `register`'s stages after "describe" (matching, hypotheses,
  verification, ICP, the verdict) on their features (module docstring).

  Args:
    source, target: `describe_scan` of each, with the same resolution and the same values of
      `DESCRIBE_FIELDS`.
    options: `RegisterOptions` (None: the defaults); `overrides` replace fields. Its fields in
      `DESCRIBE_FIELDS` must be the ones the features were computed with; mr and the
      viewpoints are the features' own.

  Returns:
    `Registration` (`transform` maps the source scan's points into the target's frame;
    `correspondences` index the scans' input points).

  Raises:
    ValueError: features of different resolutions or options, or options that differ from
      theirs (naming the field).
  """
  opts = resolve(options, overrides)
  if source.mr != target.mr:
    raise ValueError(f"mr: the source was described at {source.mr:.6g}, the target at "
                     f"{target.mr:.6g}; describe both at one resolution")
  for field, a, b, own in zip(DESCRIBE_FIELDS, source.options, target.options,
                              _describe_options(opts)):
    if not (a == b == own):
      raise ValueError(f"{field}: the features were described with {a!r} (source) and {b!r} "
                       f"(target), the options say {own!r}")
  if len(source.evidence) != len(target.evidence):
    raise ValueError(f"params: the source was described with {len(source.evidence)} evidence "
                     f"runs, the target with {len(target.evidence)}; describe both with the same "
                     "params")
  seed = validate_seed(opts.inputs.seed)
  wide = high_effort_options(opts) if opts.verdict.effort == "high" else opts
  timer = stages.StageTimer()
  radius = validate_radius(opts.description.radius_mr * source.mr)
  voxel = target.voxel or source.voxel
  runs = []
  with timer("matching"):
    for k, (a, b) in enumerate(zip(source.runs, target.runs)):
      prepared = stages.Prepared((a.side, b.side), source.mr, radius,
                                 np.random.default_rng(seed + k), seed + k, voxel)
      features = stages.Features((a.frames, b.frames), (a.descriptors, b.descriptors))
      matches = stages.match(features, wide)
      if source.evidence:  # the default detector's or the object weights' (`describe_scan`)
        ea, eb = source.evidence[k], target.evidence[k]
        sampled = prepared._replace(sides=(ea.side, eb.side))
        matches = stages.with_evidence(matches, sampled, stages.Features(
            (ea.frames, eb.frames), (ea.descriptors, eb.descriptors)))
      runs.append((prepared, features, matches))
  prepared, features, matches = runs[0] if len(runs) == 1 else pool(runs)
  return conclude(prepared, features, matches, opts, timer)
