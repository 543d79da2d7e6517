"""6-DoF pose estimation (paper section 3.2.3, table `tabel_pose`): one-correspondence LRF RANSAC
(100 iterations) vs classic 3-point RANSAC (1000 iterations).

Protocol per model/scene pair:

* keypoints: the repeatability protocol's seeded model points and their ground-truth scene
  correspondences (1000 per pair, `repeatability.correspondences`);
* LRF-Net frames (r = 15 mr) and TOLDI descriptors on them, on both sides;
* each model descriptor matched to its nearest scene descriptor; the 100 matches of smallest
  ratio d1/d2 are the correspondences (the paper: "keeping 100 correspondences with the highest
  similarity scores");
* both estimators on the same correspondences with the same inlier threshold (`inlier_mr` mr),
  score (inlier count) and final refit, same seed (`registration.lrf_ransac`,
  `registration.ransac_3point`); the frames of the LRF variant are the LRF-Net frames of the
  matched keypoints;
* err_r (degrees) and err_t (mr) against the ground truth model -> scene (eqs. `eq_err_r`,
  `eq_err_t`).

Records also carry how many of the 100 correspondences are correct (within `inlier_mr` mr under
the ground truth) and the estimator's time (a second, compiled call).
"""

from __future__ import annotations

import time
from typing import Any
from collections.abc import Iterable, Iterator

import numpy as np

from lrf_jax.defaults import RADIUS_MR
from lrf_jax.frames.patch_frames import frames_from_patches
from lrf_jax.datasets import Pair, transform_points
from lrf_jax.descriptors import (DESCRIPTORS, describe_patches, match_descriptors,
                                 top_correspondences)
from lrf_jax.evaluation.repeatability import (PatchCache, correspondences, group_records,
                                              paper_options)
from lrf_jax.frames import METHODS
from lrf_jax.geometry.normals import default_normals
from lrf_jax.frames.normals_rule import prepare_extra
from lrf_jax.registration import lrf_ransac, pose_errors, ransac_3point

# The paper's table `tabel_pose` (err_t in mr, err_r in degrees).
PAPER_POSE = {
    "RANSAC": {"BR": (0.000, 0.030), "UWA3M": (7.929, 0.696), "UWAOR": (9.513, 0.769)},
    "LRF-Net": {"BR": (0.000, 0.024), "UWA3M": (6.088, 0.608), "UWAOR": (4.392, 0.405)},
}
SUCCESS_DEG = 5.0
SUCCESS_MR = 10.0


# The estimators compared on every pair, in the order of its records.
ESTIMATORS = ("lrf_ransac", "ransac_3point")

