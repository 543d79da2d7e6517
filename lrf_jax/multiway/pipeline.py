"""Many scans into one model: pairwise LRF registration over a candidate graph, a robust pose
graph, optional joint ICP; `register_all(scans) -> MultiwayResult`.

Pipeline (every length in mr, the median over the scans of each one's working resolution as
`register` measures it, `median_mr`, unless `mr` is given):

1. candidates (`candidate_pairs`): all pairs when there are at most `all_pairs_max` scans;
   otherwise each scan with the next one in the given order (`neighbors` of them) plus, as
   loop-closure candidates, the `loop_candidates` scans whose D2 shape distribution (the
   histogram of distances between random point pairs, `shape_signature`, invariant to rigid
   motion) is closest to its own (L1 distance of the histograms).
2. pairwise: each scan of a candidate pair is described once a pass (`scan_features.describe_scan`:
   keypoints, LRFs, descriptors at the one mr of the set) and each candidate (i < j) registered
   from the two scans' features (`scan_features.register_scans`: `register`'s later stages and
   verdict), as tasks on an engine (`lrf_jax.multiway.tasks`: this process or a Ray cluster), each
   finished pair recorded in `state_dir` when one is given. Its verdict decides how far an edge is trusted: `success` edges are trusted, "not sure"
   edges are weak (kept as candidates: on real scans many right poses are "not sure" at low
   overlap, and most wrong ones are too), and a pair that could not be registered at all gives
   no edge. Every edge carries `tasks.EDGE_POINTS` points of scan i where the two scans overlap
   (farthest-point sample of the source points within `icp_mr` mr of the target after the
   pairwise transform).
3. pose graph (`lrf_jax.multiway.pose_graph.solve`): trusted edges start it (the spanning tree that
   explains most edges, then `scipy.optimize.least_squares` with a Cauchy loss of scale
   `robust_mr` over SE(3), then every edge whose RMS point residual exceeds `reject_mr` is
   rejected and the rest re-solved); weak edges join only where the graph corroborates them:
   inside a component, when they agree with it; between two components, when at least two of
   them agree on one placement through independent routes: distinct scans at both ends, each
   side's ends placed with confidence (linked by trusted edges), so that every pair closes a
   cycle with two trusted legs. A wrong loop closure the verdict let through contradicts the
   cycles it closes and is rejected; a single weak edge, or weak edges that share a scan (two
   unverified edges confirming each other), never join a scan. A scan placed only through weak
   edges is flagged (`MultiwayResult.placed_not_sure`, edges.tsv's `placement`).
   With `effort="normal"` (the default) the "not sure" pairs whose scans this graph leaves in
   different components are then registered again as `effort="high"` registers them
   (`_escalated`: their scans described once more with the pooled seeds) and the graph solved
   again, so a set the first graph joins pays nothing more; `"fast"` is the first pass alone,
   `"high"` the pooled seeds for every pair (never `register`'s pass at twice the working
   resolution: the set's resolution is given). A custom `pairwise` function runs once per pair
   (no second pass).
4. the model is the largest connected component of accepted edges (ties: the one with the
   earliest scan); its earliest scan is the reference frame (the first scan unless the first
   scan is left out). Scans outside it are left out: they get no pose (NaN) and are listed in
   `MultiwayResult.left_out`; nothing of them is merged.
5. optional joint ICP (`refine_poses`, default on): point-to-plane residuals of every
   accepted pair in both directions (pairs re-found each round within `icp_mr` mr, Cauchy loss
   of scale `robust_mr`), all poses of the model at once in one `least_squares` per round.

The same scans, options and seed give the same poses.
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any
from collections.abc import Callable, Sequence

import numpy as np

from lrf_jax.checks import validate_viewpoint
from lrf_jax.geometry.cloud import CheckedCloud, as_cloud
from lrf_jax.geometry.resolution import registration_resolution
from lrf_jax.multiway import pose_graph, tasks
from lrf_jax.multiway.candidates import candidate_pairs
from lrf_jax.multiway.joint_icp import refine_poses
from lrf_jax.multiway.outputs import check_names, scan_names
from lrf_jax.multiway.result import MultiwayEdge, MultiwayResult
from lrf_jax.multiway.options import REJECT_MR, MultiwayOptions, check_counts, resolve
from lrf_jax.registration import options as register_options
from lrf_jax.registration.effort import tried

__all__ = ["REJECT_MR", "MultiwayOptions", "check_counts", "load_scans", "median_mr",
           "register_all"]


def load_scans(scans: Sequence[Any], names: Sequence[str]) -> list[CheckedCloud]:
  """Each scan (a path, array, `Cloud` or object with `.points`) as a `CheckedCloud` (checked
  once here: every pair it is in takes it as it is); a bad scan raises ValueError naming its
  path (or its name), FileNotFoundError for a missing path."""
  out = []
  for scan, name in zip(scans, names):
    label = str(scan) if isinstance(scan, (str, os.PathLike)) else name
    try:
      c = as_cloud(scan, label)
    except ValueError as e:
      raise ValueError(e if label in str(e) else f"{label}: {e}") from None
    if len(c.points) < 10:
      raise ValueError(f"{label}: expected a cloud of at least 10 points, got {len(c.points)}")
    out.append(c)
  return out


def _viewpoints(viewpoints: Any, n: int) -> list[Any]:
  if viewpoints is None:
    return [None] * n
  arr = np.asarray(viewpoints, dtype=object if isinstance(viewpoints, (list, tuple)) and any(
      v is None for v in viewpoints) else np.float64)
  if arr.dtype != object and arr.shape == (3,):
    return [validate_viewpoint(np.asarray(viewpoints, np.float64), "viewpoints")] * n
  if len(viewpoints) != n:
    raise ValueError(f"viewpoints: expected None, one (3,) sensor position or one per scan "
                     f"({n}), got {len(viewpoints)}")
  return [validate_viewpoint(v, f"viewpoints[{k}]") for k, v in enumerate(viewpoints)]


def _pairwise(clouds, names, pairs, *, mr, options, viewpoints, pairwise, progress, params,
              register_kw, engine, state_dir, hashes
              ) -> tuple[list[dict[str, Any]], dict[str, int]]:
  """Stage "pairwise": one registration per candidate pair; its edge records (`tasks.edge_record`)
  and the work done (scans described, pairs registered, pairs read from the state folder)."""
  seed, icp_mr = options.pairs.inputs.seed, options.pairs.icp.icp_mr
  if pairwise is None:
    return _run_pairs(clouds, names, pairs, options.pairs.with_overrides(mr=float(mr)), mr=mr,
                      viewpoints=viewpoints, hashes=hashes, params=params, engine=engine,
                      state_dir=state_dir, progress=progress)
  recs = [_custom_pair(pairwise, clouds, i, j, mr=mr, seed=seed, viewpoints=viewpoints,
                       icp_mr=icp_mr, register_kw=register_kw,
                       overlap_seed=tasks.overlap_seed(seed, hashes[i], hashes[j]))
          for i, j in pairs]
  return recs, dict(scans_described=0, pairs_registered=len(pairs), pairs_resumed=0)


def _run_pairs(clouds, names, pairs, opts, *, mr, viewpoints, hashes, params, engine, state_dir,
               progress) -> tuple[list[dict[str, Any]], dict[str, int]]:
  """`tasks.run_pairs` at the pair options `opts` (their `mr` the set's), its records kept in
  `state_dir` under those options."""
  distance = opts.icp.icp_mr * mr
  records = tasks.PairRecords(state_dir, hashes, opts, mr, distance, params)
  return tasks.run_pairs(clouds, names, pairs, options=opts, mr=mr, viewpoints=viewpoints,
                         distance=distance, params=params, engine=engine, records=records,
                         progress=progress)


def _edges(recs: Sequence[dict[str, Any]]) -> tuple[list[MultiwayEdge], list[np.ndarray]]:
  """The edges of edge records and their overlap points."""
  edges = [MultiwayEdge(r["i"], r["j"], np.full((4, 4), np.nan) if r["transform"] is None
                        else np.asarray(r["transform"], np.float64), r["verdict"], r["reason"],
                        int(r["n_inliers"]), float(r["overlap"]),
                        float("inf") if r["rmse"] is None else float(r["rmse"]), float("inf"),
                        False, r["reason_code"]) for r in recs]
  points = [np.asarray(r["points"], np.float64).reshape(-1, 3) for r in recs]
  return edges, points


def _escalated(recs, work, component, clouds, names, *, opts, mr, viewpoints, hashes, params,
               engine, state_dir, progress) -> tuple[list[dict[str, Any]], dict[str, int]]:
  """`effort="normal"`'s second pass: the "not sure" pairs (and those with no hypothesis, which
  `register` calls "not sure" and an edge record an error) whose scans lie in different
  components of the first pose graph (`component`, a label per scan: the graph has joined
  what its trusted and corroborated weak edges allow), registered again as `effort="high"`
  registers them (each of their scans described once more with the pooled seeds); their
  records replace the first pass's, `reason` saying what was tried (a pooled pass that fails
  leaves the first record). A set the first graph joins costs nothing more; a scan it leaves
  out costs its pairs."""
  todo = [k for k, r in enumerate(recs)
          if (r["verdict"] == "not sure" or r["reason_code"] == "no_hypothesis")
          and component[r["i"]] != component[r["j"]]]
  if not todo:
    return recs, work
  again, more = _run_pairs(clouds, names, [(recs[k]["i"], recs[k]["j"]) for k in todo],
                           opts.with_overrides(effort="high"), mr=mr, viewpoints=viewpoints,
                           hashes=hashes, params=params, engine=engine, state_dir=state_dir,
                           progress=progress)
  out = list(recs)
  for k, rec in zip(todo, again):
    if rec["verdict"] == "error":  # the pooled pass failed: the first pass's record stands
      continue
    out[k] = dict(rec, reason=f"{rec['reason']} ({tried(recs[k]['reason_code'])})")
  return out, {key: work[key] + more[key] for key in work}


def _custom_pair(pairwise, clouds, i, j, *, mr, seed, viewpoints, icp_mr, register_kw,
                 overlap_seed) -> dict[str, Any]:
  """A pair registered by a user's `pairwise` function, as an edge record."""
  reg, error = None, None
  try:
    reg = pairwise(clouds[i], clouds[j], mr=mr, seed=seed, source_viewpoint=viewpoints[i],
                   target_viewpoint=viewpoints[j], **register_kw)
  except ValueError as e:
    error = str(e)
  return tasks.edge_record(i, j, reg, error, clouds[i].points, clouds[j].points, icp_mr * mr,
                           overlap_seed)


