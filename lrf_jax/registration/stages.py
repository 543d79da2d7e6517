"""The stages of `register`, each a function of the previous stages' typed results and its group
of `RegisterOptions` (`prepare`, `match` and `default_evidence`, which read several groups, take
the whole options):

  prepare      read and check the clouds, the working resolution, thinning, keypoints, normals
  describe     the keypoints' LRFs and descriptors (`Features`)
  match        correspondences, and the default matching's for the verdict (`Matches`)
  hypothesize  pose hypotheses and their inlier counts, the evidence and its chance level
  verify       the winner (refitted on its inliers) and its rivals (`Verified`); `verify_near`
               the same among the hypotheses near a given pose (`register(..., init=T)`)

then `refine.refine_pose` (ICP) and `evidence.decide` (the verdict): `pipeline.register`. A
stage checks nothing its inputs' types already guarantee: `prepare` builds each side's
`CheckedCloud` once and every later stage reads it.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, NamedTuple, cast

import numpy as np

from lrf_jax.frames.compute import frames_checked
from lrf_jax.frames.weights import weights_file, weights_options
from lrf_jax.checks import validate_radius, validate_seed
from lrf_jax.descriptors import descriptors_checked, select_correspondences
from lrf_jax.frames import METHODS
from lrf_jax.geometry.cloud import CheckedCloud, as_cloud
from lrf_jax.geometry.keypoints import iss_keypoints
from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals
from lrf_jax.geometry.resolution import Resolution, pair_resolution, registration_resolution
from lrf_jax.geometry.sampling import thin_cloud, thinning_voxel_size
from lrf_jax.registration import host
from lrf_jax.registration.estimators import centred, finish_result, uncentre
from lrf_jax.registration.evidence import distinct_from
from lrf_jax.registration.options import (DescribeOptions, HypothesisOptions, KeypointOptions,
                                          MatchOptions, RegisterOptions, check_voxel_size)
from lrf_jax.registration.rivals import (REST_FACTOR, EvidenceSet, chance_inliers,
                                         evidence_set, overlap_scores, pose_hypotheses,
                                         rest_hypotheses, rest_rival, rival_inliers)
from lrf_jax.search import engine


class StageTimer:
  """Wall seconds per named stage (`with timer("frames"): ...`)."""

  def __init__(self):
    self.seconds: dict[str, float] = {}
    self._t0 = time.perf_counter()

  @contextlib.contextmanager
  def __call__(self, name: str):
    t = time.perf_counter()
    try:
      yield
    finally:
      self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t

  def total(self) -> float:
    return time.perf_counter() - self._t0


class Side(NamedTuple):
  """One cloud as the stages work on it."""

  cloud: CheckedCloud            # the working cloud (thinned where it was), as the frames take it
  viewpoint: np.ndarray | None
  keypoints: np.ndarray          # (k,) sorted int64 indices into cloud.points
  normals: np.ndarray | None     # estimated towards the viewpoint when a method or SHOT needs them
  input_index: np.ndarray | None  # each working point's input point (thinned clouds), or None
  raw: np.ndarray | None = None  # input points for refine's last pass (thinned, not capped)
  input_spacing: float | None = None  # the input points' mean nearest-neighbor spacing, if measured

  @property
  def points(self) -> np.ndarray:
    return self.cloud.points

  @property
  def faces(self) -> np.ndarray | None:
    return self.cloud.faces


class Prepared(NamedTuple):
  """Stage "prepare": the checked inputs every later stage reads."""

  sides: tuple[Side, Side]
  mr: float
  radius: float                # the support radius (cloud units), `validate_radius`'s range
  rng: np.random.Generator
  seed: int                    # `validate_seed`'s
  voxel_size: float            # the clouds' thinning voxel (0: none)


class Features(NamedTuple):
  """Stage "describe": per side, (frames (k, 3, 3) float32, valid (k,) bool) and (descriptors
  (k, D) float32, valid (k,) bool)."""

  frames: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
  descriptors: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


class Matches(NamedTuple):
  """Stage "match": correspondences as keypoint positions (source, target), best ratio first;
  the default matching's (`evidence_*`), which the verdict counts on; and whether they are the
  same (`own`: the default detector, estimator and matching chose them). With ISS keypoints, or
  learned weights other than the object weights, the evidence is the default detector's keypoints
  described with the object weights (`default_evidence`): `evidence_points` holds its world
  points and frames (p, q, f_p, f_q), and `evidence_*` index those keypoints, not these."""

  source: np.ndarray
  target: np.ndarray
  evidence_source: np.ndarray
  evidence_target: np.ndarray
  own: bool
  evidence_points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


class Hypotheses(NamedTuple):
  """Stage "hypothesize": the correspondences' centred float32 coordinates (src, dst) and
  centroids (cs, cd), the (H, 3, 3), (H, 3) poses in centred coordinates, their inlier counts,
  the frames of the correspondences, the evidence set and its chance level."""

  src: np.ndarray
  dst: np.ndarray
  cs: np.ndarray
  cd: np.ndarray
  rotations: np.ndarray
  translations: np.ndarray
  counts: np.ndarray
  evidence: EvidenceSet
  chance: int


class Verified(NamedTuple):
  """Stage "verify": the winner refitted on its inliers (`estimators.RansacResult`-like, from
  `finish_result`), the overlaps of the re-ranked hypotheses, the winner's evidence inliers and the
  best rival's, and the target grid at the overlap distance (reused by ICP)."""

  coarse: Any
  fits: np.ndarray
  evidence_mask: np.ndarray
  rival: int
  target_grid: engine.Grid
  overlap_distance: float