def evaluate_pose_pair(pair: Pair, *, n_keypoints: int = 1000, n_correspondences: int = 100,
                       lrf_iterations: int = 100, ransac_iterations: int = 1000,
                       inlier_mr: float = 5.0, seed: int = 0, radius_mr: float = RADIUS_MR,
                       params: Any = None, descriptor: str = "toldi", lrf: str = "lrf_net",
                       cache: PatchCache | None = None,
                       setting: dict[str, Any] | None = None) -> list[dict[str, Any]]:
  """Pose errors of the two estimators on one pair.

  Args:
    pair: model-scene pair (transform = model -> scene).
    n_keypoints: keypoints per pair.
    n_correspondences: correspondences kept (100).
    lrf_iterations: iterations of the one-correspondence estimator (100).
    ransac_iterations: iterations of 3-point RANSAC (1000).
    inlier_mr: inlier threshold of both, in mr.
    seed: keypoint, subsample and RANSAC seed.
    radius_mr: support radius in mr.
    params: LRF-Net parameters (None: the shipped weights).
    descriptor: descriptor used for matching (TOLDI in the paper).
    lrf: LRF method of frames and descriptors (LRF-Net in the paper).
    cache: shared patch cache.
    setting: stored in the records.

  Returns:
    Two records (methods "lrf_ransac", "ransac_3point"): experiment "pose", dataset, pair,
    method, setting (iterations, n_correspondences, inlier_mr, descriptor, lrf), err_r (deg),
    err_t (mr), n_inliers, n_correct_correspondences, n_correspondences, seconds (estimator).
  """
  cache = cache or PatchCache()
  mi, si = correspondences(pair, n_keypoints, seed)
  radius = radius_mr * pair.mr
  spec = METHODS[lrf]
  side = {}
  for tag, pts, faces, idx, vp in (
      ("model", pair.model_points, pair.model_faces, mi, pair.model_viewpoint),
      ("scene", pair.scene_points, pair.scene_faces, si, pair.scene_viewpoint)):
    patches = cache.get(pts, idx, radius, spec.default_k, seed, spec.z_ratio)
    extra = prepare_extra(spec, pts, idx, patches, faces=faces, radius=radius, viewpoint=vp,
                          normals=lambda: default_normals(pts, radius, faces, None, vp))  # noqa: B023 (called in this iteration)
    f, v = frames_from_patches(patches, lrf, params=params if spec.needs_params else None,
                               extra=extra, **dict(paper_options(lrf)))
    dp = cache.get(pts, idx, radius, None, seed, 1.0 / 3.0)
    nrm = default_normals(pts, radius, faces, None, vp) if DESCRIPTORS[descriptor].prepare else None
    d, ok = describe_patches(dp, f, v, descriptor, points=pts, keypoints=idx, radius=radius,
                             faces=faces, normals=nrm)
    side[tag] = (pts[idx], np.asarray(f), np.asarray(v), np.asarray(d), np.asarray(ok))
  (pm, fm, vm, dm, okm), (ps, fs, vs, ds, oks) = side["model"], side["scene"]
  matches = match_descriptors(dm, ds, okm & vm, oks & vs)
  qi, ri = top_correspondences(matches, n_correspondences)
  src, dst = pm[qi], ps[ri]
  thr = inlier_mr * pair.mr
  resid = np.linalg.norm(transform_points(pair.transform, src) - dst, axis=1)
  n_correct = int((resid <= thr).sum())
  base = {"experiment": "pose", "dataset": pair.dataset, "pair": pair.name, "radius": radius,
          "n_correspondences": int(len(qi)), "n_correct_correspondences": n_correct}
  common = {"n_correspondences": n_correspondences, "inlier_mr": inlier_mr,
            "descriptor": descriptor, "lrf": lrf, **(setting or {})}
  estimators = (
      ("lrf_ransac", lrf_iterations,
       lambda: lrf_ransac(src, dst, fm[qi], fs[ri], inlier_threshold=thr, scale=radius,
                          iterations=lrf_iterations, seed=seed)),
      ("ransac_3point", ransac_iterations,
       lambda: ransac_3point(src, dst, inlier_threshold=thr, iterations=ransac_iterations,
                             seed=seed)),
  )
  records = []
  for name, iters, run in estimators:
    rec = dict(base, method=name, setting=dict(common, iterations=iters))
    if len(qi) < 3:
      records.append(dict(rec, err_r=None, err_t=None, n_inliers=0,
                          note=f"only {len(qi)} correspondences"))
      continue
    run()  # compile
    t0 = time.perf_counter()
    res = run()
    seconds = time.perf_counter() - t0
    err_r, err_t = pose_errors(res.transform, pair.transform, pair.mr)
    records.append(dict(rec, err_r=err_r, err_t=err_t, n_inliers=res.n_inliers,
                        seconds=seconds, transform=res.transform.tolist()))
  return records