def _graph(n, edges, points, *, mr, reject_mr, robust_mr, seed):
  """Stage "graph": the pose graph over the edges with overlap points; (poses, accepted (E,),
  errors (E,) in mr, component (n,))."""
  usable = [k for k, (e, p) in enumerate(zip(edges, points)) if e.verdict != "error" and len(p)]
  pg_edges = [pose_graph.PoseEdge(edges[k].i, edges[k].j, edges[k].transform, points[k],
                                  float(edges[k].n_inliers)) for k in usable]
  trusted = [edges[k].verdict == "success" for k in usable]
  accepted = np.zeros(len(edges), bool)
  errors = np.full(len(edges), np.inf)
  if not pg_edges:
    return np.tile(np.eye(4), (n, 1, 1)), accepted, errors, np.arange(n)
  res = pose_graph.solve(n, pg_edges, trusted=trusted, scale=mr, threshold=reject_mr,
                         robust=robust_mr, seed=seed)
  accepted[usable] = res.accepted
  errors[usable] = res.errors
  return res.poses, accepted, errors, res.component


def _model(component: np.ndarray) -> int:
  """The label of the largest component (ties: the lowest label, i.e. the earliest scan)."""
  labels, counts = np.unique(component, return_counts=True)
  return int(labels[np.argmax(counts)])  # np.unique sorts, argmax takes the first maximum