def prepare(source: Any, target: Any, opts: RegisterOptions) -> Prepared:
  """Stage "prepare": read and check the clouds (each once, `CheckedCloud`), the working
  resolution and thinning (`working_clouds`), keypoints and, where the method or descriptor
  needs them, normals towards the viewpoints."""
  clouds = [as_cloud(x, name) for x, name in ((source, "source"), (target, "target"))]
  for name, cloud in zip(("source", "target"), clouds):
    if len(cloud.points) < 10:
      raise ValueError(f"{name}: expected a cloud of at least 10 points, got {len(cloud.points)}")
  inputs = opts.inputs  # checked when the options were built: the seed and viewpoints are
  seed = int(inputs.seed)
  spec = METHODS[opts.description.method]
  if spec.needs_mesh and any(c.faces is None for c in clouds):
    raise ValueError(f"method {opts.description.method!r} needs triangle meshes on both sides")
  views = [None if vp is None else np.asarray(vp, np.float64)
           for vp in (inputs.source_viewpoint, inputs.target_viewpoint)]
  mr, thinned, voxel = working_clouds(clouds[0], clouds[1], inputs.mr, inputs.voxel_size)
  radius = opts.description.radius_mr * mr
  rng = np.random.default_rng(seed)
  sides = [prepare_side(cloud, index, vp, mr, radius, opts.detection, opts.description, rng
                        )._replace(input_spacing=res.mean_spacing if c.faces is None else None)
           for (cloud, index, res), vp, c in zip(thinned, views, clouds)]  # a mesh: its edges'
  if inputs.voxel_size is None:  # thinned by default: refine's last pass pairs the input points
    sides = [side if side.input_index is None or res.capped else side._replace(raw=c.points)
             for side, c, (_, _, res) in zip(sides, clouds, thinned)]  # an oversampled cloud's
    # voxel centroids average many points of its surface: pairing its input points moved the
    # fused fragments' poses further from the truth, not nearer
  # the support radius, checked once here (the frames and descriptors take it as checked)
  radius = validate_radius(radius)
  return Prepared(cast("tuple[Side, Side]", tuple(sides)), float(mr), radius, rng, seed, voxel)


def prepare_side(cloud: CheckedCloud, index: np.ndarray | None, viewpoint: np.ndarray | None,
                 mr: float, radius: float, detection: KeypointOptions,
                 description: DescribeOptions, rng: np.random.Generator) -> Side:
  """One working cloud as the later stages take it: its keypoints (`draw_keypoints` from `rng`)
  and, where `description.method` or a SHOT descriptor needs them and a viewpoint is known,
  normals towards `viewpoint` at `NORMAL_RADIUS_RATIO` x `radius` (normals a file carried are
  dropped: they are estimated at the support radius, not read)."""
  spec = METHODS[description.method]
  pts = cloud.points
  if cloud.normals is not None:
    cloud = cloud.with_normals(None)
  kp = draw_keypoints(pts, mr, detection, rng)
  normals = None
  if viewpoint is not None and (spec.needs_normals or description.descriptor == "shot"):
    normals = estimate_normals(pts, NORMAL_RADIUS_RATIO * radius, cloud.faces, viewpoint)
    if not spec.uses_viewpoint:  # the frames read them too
      cloud = cloud.with_normals(normals)
  return Side(cloud, viewpoint, np.asarray(kp, np.int64), normals, index)