def run_pose(dataset_names: list[str], opts: Any, cache: PatchCache, *, params: Any = None,
             inlier_mr: float = 5.0) -> Iterator[dict[str, Any]]:
  """Yield the pose records over datasets (names of `evaluation.experiments.DATASETS`).

  Args:
    dataset_names: e.g. ["BR@0.3", "UWA3M", "UWAOR"] (the paper's three).
    opts: `evaluation.EvalOptions` (data_root, n_keypoints, seed, radius_mr, max_pairs).
    cache: shared `PatchCache`.
    params: LRF-Net parameters (None: the shipped weights).
    inlier_mr: inlier threshold of both estimators, in mr.

  Yields:
    Records of `evaluate_pose_pair`, "dataset" set to the dataset name.
  """
  from lrf_jax.evaluation.experiments import iter_pairs
  for ds, setting, pair in iter_pairs(dataset_names, opts):
    for rec in evaluate_pose_pair(pair, n_keypoints=opts.n_keypoints, seed=opts.seed,
                                  radius_mr=opts.radius_mr, params=params,
                                  inlier_mr=inlier_mr, cache=cache, setting=setting):
      rec["dataset"] = ds
      yield rec


def summarise_pose(records: Iterable[dict[str, Any]]) -> dict[tuple, dict[str, Any]]:
  """{(dataset, method): {"err_r_mean", "err_t_mean", "err_r_median", "err_t_median", "success",
  "n_pairs", "seconds"}}; success = err_r <= 5 deg and err_t <= 10 mr."""
  groups = group_records(records, "pose")
  out = {}
  for key, rs in groups.items():
    ok = [r for r in rs if r.get("err_r") is not None]
    er = np.array([r["err_r"] for r in ok])
    et = np.array([r["err_t"] for r in ok])
    out[key] = {
        "n_pairs": len(rs),
        "err_r_mean": float(er.mean()) if ok else None,
        "err_t_mean": float(et.mean()) if ok else None,
        "err_r_median": float(np.median(er)) if ok else None,
        "err_t_median": float(np.median(et)) if ok else None,
        "success": float(np.mean((er <= SUCCESS_DEG) & (et <= SUCCESS_MR))) if ok else None,
        "seconds": float(np.mean([r["seconds"] for r in ok])) if ok else None,
        "correct_corr": float(np.mean([r["n_correct_correspondences"] for r in rs])),
    }
  return out


def _paper_key(ds: str) -> str | None:
  base = ds.split("@")[0].split("-")[0]
  return base if base in PAPER_POSE["RANSAC"] else None


def pose_report(records: list[dict[str, Any]]) -> str:
  """Markdown: the paper's pose table beside ours (means, plus medians and success rates)."""
  summary = summarise_pose(records)
  if not summary:
    return ""
  paper_name = {"ransac_3point": "RANSAC", "lrf_ransac": "LRF-Net"}
  lines = ["## pose (6-DoF, 100 TOLDI+LRF-Net correspondences)", "",
           "| dataset | estimator | pairs | err_t mean (mr) | err_r mean (deg) | err_t median | "
           "err_r median | success | correct corr. | time (ms) | paper err_t | paper err_r |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  for (ds, method), v in sorted(summary.items()):
    pk = _paper_key(ds)
    paper = PAPER_POSE[paper_name[method]].get(pk) if pk and method in paper_name else None
    pcells = f"{paper[0]:.3f} | {paper[1]:.3f}" if paper else " | "
    if v["err_r_mean"] is None:
      lines.append(f"| {ds} | {method} | {v['n_pairs']} | n/a | n/a | | | | | | {pcells} |")
      continue
    lines.append(
        f"| {ds} | {method} | {v['n_pairs']} | {v['err_t_mean']:.3f} | {v['err_r_mean']:.3f} | "
        f"{v['err_t_median']:.3f} | {v['err_r_median']:.3f} | {v['success']:.2f} | "
        f"{v['correct_corr']:.1f} | {1e3 * v['seconds']:.1f} | {pcells} |")
  lines += ["", f"lrf_ransac: one correspondence per hypothesis (pose from the two LRF-Net "
            f"frames, 100 iterations); ransac_3point: classic, 1000 iterations; same inlier "
            f"threshold, score and refit. success: err_r <= {SUCCESS_DEG:g} deg and err_t <= "
            f"{SUCCESS_MR:g} mr. correct corr.: mean number of the 100 correspondences within "
            "the inlier threshold under the ground truth.", ""]
  return "\n".join(lines)