def register_all(scans: Sequence[Any], options: MultiwayOptions | None = None, *,
                 names: Sequence[str] | None = None, viewpoints: Any = None,
                 progress: bool = False, pairwise: Callable[..., Any] | None = None,
                 engine: Any = None, state_dir: str | os.PathLike | None = None,
                 params: Any = None, **overrides: Any) -> MultiwayResult:
  """Register many scans of one object or scene into one frame (module docstring).

  Args:
    scans: n >= 2 scans: paths of any cloud/mesh `lrf_jax.io` reads, (m, 3) arrays, `Cloud`s or
      objects with `.points`, each in its own frame.
    options: a `MultiwayOptions` (None: `lrf_jax.multiway.options.DEFAULTS`, every default
      below).
    names: n distinct names for the result and the outputs, each usable as a file name
      (`check_names`; default `scan_names(scans)`).
    viewpoints: None, one (3,) sensor position used for every scan (in each scan's own frame),
      or n of them (None entries allowed); passed to `register`.
    progress: show a tqdm progress bar over the pairs (stderr).
    pairwise: the pairwise registration (default: `register`'s stages on features described
      once per scan, `lrf_jax.registration.scan_features`): called as
      `pairwise(source_cloud, target_cloud, mr=, seed=, source_viewpoint=, target_viewpoint=,
      **kw)` where kw holds the pair options given as keywords or differing from the defaults
      (and `voxel_size` where not None, `params` where given), returning an object with
      `transform`, `success`, `reason`, `n_inliers`, `overlap`, `rmse` (and optionally
      `estimated`); a ValueError, or `estimated` False, marks the pair "error" (no edge).
    engine: where the pairwise stage runs: None (this process) or an engine of
      `lrf_jax.batch` (`lrf_jax.batch.make_engine("ray", address)`): each scan of a pair to
      register is described once a pass (the default's second pass describes the scans of
      the pairs it registers again) and every pair registered as a task
      (`lrf_jax.multiway.tasks`); the result does not depend on the engine.
    state_dir: a folder kept between runs (None: none): every registered pair leaves a record
      there, and a run with the same scans, options and resolution registers only the pairs
      without one (a killed job loses no finished pair; a finished one redoes nothing).
    params: learned LRF parameters of every pair (None: the method's shipped weights).
    **overrides: fields of `MultiwayOptions` replacing those of `options`: every field of
      `RegisterOptions` but the viewpoints (e.g. `n_keypoints`, `radius_mr`, `method`), passed
      to every pairwise registration, and those listed below (the tables of options are in
      the docs' Pipeline stages pages).

  Keyword Args:
    mr (float | None): mesh resolution in the clouds' units (None: the median of the scans' working
      resolutions as `register` measures them, `median_mr`).
    all_pairs_max (int): up to this many scans every pair is registered (`candidate_pairs`).
    neighbors (int): otherwise, pairs with this many next scans in the given order...
    loop_candidates (int): ...plus this many loop-closure candidates per scan (D2 signature).
    reject_mr (float): an edge whose RMS point residual under the optimised poses exceeds this (mr)
      is rejected.
    robust_mr (float): scale of the Cauchy loss of the pose graph and the joint ICP, in mr.
    refine (bool): run the joint ICP (`refine_poses`) after the pose graph.
    refine_iterations (int): its rounds at most.
    icp_mr (float): overlap and ICP pairing distance, in mr.
    seed (int): seed of the pairwise registrations, the samples and the pose graph's start.
    voxel_size (float | None): passed to every pairwise `register`: None thins a scan far
      denser than mr as `register` chooses, 0 keeps every point, a positive edge (cloud units)
      thins every scan by voxel averaging at it. The pose graph, the joint ICP and the outputs
      use the scans' own points.

  Returns:
    `MultiwayResult`: poses into the reference scan's frame, the edges with their verdicts,
    residuals and whether the graph accepted them, the scans left out.

  Raises:
    TypeError: an override that is not an option of `register_all`.
    ValueError: fewer than 2 scans, an unreadable or malformed scan (the message names it),
      a custom `pairwise` with an engine or a state folder,
      `names` of the wrong length or a name `check_names` refuses, a non-positive mr or
      distance.
    FileNotFoundError: a path that does not exist.

  Example:
    >>> res = lrf_jax.register_all(["bun000.ply", "bun045.ply", "bun090.ply"])
    >>> res.poses[1]   # maps bun045 into bun000's frame
  """
  t0 = time.perf_counter()
  timings = {}
  if len(scans) < 2:
    raise ValueError(f"scans: expected at least 2 scans, got {len(scans)}")
  names = scan_names(scans) if names is None else check_names(names, "names")
  if len(names) != len(scans):
    raise ValueError(f"names: expected {len(scans)} names, got {len(names)}")
  opts = resolve(options, overrides)  # every option checked before any pair is registered
  graph, inputs = opts.graph, opts.pairs.inputs
  mr, seed, icp_mr = inputs.mr, inputs.seed, opts.pairs.icp.icp_mr
  views = _viewpoints(viewpoints, len(scans))
  if pairwise is not None and (engine is not None or state_dir is not None):
    raise ValueError("pairwise: a custom pairwise registration runs in this process and keeps "
                     "no records; pass engine=None and state_dir=None with it")
  register_kw = _custom_keywords(opts, overrides, params)
  clouds = load_scans(scans, names)
  n = len(clouds)
  if mr is None:
    mr = median_mr(clouds, names)
  elif not (np.isfinite(mr) and mr > 0):
    raise ValueError(f"mr: expected a positive mesh resolution, got {mr!r}")
  timings["load"] = time.perf_counter() - t0
  pairs = candidate_pairs([c.points for c in clouds], all_pairs_max=graph.all_pairs_max,
                          neighbors=graph.neighbors, loop_candidates=graph.loop_candidates,
                          seed=seed)
  t = time.perf_counter()
  hashes = [tasks.scan_hash(c, v) for c, v in zip(clouds, views)]
  recs, work = _pairwise(clouds, names, pairs, mr=mr, options=opts, viewpoints=views,
                         pairwise=pairwise, progress=progress, params=params,
                         register_kw=register_kw, engine=engine, state_dir=state_dir,
                         hashes=hashes)
  edges, points = _edges(recs)
  timings["pairwise"] = time.perf_counter() - t
  t = time.perf_counter()
  graphed = dict(mr=mr, reject_mr=graph.reject_mr, robust_mr=graph.robust_mr, seed=seed)
  poses, accepted, errors, component = _graph(n, edges, points, **graphed)
  timings["graph"] = time.perf_counter() - t
  if pairwise is None and opts.pairs.verdict.effort == "normal":
    t = time.perf_counter()
    again, work = _escalated(recs, work, component, clouds, names,
                             opts=opts.pairs.with_overrides(mr=float(mr)), mr=mr,
                             viewpoints=views, hashes=hashes, params=params, engine=engine,
                             state_dir=state_dir, progress=progress)
    timings["pairwise"] += time.perf_counter() - t
    if again is not recs:
      edges, points = _edges(again)
      t = time.perf_counter()
      poses, accepted, errors, component = _graph(n, edges, points, **graphed)
      timings["graph"] += time.perf_counter() - t
  t = time.perf_counter()
  reference = _model(component)
  in_model = component == reference
  sure = pose_graph.components(n, [(e.i, e.j) for e, a in zip(edges, accepted)
                                   if a and e.verdict == "success"])
  confident = in_model & (sure == sure[reference])
  timings["graph"] += time.perf_counter() - t
  t = time.perf_counter()
  kept = [(e.i, e.j) for e, a in zip(edges, accepted) if a and in_model[e.i]]
  if graph.refine and kept:
    poses = refine_poses([c.points for c in clouds], poses, kept, reference=reference, mr=mr,
                         icp_mr=icp_mr, robust_mr=graph.robust_mr,
                         iterations=graph.refine_iterations, seed=seed)
  timings["refine"] = time.perf_counter() - t
  poses = np.where(in_model[:, None, None], poses, np.nan)
  final = []
  for e, a, p in zip(edges, accepted, points):
    res = float("inf")
    if in_model[e.i] and in_model[e.j] and len(p):
      edge = pose_graph.PoseEdge(e.i, e.j, e.transform, p)
      res = float(pose_graph.edge_errors(poses, [edge], mr)[0])
    final.append(dataclasses.replace(e, accepted=bool(a), residual_mr=res))
  return MultiwayResult(names=tuple(names), poses=poses, in_model=in_model,
                        reference=reference, edges=tuple(final), mr=float(mr),
                        seconds=time.perf_counter() - t0, timings=timings,
                        confident=confident, work=work)


def _custom_keywords(options: MultiwayOptions, overrides: dict[str, Any], params: Any
                     ) -> dict[str, Any]:
  """The keywords a custom `pairwise` receives besides mr, seed and the viewpoints: the pair
  options given as `overrides` or differing from `register`'s defaults (`voxel_size` only where
  not None, `register`'s own choice), and `params` where given."""
  defaults = register_options.DEFAULTS.as_dict()
  own = ("mr", "seed", "icp_mr", "voxel_size")
  out = {k: v for k, v in options.pairs.as_dict().items()
         if k not in own and (k in overrides or v != defaults[k])}
  if options.pairs.inputs.voxel_size is not None:
    out["voxel_size"] = options.pairs.inputs.voxel_size
  if params is not None:
    out["params"] = params
  return out


def median_mr(clouds: Sequence[CheckedCloud], names: Sequence[str]) -> float:
  """`register_all`'s mr when none is given: the median of the scans' working resolutions
  (`registration_resolution`: a clean scan's mean spacing, a raw sweep's area-weighted one, a
  full-density fragment's fraction of its extent)."""
  return float(np.median([registration_resolution(c.points, c.faces, name=f"scan {name}").mr
                          for name, c in zip(names, clouds)]))