def draw_keypoints(points: np.ndarray, mr: float, detection: KeypointOptions,
                   rng: np.random.Generator) -> np.ndarray:
  """A cloud's keypoints (indices into `points`): ISS (`detection.keypoints="iss"`, at most
  `detection.n_keypoints`) or `detection.n_keypoints` sorted seeded random points drawn from
  `rng`."""
  count = int(detection.n_keypoints)
  if detection.keypoints == "iss":
    return iss_keypoints(points, mr=mr, max_keypoints=count)
  return np.sort(rng.choice(len(points), min(count, len(points)), replace=False))


def reseed(prepared: Prepared, detection: KeypointOptions, seed: int) -> Prepared:
  """`prepared` with each side's keypoints drawn again (`draw_keypoints`) from `seed`'s stream,
  and `seed` for the later stages' draws: the same working clouds, normals and resolution."""
  rng = np.random.default_rng(validate_seed(seed))
  sides = tuple(side._replace(keypoints=np.asarray(draw_keypoints(side.points, prepared.mr,
                                                                  detection, rng), np.int64))
                for side in prepared.sides)
  return prepared._replace(sides=cast("tuple[Side, Side]", sides), rng=rng, seed=int(seed))


def working_clouds(source: CheckedCloud, target: CheckedCloud, mr: Any, voxel_size: Any
                   ) -> tuple[float, list[tuple[CheckedCloud, np.ndarray | None, Resolution]],
                              float]:
  """The working resolution of a pair and the clouds `register` works on: (mr, [(cloud, index
  into the input points or None, the input cloud's `registration_resolution`) for source and
  target], the thinning voxel edge or 0).

  `mr` None: `pair_resolution` of the two `registration_resolution`s. Each cloud is then thinned
  (or not) by `working_cloud` at that mr; the voxel returned is the last side's that was
  thinned."""
  check_voxel_size(voxel_size)
  resolutions = [registration_resolution(c.points, c.faces, name=n)
                 for c, n in zip((source, target), ("source", "target"))]
  if mr is None:
    mr = pair_resolution(*resolutions)
  out: list[tuple[CheckedCloud, np.ndarray | None, Resolution]] = []
  used = 0.0
  for cloud, res in zip((source, target), resolutions):
    thin, index, voxel = working_cloud(cloud, float(mr), voxel_size, res)
    out.append((thin, index, res))
    used = voxel or used
  return float(mr), out, used


def working_cloud(cloud: CheckedCloud, mr: float, voxel_size: Any, resolution: Any = None, *,
                  name: str = "cloud") -> tuple[CheckedCloud, np.ndarray | None, float]:
  """One cloud as `register` works on it at the working resolution `mr`: (cloud, each working
  point's input point index or None, the thinning voxel edge or 0).

  `voxel_size` None: a cloud (not a mesh) whose mean spacing is under half of mr, or under 0.8
  mr where its extent capped its resolution (`thinning_voxel` of its
  `registration_resolution`, `resolution` when already measured), is thinned
  by the voxel whose centroids come out spaced mr apart (a voxel of mr leaves them closer, about
  0.7 mr: the voxel is scaled by mr over the spacing that gives, measured); 0: it is kept; a
  positive number: it is thinned at that edge (a mesh included, which loses its faces)."""
  check_voxel_size(voxel_size)
  res = None
  if voxel_size is None and cloud.faces is None:
    res = resolution if resolution is not None else registration_resolution(cloud.points, None,
                                                                             name=name)
  voxel = thinning_voxel_size(cloud.points, res, mr, faces=cloud.faces,  # type: ignore[arg-type]
                              voxel_size=voxel_size)
  if not voxel:
    return cloud, None, 0.0
  thin, first, _ = thin_cloud(cloud.points, voxel)
  return CheckedCloud(thin, name="thinned cloud"), first, float(voxel)


