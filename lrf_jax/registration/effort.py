"""`register(..., effort="high")`: more keypoints and several seeds, pooled into one set of
correspondences before the one hypothesis stage and the one verdict; the default
`effort="normal"` runs it on a pair its first pass leaves "not sure" (`escalates`). Both end,
where the pooled pass is not sure too and the working resolution was measured, with one pass
at twice that resolution (`coarser_pass`).

The stages prepare, describe and match run for `EFFORT_SEEDS` seeds (the option's seed, seed + 1,
...) with `EFFORT_KEYPOINTS` times the keypoints, on the same working clouds (`stages.reseed`:
only the keypoints and the seeded subsamples differ). Each seed matches its own source keypoints
to its own target keypoints (the best `n_correspondences` of `EFFORT_KEYPOINTS` times as many
candidates); the seeds' keypoints, frames, descriptors and correspondences are then concatenated
(`pool`), a correspondence found by two seeds (the same source and target point) kept once.
Hypotheses, the chance level (the pooled correspondences shuffled), the rivals and the verdict
are then computed once on the pooled set, exactly as for one seed: there is no "try K times and
keep the one that claims", so no multiple testing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, cast

import numpy as np

from lrf_jax.checks import derived_seed
from lrf_jax.registration import stages
from lrf_jax.registration.options import RegisterOptions
from lrf_jax.registration.result import Registration

# Seeds pooled and the factor on `n_keypoints` with effort="high", chosen on bench_scenes.py's
# tune split (35 cases; claimed right / wrong): default 20 / 0; 3 seeds x 2 keypoints 22 / 0
# (median 15.3 s a case); 2 seeds x 2 keypoints 22 / 0, the same claims in less time (11.5 s).
EFFORT_SEEDS = 2
EFFORT_KEYPOINTS = 2
# The last step of "normal" and "high" on a pair still not sure after the pooled pass: one pass
# at COARSER_MR times the working resolution (descriptors, frames and every length in mr twice as
# wide). Chosen on the full-density fused fragments (three pairs flipped or not sure at their own
# resolution, all claimed right at 1.5x and at 2x; 2x with twice the winning support) and
# checked on every benchmark's negatives; see `coarser_pass`.
COARSER_MR = 2.0


def high_effort_options(opts: RegisterOptions) -> RegisterOptions:
  """The options of each seed's prepare/describe/match: `EFFORT_KEYPOINTS` x the keypoints."""
  return opts.with_overrides(n_keypoints=EFFORT_KEYPOINTS * int(opts.detection.n_keypoints))


def tried(first_code: str) -> str:
  """What `effort="normal"` tried when its first pass (verdict code `first_code`) was not sure,
  in words, for `Registration.reason`."""
  return (f"tried one pass ({first_code}), then {EFFORT_SEEDS} seeds with {EFFORT_KEYPOINTS}x "
          "the keypoints pooled")


def tried_pooled() -> str:
  """What `effort="high"` tried before `coarser_pass`, in words, for `Registration.reason`."""
  return f"tried {EFFORT_SEEDS} seeds with {EFFORT_KEYPOINTS}x the keypoints pooled"


def coarser_runs(result_code: str, opts: RegisterOptions) -> bool:
  """Whether `coarser_pass` follows a pooled pass whose verdict has `result_code`: it was not
  sure, and the working resolution was measured (an `mr` given is the user's scale, kept)."""
  return escalates(result_code) and opts.inputs.mr is None


def coarser_options(opts: RegisterOptions, mr: float) -> RegisterOptions:
  """`opts` at `COARSER_MR` x the working resolution `mr` (cloud units): the same counts and
  multiples of mr, every length twice as long."""
  return opts.with_overrides(mr=COARSER_MR * float(mr))


def coarser_tried(code: str) -> str:
  """`coarser_pass`'s step in words, with its verdict's `code`, for `Registration.reason`."""
  return f"then one pass at {COARSER_MR:g}x the working resolution ({code})"


def coarser_pass(pooled: Registration, note: str | None, run: Callable[[], Registration],
                 opts: RegisterOptions, timer: stages.StageTimer) -> Registration:
  """The last step of `effort="normal"` and `"high"`: where the pooled pass is not sure and
  `coarser_runs`, `run()`, one pass at `coarser_options` (with or without an init), judged by
  the same verdict on its own evidence; its result where it is claimed, else `pooled`'s.

  A support of the default radius can be too small to tell a room's planes apart when the
  working resolution is fine against the room (a full-density fragment at about 1/300 of its
  extent): one pass at twice the scale finds the pose the finer passes leave not sure.

  Args:
    pooled: the pooled pass's result.
    note: the steps before, in words ("tried one pass (rival), then 2 seeds ... pooled"); None
      for `effort="high"`'s pooled pass alone (`tried_pooled`, named only where the coarser
      pass runs).
    run: the coarser pass, called only where it runs; a ValueError (no correspondences at that
      scale) keeps `pooled`.
    opts: the call's options (`coarser_runs`).
    timer: the call's timer (`seconds` and `timings` count every pass).

  Returns:
    `Registration`: `pooled` (with `note` in its reason) where the pass does not run; else
    `reason` names the pooled pass's verdict and the coarser one's.
  """
  if not coarser_runs(pooled.reason_code, opts):
    return pooled if note is None else dataclasses.replace(pooled,
                                                           reason=f"{pooled.reason} ({note})")
  note = tried_pooled() if note is None else note
  try:
    second = run()
  except ValueError as e:
    return dataclasses.replace(pooled, reason=f"{pooled.reason} ({note}, "
                               f"{coarser_tried('error')}: {e})", seconds=timer.total(),
                               timings=dict(timer.seconds))
  if second.success:
    return dataclasses.replace(second, reason=f"{second.reason} ({note} "
                               f"({pooled.reason_code}), {coarser_tried(second.reason_code)})",
                               seconds=timer.total(), timings=dict(timer.seconds))
  return dataclasses.replace(pooled, reason=f"{pooled.reason} ({note}, "
                             f"{coarser_tried(second.reason_code)})", seconds=timer.total(),
                             timings=dict(timer.seconds))