def input_indices(prepared: Prepared, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
  """(C, 2) int64 correspondences as input point indices (a thinned side's working points map
  to their voxel's first input point)."""
  cols = [idx if side.input_index is None else side.input_index[idx]
          for side, idx in zip(prepared.sides, (src, dst))]
  return np.stack(cols, axis=1).astype(np.int64)


def describe(prepared: Prepared, description: DescribeOptions, params: Any, timer: StageTimer
             ) -> Features:
  """Stages "frames" and "descriptors": each side's LRFs (`description.method`) and descriptors
  (`description.descriptor`) at its keypoints, as numpy arrays (no JAX imported where host kernels
  compute them).

  A viewpoint-aware method (lrf_net_plus) given neither a viewpoint nor a mesh takes its z sign
  from each patch (`oriented_sign=False`) rather than from normals oriented over the whole
  cloud: that orientation costs about a second per cloud and, measured on the registration
  benchmark, does not register more pairs."""
  method, descriptor = description.method, description.descriptor
  spec = METHODS[method]
  trained_under = (weights_options(weights_file(spec.weights, description.weights))
                   if spec.needs_params and params is None else {})
  frames, descs = [], []
  with timer("frames"):
    for side in prepared.sides:
      options: dict[str, Any] = trained_under | (
          {"oriented_sign": False}
          if spec.uses_viewpoint and side.viewpoint is None and side.faces is None else {})
      # `prepare` checked the cloud, keypoints, radius, seed and viewpoint: the cores that
      # `compute_frames` and `compute_descriptors` call after their checks, on the working clouds
      out = frames_checked(method, side.cloud, side.keypoints, prepared.radius, params=params,
                           weights=description.weights, seed=prepared.seed, viewpoint=side.viewpoint, options=options)
      frames.append((np.asarray(out[0]), np.asarray(out[1])))
  with timer("descriptors"):
    for side, (f, v) in zip(prepared.sides, frames):
      d, ok = descriptors_checked(descriptor, side.cloud.points, side.keypoints, prepared.radius,
                                  f.astype(np.float32), v.astype(bool), faces=side.faces,
                                  seed=prepared.seed, normals=side.normals)
      descs.append((np.asarray(d), np.asarray(ok)))
  return Features(cast(Any, tuple(frames)), cast(Any, tuple(descs)))


def _select(features: Features, estimator: str, n_correspondences: int, radius_mr: float,
            mutual: bool = False, ratio: float | None = None) -> tuple[np.ndarray, np.ndarray]:
  """Nearest descriptors (mutual ones only with `mutual`, those passing the ratio test with
  `ratio`), the `n_correspondences` of smallest ratio d1/d2."""
  (_, v_s), (_, v_t) = features.frames
  (d_s, ok_s), (d_t, ok_t) = features.descriptors
  need_frames = estimator != "3point"
  qi, ri, _ = select_correspondences(d_s, d_t, ok_s & (v_s | ~need_frames),
                                     ok_t & (v_t | ~need_frames), n=n_correspondences,
                                     mutual=mutual, ratio=ratio)
  if len(qi) < (1 if need_frames else 3):
    raise ValueError(f"register: only {len(qi)} descriptor matches (valid frames: source "
                     f"{int(v_s.sum())}, target {int(v_t.sum())}); the clouds are too small or "
                     f"too sparse for r = {radius_mr} mr")
  return qi, ri


# The verdict's evidence: the default matching's correspondences, as many as by default
# (`MatchOptions.n_correspondences`) whatever `n_correspondences` chose the hypotheses'.
EVIDENCE_CORRESPONDENCES = MatchOptions().n_correspondences


def match(features: Features, opts: RegisterOptions) -> Matches:
  """Stage "matching": the correspondences of `opts.matching` for `opts.hypotheses.estimator`
  (`_select`) and the default matching's (`EVIDENCE_CORRESPONDENCES` of them), which the
  verdict counts on whatever option chose the hypotheses' (none when there is none with two
  valid frames); the default's are the same correspondences for the default estimator,
  matching, count and detector (`opts.detection`). Fewer correspondences would let a pose on a
  repeated structure outnumber a truth that few of them witness."""
  matching, estimator = opts.matching, opts.hypotheses.estimator
  n = int(matching.n_correspondences)
  qi, ri = _select(features, estimator, n, opts.description.radius_mr, matching.mutual,
                   matching.ratio)
  detector = opts.detection.keypoints
  own = (estimator == "graph" and not matching.mutual and matching.ratio is None
         and detector == "random" and n == EVIDENCE_CORRESPONDENCES)
  if own:
    return Matches(qi, ri, qi, ri, True)
  if detector != "random":  # the evidence is the default detector's: `default_evidence`
    empty = np.zeros(0, np.int64)
    return Matches(qi, ri, empty, empty, False)
  try:
    eqi, eri = _select(features, "graph", EVIDENCE_CORRESPONDENCES, 0.0)
  except ValueError:
    eqi, eri = np.zeros(0, np.int64), np.zeros(0, np.int64)
  return Matches(qi, ri, eqi, eri, False)


def evidence_description(description: DescribeOptions, params: Any) -> DescribeOptions | None:
  """The description the verdict's evidence is counted on where it is not the run's own, else
  None: a learned method with weights other than its shipped object weights (`weights` another
  kind or a file, or `params` given) is described for the evidence with the object weights, the
  rest of `description` kept. Weights fitted to the scans being registered (a user's own scans,
  the room weights on the scene they were tuned on) can make the descriptors agree on a wrong
  pose, the chance level and the rivals counted on the same descriptors included; the shipped
  object weights never saw those scans."""
  if not METHODS[description.method].needs_params:
    return None
  if params is None and description.weights == "objects":
    return None
  return description.with_overrides(weights="objects")


def default_evidence(prepared: Prepared, matches: Matches, opts: RegisterOptions, params: Any,
                     timer: StageTimer) -> Matches:
  """`matches` with the default detector's and the object weights' evidence, for options whose
  keypoints are not seeded random points (ISS) or whose learned weights are not the shipped
  object weights (`evidence_description`): the keypoints `prepare` draws by default with the
  same seed (`reseed`), described with the object weights where those are not the run's, and
  matched as by default. A detector that picks the same points on two identical copies of an
  object sends every match to one copy, and its correspondences could never witness the other;
  independent random keypoints on each copy split them, as for the default, so no detector
  claims what the default's evidence would not; no weights either."""
  described = evidence_description(opts.description, params)
  if opts.detection.keypoints == "random" and described is None:
    return matches
  plain = opts.detection.with_overrides(keypoints="random")
  sampled = reseed(prepared, plain, prepared.seed)
  features = (describe(sampled, opts.description, params, timer) if described is None
              else describe(sampled, described, None, timer))
  with timer("matching"):
    return with_evidence(matches, sampled, features)


def with_evidence(matches: Matches, sampled: Prepared, features: Features) -> Matches:
  """`matches` with the evidence of the default matching (`EVIDENCE_CORRESPONDENCES`
  correspondences) between the seeded random keypoints
  of `sampled` (described in `features`): their world points and frames, and the indices of
  the correspondences among them (none when they give no match)."""
  try:
    eqi, eri = _select(features, "graph", EVIDENCE_CORRESPONDENCES, 0.0)
  except ValueError:
    eqi, eri = np.zeros(0, np.int64), np.zeros(0, np.int64)
  return matches._replace(evidence_source=eqi, evidence_target=eri, own=False,
                          evidence_points=_keypoint_points(sampled, features, eqi, eri))


def _keypoint_points(prepared: Prepared, features: Features, src: np.ndarray, dst: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """The world points and frames of correspondences (keypoint positions src, dst)."""
  (s, t), ((f_s, _), (f_t, _)) = prepared.sides, features.frames
  return s.points[s.keypoints[src]], t.points[t.keypoints[dst]], f_s[src], f_t[dst]


def hypothesize(prepared: Prepared, features: Features, matches: Matches,
                hypotheses: HypothesisOptions) -> Hypotheses | None:
  """Stage "hypotheses": poses from the correspondences (`pose_hypotheses` of
  `hypotheses.estimator`), their inlier counts at inlier_mr mr, and the evidence set (the
  default matching's, with the compatibility graph's hypotheses) with its chance level. None: no
  hypothesis could be built."""
  threshold = float(hypotheses.inlier_mr * prepared.mr)
  iterations, radius, seed = int(hypotheses.iterations), prepared.radius, prepared.seed
  p, q, f_p, f_q = _keypoint_points(prepared, features, matches.source, matches.target)
  src, dst, cs, cd = centred(p, q)
  rs, ts = pose_hypotheses(src, dst, f_p, f_q, hypotheses.estimator, iterations, radius, seed,
                           threshold)
  if len(rs) == 0:
    return None
  counts = host.count_inliers(rs, ts, src, dst, threshold)
  if matches.own:
    ev = EvidenceSet(src, dst, cs, cd, f_p, f_q, rs, ts)
    chance = chance_inliers(src, dst, f_p, f_q, "graph", iterations, radius, seed, threshold)
  else:
    world = matches.evidence_points
    if world is None:
      world = _keypoint_points(prepared, features, matches.evidence_source,
                               matches.evidence_target)
    ev, chance = evidence_set(*world, iterations, radius, seed, threshold)
  return Hypotheses(src, dst, cs, cd, rs, ts, counts, ev, chance)


def verify(prepared: Prepared, hyps: Hypotheses, hypotheses: HypothesisOptions, icp_mr: float,
           own: bool) -> Verified:
  """Stage "verification": the winner (the most inliers for "graph"; the best overlap within
  `icp_mr` mr among the `hypotheses.verify` best-scoring hypotheses for "lrf" and "3point"),
  refitted by Kabsch on its inliers, its inliers among the evidence correspondences and the best
  rival's (`_rivals`)."""
  overlap_distance = icp_mr * prepared.mr
  target_grid = engine.Grid(prepared.sides[1].points, overlap_distance)
  best, fits = _rerank(hyps, prepared.sides[0].points, target_grid, overlap_distance,
                       0 if hypotheses.estimator == "graph" else hypotheses.verify, prepared.rng)
  return _refitted(prepared, hyps, (hyps.rotations[best], hyps.translations[best]), best,
                   hyps.counts[best], fits, hypotheses, target_grid, overlap_distance, own)


def verify_near(prepared: Prepared, hyps: Hypotheses, transform: np.ndarray,
                hypotheses: HypothesisOptions, icp_mr: float, own: bool) -> Verified:
  """`verify` among the poses near one found elsewhere (`register(..., init=T)`: `T` refined):
  the hypothesis with the most inliers among those not `evidence.distinct` from `transform`
  (measured as rivals are, at the evidence correspondences' source centroid), or `transform`
  itself where it explains more of the correspondences, refitted by Kabsch on its inliers as
  `verify` refits its winner, with that refit's evidence inliers and rivals. The pipeline then
  refines and judges it as it does its winner (ICP from the refit; the "moved" test compares
  ICP's pose with it): the pose `register` would have found had its search been limited to the
  neighbourhood of `transform` (`Verified.coarse.best_hypothesis` is -1 where `transform` itself
  won)."""
  threshold = float(hypotheses.inlier_mr * prepared.mr)
  overlap_distance = icp_mr * prepared.mr
  target_grid = engine.Grid(prepared.sides[1].points, overlap_distance)
  r = np.asarray(transform[:3, :3], np.float64)
  t = np.asarray(transform[:3, 3], np.float64) - hyps.cd + r @ hyps.cs  # centred coordinates
  best, start, count = -1, (r, t), int(np.sum(host.inlier_mask(r, t, hyps.src, hyps.dst,
                                                                threshold)))
  rs = np.asarray(hyps.rotations, np.float64)
  if len(rs):
    point = hyps.evidence.cs - hyps.cs  # where `poses_apart` measures, in centred coordinates
    near = ~distinct_from(rs, hyps.translations, r, t, prepared.radius, point)
    counts = np.where(near, np.asarray(hyps.counts), -1)
    if counts.max() > count:
      best = int(np.argmax(counts))
      start, count = (rs[best], np.asarray(hyps.translations[best], np.float64)), int(counts[best])
  return _refitted(prepared, hyps, start, best, count, np.zeros(0), hypotheses, target_grid,
                   overlap_distance, own)


def _refitted(prepared: Prepared, hyps: Hypotheses, pose: tuple, best: int, count: int,
              fits: np.ndarray, hypotheses: HypothesisOptions, target_grid: engine.Grid,
              overlap_distance: float, own: bool) -> Verified:
  """A centred pose (r, t) refitted by Kabsch on its inliers (`host.select_and_refine`), its
  evidence inliers and rivals (`_rivals`): `verify`'s and `verify_near`'s `Verified`."""
  threshold = float(hypotheses.inlier_mr * prepared.mr)
  r, t, mask = host.select_and_refine(pose[0], pose[1], hyps.src, hyps.dst, threshold)
  coarse = finish_result(*uncentre(r, t, hyps.cs, hyps.cd), mask, best, count)
  ev_mask, rival = _rivals(prepared, hyps, (r, t, mask), own, threshold,
                           int(hypotheses.iterations), target_grid, overlap_distance)
  return Verified(coarse, fits, ev_mask, rival, target_grid, overlap_distance)


def judge_pose(prepared: Prepared, hyps: Hypotheses, transform: np.ndarray,
               hypotheses: HypothesisOptions, icp_mr: float, own: bool
               ) -> tuple[np.ndarray, np.ndarray, int]:
  """The evidence of a pose found elsewhere (`register(..., init=T)` after ICP): its inliers
  among the correspondences (`hyps.src`, `hyps.dst`) and among the evidence correspondences,
  counted at the pose itself, and its rivals (`_rivals`). Not refitted on its inliers, as
  `verify` refits its winner (a hypothesis of the correspondences): a pose turned away from
  the truth has a few true correspondences near its turn's axis, and a refit on them lands on
  the truth with all of its support, which would then be counted for the pose turned. Returns
  (inlier mask, evidence inlier mask, rival inliers)."""
  threshold = float(hypotheses.inlier_mr * prepared.mr)
  overlap_distance = icp_mr * prepared.mr
  target_grid = engine.Grid(prepared.sides[1].points, overlap_distance)
  r = np.asarray(transform[:3, :3], np.float64)
  t = np.asarray(transform[:3, 3], np.float64) - hyps.cd + r @ hyps.cs  # centred coordinates
  mask = host.inlier_mask(r, t, hyps.src, hyps.dst, threshold)
  ev_mask, rival = _rivals(prepared, hyps, (r, t, mask), own, threshold,
                           int(hypotheses.iterations), target_grid, overlap_distance)
  return mask, ev_mask, rival


def _rerank(hyps: Hypotheses, src_pts: np.ndarray, target_grid: engine.Grid, distance: float,
            verify: int | None, rng: np.random.Generator) -> tuple[int, np.ndarray]:
  """The hypothesis of best overlap among the `verify` best-scoring ones (None: all; 0: the
  inlier count alone decides), and the overlaps."""
  order = np.argsort(-hyps.counts, kind="stable")
  best = int(order[0])
  fits = np.zeros(0)
  if verify is None or verify > 0:
    cand = order if verify is None else order[:int(verify)]
    sub = src_pts[np.sort(rng.choice(len(src_pts), min(1000, len(src_pts)), replace=False))]
    r_c = np.asarray(hyps.rotations, np.float64)[cand]
    t_c = (np.asarray(hyps.translations, np.float64)[cand] + hyps.cd
           - np.einsum("hij,j->hi", r_c, hyps.cs))
    fits = overlap_scores(r_c, t_c, sub, target_grid, distance)
    best = int(cand[int(np.argmax(fits))])  # first maximum: the higher inlier count
  return best, fits


def _rivals(prepared: Prepared, hyps: Hypotheses, winner: tuple, own: bool, threshold: float,
            iterations: int, target_grid: engine.Grid, overlap_distance: float
            ) -> tuple[np.ndarray, int]:
  """The winner (its centred (r, t) and inlier mask) in the evidence's centred coordinates, its
  inliers there, and its rivals: the evidence's graph hypotheses, those of the correspondences
  outside the winner's inliers (`rest_hypotheses`), and the estimator's own. Returns (evidence
  inlier mask, rival inliers)."""
  r, t, mask = winner
  ev, rs, ts, cs, cd = hyps.evidence, hyps.rotations, hyps.translations, hyps.cs, hyps.cd
  radius, seed = prepared.radius, prepared.seed
  r_w, t_w = uncentre(r, t, cs, cd)
  t_e = t_w - ev.cd + r_w @ ev.cs
  ev_mask = mask if own else host.inlier_mask(r_w, t_e, ev.src, ev.dst, threshold)
  pool_r, pool_t = [ev.rs], [ev.ts]
  if not own:
    pool_r.append(np.asarray(rs, np.float64))
    pool_t.append(np.asarray(ts, np.float64) + (cd - ev.cd)
                  - np.einsum("hij,j->hi", np.asarray(rs, np.float64), cs - ev.cs))
  rival = rival_inliers(np.concatenate(pool_r), np.concatenate(pool_t), ev.src, ev.dst,
                        threshold, r_w, t_e, ev_mask, radius)
  near = host.inlier_mask(r_w, t_e, ev.src, ev.dst, REST_FACTOR * threshold)
  rest_r, rest_t = rest_hypotheses(ev, near, iterations, radius, seed, threshold)
  rival = rest_rival(rest_r, rest_t, ev, threshold, r_w, t_e, near, radius, rival,
                     prepared.sides[0].points, target_grid, overlap_distance, seed,
                     int(np.sum(ev_mask)))
  return ev_mask, rival