def one_pass(source: Any, target: Any, opts: RegisterOptions, params: Any,
             timer: stages.StageTimer
             ) -> tuple[stages.Prepared, stages.Features, stages.Matches]:
  """prepare, describe and match once at `opts` (`effort="fast"`, and the first pass of
  `"normal"`), with the default detector's evidence, described with the object weights, where
  the keypoints or the learned weights are not the default's (`stages.default_evidence`)."""
  with timer("prepare"):
    prepared = stages.prepare(source, target, opts)
  features = stages.describe(prepared, opts.description, params, timer)
  with timer("matching"):
    matches = stages.match(features, opts)
  return prepared, features, stages.default_evidence(prepared, matches, opts, params, timer)


def escalates(code: str) -> bool:
  """Whether `effort="normal"` runs the pooled stages after a first pass whose verdict has
  `code` (an `evidence.REASON_CODES` key): every "not sure" (a claim is kept)."""
  return code != "claimed"


def pooled_stages(source: Any, target: Any, opts: RegisterOptions, params: Any,
                  timer: stages.StageTimer, first: stages.Prepared | None = None
                  ) -> tuple[stages.Prepared, stages.Features, stages.Matches]:
  """prepare, describe and match for `EFFORT_SEEDS` seeds (`high_effort_options`), pooled
  (`pool`). The pooled `Prepared` carries the first seed's generator and seed, which the later
  stages draw from.

  `first`: the `Prepared` of a first pass at `opts` (`effort="normal"`'s): its working clouds,
  resolution and normals are reused and only the keypoints drawn again (`stages.reseed` with
  the same seed draws what `stages.prepare` at the wider options draws), so the result equals
  `effort="high"`'s, bit for bit."""
  wide = high_effort_options(opts)
  with timer("prepare"):
    base = (stages.prepare(source, target, wide) if first is None
            else stages.reseed(first, wide.detection, first.seed))
  runs = []
  for k in range(EFFORT_SEEDS):
    with timer("prepare"):
      prepared = base if k == 0 else stages.reseed(base, wide.detection,
                                                    derived_seed(base.seed, k))
    features = stages.describe(prepared, wide.description, params, timer)
    with timer("matching"):
      matches = stages.match(features, wide)
    runs.append((prepared, features,
                 stages.default_evidence(prepared, matches, wide, params, timer)))
  return pool(runs)


def _concat_pairs(pairs: list) -> tuple[np.ndarray, np.ndarray]:
  return np.concatenate([a for a, _ in pairs]), np.concatenate([b for _, b in pairs])


def pool(runs: list[tuple[stages.Prepared, stages.Features, stages.Matches]]
         ) -> tuple[stages.Prepared, stages.Features, stages.Matches]:
  """One `Prepared`, `Features` and `Matches` from several seeds' on the same working clouds:
  keypoints, frames and descriptors concatenated per side (seed after seed), each seed's
  correspondences offset into the concatenation, and a correspondence between the same two
  working points kept once (its first seed's)."""
  first = runs[0][0]
  sides = []
  for i, side in enumerate(first.sides):
    sides.append(side._replace(keypoints=np.concatenate([p.sides[i].keypoints
                                                         for p, _, _ in runs])))
  frames = tuple(_concat_pairs([f.frames[i] for _, f, _ in runs]) for i in range(2))
  descs = tuple(_concat_pairs([f.descriptors[i] for _, f, _ in runs]) for i in range(2))
  offsets = np.cumsum([[0, 0]] + [[len(p.sides[0].keypoints), len(p.sides[1].keypoints)]
                                  for p, _, _ in runs[:-1]], axis=0)
  kp_s, kp_t = sides[0].keypoints, sides[1].keypoints
  picked = []
  for names in (("source", "target"), ("evidence_source", "evidence_target")):
    if names[0] == "evidence_source" and runs[0][2].evidence_points is not None:
      picked.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))  # index other keypoints
      continue
    qi = np.concatenate([getattr(m, names[0]) + o[0] for (_, _, m), o in zip(runs, offsets)])
    ri = np.concatenate([getattr(m, names[1]) + o[1] for (_, _, m), o in zip(runs, offsets)])
    qi, ri = qi.astype(np.int64), ri.astype(np.int64)
    _, first_seen = np.unique(np.stack([kp_s[qi], kp_t[ri]], axis=1), axis=0, return_index=True)
    keep = np.sort(first_seen)
    picked.append((qi[keep], ri[keep]))
  points = None
  if runs[0][2].evidence_points is not None:  # the default detector's, world coordinates
    each = [cast(tuple, m.evidence_points) for _, _, m in runs]
    joined = [np.concatenate([e[i] for e in each]) for i in range(4)]
    _, first_seen = np.unique(np.concatenate(joined[:2], axis=1), axis=0, return_index=True)
    points = cast(Any, tuple(x[np.sort(first_seen)] for x in joined))
  prepared = first._replace(sides=cast("tuple[stages.Side, stages.Side]", tuple(sides)))
  features = stages.Features(cast(Any, frames), cast(Any, descs))
  matches = stages.Matches(picked[0][0], picked[0][1], picked[1][0], picked[1][1],
                           runs[0][2].own, points)
  return prepared, features, matches
