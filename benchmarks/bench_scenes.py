"""Scene and object registration benchmark: `lrf_jax.register` beside Open3D's tutorial pipeline.

    LRF_DATA=/path/to/data python benchmarks/bench_scenes.py [--split tune|test|all]
        [--kinds room,object] [--only NAME-SUBSTRING] [--limit N] [--lrf-kw '{"iterations": 500}']
        [--skip-open3d] [--kiss] [--hints] [--inits] [--turns] [--probe] [--viewpoints]
        [--seed 0]
        [--json OUT.json]

Runs every case of `benchmarks/scene_cases.py` (rooms from 3DMatch, objects from the bunny and
UWA3M scans, each with known truth and an overlap of 10-30 % or > 30 %; split by scene/object
into "tune" and "test") through

* lrf_jax: `lrf_jax.register(source, target, seed=seed, **lrf_kw)`, timed per call (after one
  untimed warm-up call, so JAX compilation is excluded);
* Open3D 0.20's global registration tutorial (`benchmarks/_open3d_pipeline.py`: voxel
  downsampling, normals, FPFH, RANSAC on feature matches with the tutorial's checkers and
  `RANSACConvergenceCriteria(100000, 0.999)`, point-to-plane ICP within 0.4 voxel), timed per
  call, with the same seed. Voxel: 5 cm for rooms (the tutorial's own size, two 3DMatch voxels);
  `OBJECT_VOXEL_MR` = 2.5 mr for objects, which puts Open3D's FPFH radius (5 voxels = 12.5 mr)
  close to lrf_jax's 15 mr support and keeps about 1/6 of the points (a few thousand per scan).
  Open3D has no verdict of its own, so its "claimed" column stays empty.

* with `--kiss`, KISS-Matcher and an ICP after it (`benchmarks/_kiss_matcher_pipeline.py`) at
  Open3D's voxel; its `valid` is counted as its claim.

With `--inits`, every case is registered again from its truth as a benchmark prints it (the
rotation to 3 decimals, `published`), from the truth turned 3 deg and turned 30 deg
(`turned`), and from the truth turned 20 deg held unmoved (`icp_iterations=0`): the truth's
init should be claimed wherever the default claims, the truth's and the 3 deg init should land
within 5 deg and 3 % of the target's extent of the truth (`near_truth`), a turned one never be
claimed at a wrong pose.

With `--turns`, every case is registered again from its truth turned 5, 10, 15, 30, 60 and 120
deg about an axis drawn per case and angle (`run_turns`), ICP on: how many come back right and
are claimed, and that none is claimed at a wrong pose.

With `--probe`, every case is registered again under each option of `PROBE_OPTIONS` (ICP's
reach, iterations and mode, the inlier distance, the support radius, fewer keypoints or
correspondences, another descriptor or frame), and the false claims are listed.

With `--viewpoints`, lrf_jax is given where each scan's sensor stood, where the case knows it
(`viewpoint_kw`: a 3DMatch fragment's origin, its first camera; the bunny's and UWA3M's
scanners), as a user who knows it would pass it: what repeatable frames do to the claims.

With `--hints`, every "not sure" of lrf_jax whose reason names a next step is run again with it,
and the pairs each step then claims (right, wrong) are counted.

Per case: RE (degrees), TE (metres for rooms, mr for objects; the error of where the source's
centroid lands, see `_errors`), true success (rooms: RE < 15 deg
and TE < 30 cm, the 3DMatch registration recall; objects: RE < 5 deg and TE < 10 mr), claimed
success (`reg.success`), `reg.overlap` and `reg.reason` when the Registration has them, wall
time. The output: the split, a Markdown table per case, and a summary per split x kind x
overlap bin with true successes of each method, false successes (claimed but not true) and the
claimed-of-true rate of lrf_jax, median RE/TE of the true successes and median time.
`--json OUT` writes every record (atomically). `run_cases(cases, lrf_kw, open3d=True)` is the
loop, importable by a tuning script.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from collections.abc import Iterable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
  sys.path.insert(0, str(REPO))

import lrf_jax  # noqa: E402
from lrf_jax.registration import pose_errors  # noqa: E402

from benchmarks._kiss_matcher_pipeline import have_kiss_matcher, kiss_registration  # noqa: E402
from benchmarks._open3d_pipeline import global_registration, have_open3d  # noqa: E402
from benchmarks.scene_cases import BINS, Case, make_cases, split_table  # noqa: E402

ROOM_VOXEL_M = 0.05
OBJECT_VOXEL_MR = 2.5
# True success: (RE limit in degrees, TE limit in the case's unit: metres / mr).
SUCCESS = {"room": (15.0, 0.30), "object": (5.0, 10.0)}
METHODS = ("lrf", "open3d", "kiss")


def open3d_voxel(case: Case) -> float:
  """Open3D's voxel size for a case, in cloud units (5 cm for rooms, 2.5 mr for objects)."""
  return ROOM_VOXEL_M if case.kind == "room" else OBJECT_VOXEL_MR * case.spacing


def _errors(case: Case, transform: np.ndarray) -> dict[str, Any]:
  """RE (degrees) and TE (the case's unit) of an estimate, and whether it is a true success.

  TE is the distance between where the estimate and the truth put the source's centroid c,
  |T_est c - T_gt c|: the translation error of both transforms written about c. Unlike the raw
  |t_est - t_gt| it does not grow with the distance of the cloud from its origin (the random
  motion of the cases moves every source by about its own size), and it equals it for a cloud
  centred at its origin.
  """
  about = np.eye(4)
  about[:3, 3] = np.asarray(case.source, np.float64).mean(0)
  re, te = pose_errors(np.asarray(transform, np.float64) @ about, case.gt @ about, case.unit)
  re_max, te_max = SUCCESS[case.kind]
  return {"re": re, "te": te, "true": bool(re < re_max and te < te_max)}


def _failed(error: BaseException, seconds: float) -> dict[str, Any]:
  return {"re": float("nan"), "te": float("nan"), "true": False, "claimed": False,
          "seconds": seconds, "error": f"{type(error).__name__}: {error}"}


def viewpoint_kw(case: Case) -> dict[str, Any]:
  """`register`'s source_viewpoint / target_viewpoint where the case knows where its scans'
  sensors stood (a 3DMatch fragment's first camera, a scan's scanner; moved with the source),
  else none."""
  out = {}
  for side in ("source", "target"):
    v = case.meta.get(f"{side}_viewpoint")
    if v is not None:
      out[f"{side}_viewpoint"] = tuple(float(x) for x in v)
  return out


def run_lrf(case: Case, lrf_kw: dict[str, Any], seed: int = 0, *,
            viewpoints: bool = False) -> dict[str, Any]:
  """One `lrf_jax.register` call on a case: errors, verdict, overlap, reason, time
  (`viewpoints`: with the case's sensor positions, `viewpoint_kw`)."""
  kw = {"seed": seed, **(viewpoint_kw(case) if viewpoints else {}), **lrf_kw}
  t0 = time.perf_counter()
  try:
    reg = lrf_jax.register(case.source, case.target, **kw)
  except Exception as e:  # noqa: BLE001 -- a failing case is a result, not the end of the run
    return _failed(e, time.perf_counter() - t0)
  seconds = time.perf_counter() - t0
  out = _errors(case, reg.transform)
  overlap = getattr(reg, "overlap", None)
  out.update({"claimed": bool(reg.success),
              "overlap": None if overlap is None else float(overlap),
              "reason": str(getattr(reg, "reason", "")), "fitness": float(reg.fitness),
              "n_inliers": int(reg.n_inliers), "seconds": seconds,
              "transform": np.asarray(reg.transform).tolist()})
  return out


def run_open3d(case: Case, seed: int = 0) -> dict[str, Any]:
  """Open3D's tutorial pipeline on a case: errors and time (no verdict: claimed is None)."""
  voxel = open3d_voxel(case)
  t0 = time.perf_counter()
  try:
    res = global_registration(case.source, case.target, voxel=voxel, seed=seed,
                              refine="point_to_plane")
  except Exception as e:  # noqa: BLE001
    return _failed(e, time.perf_counter() - t0) | {"claimed": None}
  out = _errors(case, res["final"])
  out.update({"claimed": None, "overlap": None, "reason": "", "fitness": res["fitness"],
              "seconds": res["seconds"], "voxel": voxel, "n_points": list(res["n_points"]),
              "transform": res["final"].tolist()})
  return out


def run_kiss(case: Case) -> dict[str, Any]:
  """KISS-Matcher and ICP (`_kiss_matcher_pipeline`) at Open3D's voxel: errors, its `valid`
  (counted as its claim) and time."""
  voxel = open3d_voxel(case)
  t0 = time.perf_counter()
  try:
    res = kiss_registration(case.source, case.target, voxel=voxel)
  except Exception as e:  # noqa: BLE001
    return _failed(e, time.perf_counter() - t0)
  out = _errors(case, res["final"])
  out.update({"claimed": res["valid"], "overlap": None, "reason": f"{res['inliers']} inliers",
              "fitness": None, "seconds": res["seconds"], "voxel": voxel,
              "transform": res["final"].tolist()})
  return out


def settled_by_hints(records: list[dict[str, Any]], cases: list[Case], lrf_kw: dict[str, Any],
                     seed: int) -> dict[str, list[int]]:
  """Every lrf "not sure" whose reason names a next step (`effort='normal' or 'high'`,
  `effort='high'`), run again with that step: per step [pairs it was named for, claimed and
  right, claimed and wrong]."""
  steps = {"effort='normal'": {"effort": "normal"}, "effort='high'": {"effort": "high"}}
  out: dict[str, list[int]] = {name: [0, 0, 0] for name in steps}
  by_name = {c.name: c for c in cases}
  for rec in records:
    lrf = rec["lrf"]
    if lrf.get("claimed") or "error" in lrf:
      continue
    for name, kw in steps.items():
      if name in lrf.get("reason", ""):
        again = run_lrf(by_name[rec["case"]], {**lrf_kw, **kw}, seed)
        out[name][0] += 1
        out[name][1] += int(bool(again["claimed"]) and again["true"])
        out[name][2] += int(bool(again["claimed"]) and not again["true"])
  return out


def published(gt: np.ndarray) -> np.ndarray:
  """`gt` as a benchmark prints it: the rotation block to 3 decimals (3DMatch's gt.log is
  0.00046 off orthonormal; this is about 1e-3 off, which `register` projects)."""
  out = np.array(gt, np.float64)
  out[:3, :3] = np.round(out[:3, :3], 3)
  return out


def turned(case: Case, degrees: float) -> np.ndarray:
  """`case.gt` turned by `degrees` about an axis through the target's centroid: a wrong
  init."""
  from scipy.spatial.transform import Rotation
  axis = np.array([0.6, 0.0, 0.8])
  turn = np.eye(4)
  turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix()
  centre = np.asarray(case.target, np.float64).mean(axis=0)
  turn[:3, 3] = centre - turn[:3, :3] @ centre
  return turn @ case.gt


def near_truth(case: Case, transform: Any) -> bool:
  """Whether a pose lies within 5 deg and 3 % of the target's extent (its bounding box's
  diagonal, at the source's centroid) of the truth: where an init of the truth must land."""
  if transform is None:
    return False
  t = np.asarray(transform, np.float64)
  centre = np.asarray(case.source, np.float64).mean(axis=0)
  moved = t[:3, :3] @ centre + t[:3, 3] - (case.gt[:3, :3] @ centre + case.gt[:3, 3])
  extent = float(np.linalg.norm(np.ptp(np.asarray(case.target, np.float64), axis=0)))
  from lrf_jax.registration.errors import rotation_error_deg
  return bool(rotation_error_deg(t[:3, :3], case.gt[:3, :3]) < 5.0
              and np.linalg.norm(moved) < 0.03 * extent)


def run_inits(records: list[dict[str, Any]], cases: list[Case], lrf_kw: dict[str, Any],
              seed: int) -> dict[str, int]:
  """`register(..., init=)` on every case with the published truth (`published`), the truth
  turned 3 deg and turned 30 deg (`turned`), and the truth turned 20 deg held unmoved
  (`icp_iterations=0`): how many pairs the default claims the truth's init claims too, how many
  of the truth's and the 3 deg inits land near the truth (`near_truth`), and how many turned
  inits are claimed at a wrong pose."""
  import warnings
  by_name = {c.name: c for c in cases}
  out = {"default_claimed": 0, "gt_claimed_of_those": 0, "gt_claimed": 0, "gt_right": 0,
         "gt_near": 0, "off3_near": 0, "off3_claimed_wrong": 0, "turned_claimed_wrong": 0,
         "held20_claimed_wrong": 0,
         "turned_claimed_right": 0, "n": 0}
  for rec in _progress(records, True, "inits (4 a case)"):
    case = by_name[rec["case"]]
    out["n"] += 1
    with warnings.catch_warnings():
      warnings.simplefilter("ignore")  # the projection's note
      gt = run_lrf(case, {**lrf_kw, "init": published(case.gt)}, seed)
      bad = run_lrf(case, {**lrf_kw, "init": turned(case, 30.0)}, seed)
      off3 = run_lrf(case, {**lrf_kw, "init": turned(case, 3.0)}, seed)
      held = run_lrf(case, {**lrf_kw, "init": turned(case, 20.0), "icp_iterations": 0}, seed)
    claimed = bool(rec["lrf"].get("claimed"))
    out["default_claimed"] += int(claimed)
    out["gt_claimed_of_those"] += int(claimed and bool(gt["claimed"]))
    out["gt_claimed"] += int(bool(gt["claimed"]))
    out["gt_right"] += int(gt["true"])
    out["gt_near"] += int(near_truth(case, gt.get("transform")))
    out["off3_near"] += int(near_truth(case, off3.get("transform")))
    out["off3_claimed_wrong"] += int(bool(off3["claimed"]) and not off3["true"])
    out["turned_claimed_wrong"] += int(bool(bad["claimed"]) and not bad["true"])
    out["held20_claimed_wrong"] += int(bool(held["claimed"]) and not held["true"])
    out["turned_claimed_right"] += int(bool(bad["claimed"]) and bad["true"])
  return out


# `--turns`: the truth turned about a seeded axis through the target's centroid, ICP on.
TURN_DEGREES = (5.0, 10.0, 15.0, 30.0, 60.0, 120.0)


def run_turns(cases: list[Case], lrf_kw: dict[str, Any], seed: int) -> dict[str, Any]:
  """`register(..., init=)` on every case from the truth turned by each of `TURN_DEGREES` about
  an axis drawn per case and angle (a generator seeded 1000 + the case's place in `cases`),
  ICP on: per angle [runs, right, claimed right, claimed wrong], and the false claims."""
  import warnings
  from scipy.spatial.transform import Rotation
  out: dict[str, Any] = {"per_degrees": {str(a): [0, 0, 0, 0] for a in TURN_DEGREES},
                         "false": []}
  for i, case in enumerate(_progress(cases, True, f"turns ({len(TURN_DEGREES)} a case)")):
    rng = np.random.default_rng(1000 + i)
    centre = np.asarray(case.target, np.float64).mean(axis=0)
    for degrees in TURN_DEGREES:
      axis = rng.normal(size=3)
      turn = np.eye(4)
      turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)
                                          ).as_matrix()
      turn[:3, 3] = centre - turn[:3, :3] @ centre
      with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_lrf(case, {**lrf_kw, "init": turn @ case.gt}, seed)
      row = out["per_degrees"][str(degrees)]
      row[0] += 1
      row[1] += int(rec["true"])
      row[2] += int(bool(rec["claimed"]) and rec["true"])
      row[3] += int(bool(rec["claimed"]) and not rec["true"])
      if rec["claimed"] and not rec["true"]:
        out["false"].append([case.name, degrees, rec["re"], rec["te"]])
  return out


# `--probe`: options that move the pose (ICP's reach and iterations, its mode) or the evidence
# (the inlier distance, the support radius, fewer keypoints or correspondences, another
# descriptor or frame): the verdict must claim no wrong pose under any of them.
PROBE_OPTIONS = ({"icp_mr": 10.0}, {"icp_iterations": 0}, {"icp_iterations": 300},
                 {"inlier_mr": 2.5}, {"inlier_mr": 10.0}, {"icp_mode": "point_to_point"},
                 {"icp_fine": False}, {"radius_mr": 25.0}, {"n_keypoints": 1000},
                 {"n_correspondences": 300}, {"descriptor": "shot"}, {"method": "shot"})


def run_probe(cases: list[Case], lrf_kw: dict[str, Any], seed: int) -> dict[str, Any]:
  """Every case under every `PROBE_OPTIONS` entry: runs, claims, the false claims (claimed
  and not a true success) with the case and option of each, and per option and split
  ("per_option": {option: {split: [cases, right, claimed and right, claimed and wrong]}}):
  what each lever does to the claims."""
  out: dict[str, Any] = {"runs": 0, "claimed": 0, "false": [], "per_option": {}}
  for case in _progress(cases, True, f"probe ({len(PROBE_OPTIONS)} options a case)"):
    for kw in PROBE_OPTIONS:
      rec = run_lrf(case, {**lrf_kw, **kw}, seed)
      out["runs"] += 1
      out["claimed"] += int(bool(rec["claimed"]))
      if rec["claimed"] and not rec["true"]:
        out["false"].append([case.name, kw, rec["re"], rec["te"]])
      row = out["per_option"].setdefault(json.dumps(kw), {}).setdefault(case.split, [0] * 4)
      row[0] += 1
      row[1] += int(rec["true"])
      row[2] += int(bool(rec["claimed"]) and rec["true"])
      row[3] += int(bool(rec["claimed"]) and not rec["true"])
  return out


def _progress(cases: list[Case], show: bool, desc: str = "cases") -> Iterable[Case]:
  """`cases` with a progress bar (rate and ETA, on stderr) where tqdm is installed."""
  if not show:
    return cases
  try:
    from tqdm import tqdm
  except ImportError:
    return cases
  return tqdm(cases, desc=desc, unit="case", file=sys.stderr)


def run_cases(cases: list[Case], lrf_kw: dict[str, Any] | None = None, open3d: bool = True, *,
              seed: int = 0, progress: bool = True, warmup: bool = True, kiss: bool = False,
              viewpoints: bool = False) -> list[dict[str, Any]]:
  """Registers every case with lrf_jax (and Open3D) and scores it against the truth.

  Args:
    cases: from `scene_cases.make_cases`.
    lrf_kw: keyword arguments of `lrf_jax.register` (default none); `seed` may be among them.
    open3d: also run Open3D's pipeline (skipped with a note when open3d is not installed).
    kiss: also run KISS-Matcher with ICP (`run_kiss`; skipped when it is not installed).
    seed: the seed of both methods.
    progress: a tqdm bar when tqdm is installed, else one line per case (on stderr).
    warmup: one untimed lrf_jax call on the first case first (JAX compilation).
    viewpoints: lrf_jax gets each case's sensor positions (`viewpoint_kw`).

  Returns:
    One record per case: the case's name, group, split, kind, origin, overlap, overlap bin,
    unit and point counts, and per method ("lrf", "open3d") a dict with re (degrees), te (in
    the case's unit), true, claimed (None for Open3D), overlap, reason, fitness, seconds and
    the transform (or "error" when the call raised).
  """
  lrf_kw = dict(lrf_kw or {})
  open3d = open3d and have_open3d()
  kiss = kiss and have_kiss_matcher()
  if warmup and cases:
    run_lrf(cases[0], lrf_kw, seed, viewpoints=viewpoints)
  bar = _progress(cases, progress)
  records = []
  for k, case in enumerate(bar):
    rec = {"case": case.name, "group": case.group, "split": case.split, "kind": case.kind,
           "origin": case.origin, "overlap": case.overlap, "bin": case.overlap_bin,
           "unit": case.unit, "unit_name": case.unit_name,
           "n_source": len(case.source), "n_target": len(case.target)}
    rec["lrf"] = run_lrf(case, lrf_kw, seed, viewpoints=viewpoints)
    if open3d:
      rec["open3d"] = run_open3d(case, seed)
    if kiss:
      rec["kiss"] = run_kiss(case)
    records.append(rec)
    line = (f"lrf {'ok' if rec['lrf']['true'] else 'x'}"
            + (f" o3d {'ok' if rec['open3d']['true'] else 'x'}" if open3d else ""))
    if hasattr(bar, "set_postfix_str"):
      bar.set_postfix_str(f"{case.name}: {line}")
    elif progress:
      print(f"[{k + 1}/{len(cases)}] {case.name} ({case.overlap:.0%}): {line} "
            f"({rec['lrf']['seconds']:.1f} s)", file=sys.stderr, flush=True)
  return records


def _f(v: Any, fmt: str = ".2f") -> str:
  return "" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)


def _yes(v: bool | None) -> str:
  return "" if v is None else ("yes" if v else "no")


def case_table(records: list[dict[str, Any]]) -> str:
  """A Markdown table, one row per case."""
  o3d = any("open3d" in r for r in records)
  head = ("| case | split | kind | overlap | lrf RE | lrf TE | lrf true | lrf claimed | "
          "lrf overlap | lrf reason | lrf s |")
  rule = "|---|---|---|---:|---:|---:|---|---|---:|---|---:|"
  if o3d:
    head += " o3d RE | o3d TE | o3d true | o3d s |"
    rule += "---:|---:|---|---:|"
  lines = [head, rule]
  for r in records:
    a = r["lrf"]
    reason = a.get("error") or a.get("reason", "")
    line = (f"| {r['case']} | {r['split']} | {r['kind']} | {r['overlap']:.2f} | "
            f"{_f(a['re'])} | {_f(a['te'])} {r['unit_name']} | {_yes(a['true'])} | "
            f"{_yes(a['claimed'])} | {_f(a.get('overlap'))} | {reason.replace('|', '/')} | "
            f"{_f(a['seconds'], '.1f')} |")
    if o3d:
      b = r["open3d"]
      line += (f" {_f(b['re'])} | {_f(b['te'])} {r['unit_name']} | {_yes(b['true'])} | "
               f"{_f(b['seconds'], '.1f')} |")
    lines.append(line)
  return "\n".join(lines)


def _median(values: list[float]) -> float | None:
  return float(np.median(values)) if values else None


def summarize(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
  """Per split x kind x overlap bin (and per split over all of them): counts and medians.

  Returns:
    One dict per row: split, kind, bin, n; per method m in ("lrf", "open3d") m_true,
    m_median_re / m_median_te (over its true successes), m_median_s, m_errors (calls that
    raised); and for lrf lrf_claimed,
    lrf_false (claimed but not true) and lrf_claimed_of_true (claimed and true / true).
  """
  rows = []
  bins = [b for b in ("<10%",) + BINS if any(r["bin"] == b for r in records)]
  keys = [(s, k, b) for s in ("tune", "test") for k in ("room", "object") for b in bins]
  keys += [(s, "all", "all") for s in ("tune", "test")]
  for split, kind, bin_name in keys:
    sel = [r for r in records if r["split"] == split and kind in ("all", r["kind"])
           and bin_name in ("all", r["bin"])]
    if not sel:
      continue
    row: dict[str, Any] = {"split": split, "kind": kind, "bin": bin_name, "n": len(sel)}
    for m in METHODS:
      res = [r[m] for r in sel if m in r]
      if not res:
        continue
      ok = [x for x in res if x["true"]]
      row[f"{m}_true"] = len(ok)
      row[f"{m}_errors"] = sum("error" in x for x in res)
      row[f"{m}_median_re"] = _median([x["re"] for x in ok])
      row[f"{m}_median_te"] = _median([x["te"] for x in ok])
      row[f"{m}_median_s"] = _median([x["seconds"] for x in res])
      if m in ("lrf", "kiss"):
        row[f"{m}_claimed"] = sum(bool(x["claimed"]) for x in res)
        row[f"{m}_false"] = sum(bool(x["claimed"]) and not x["true"] for x in res)
        row[f"{m}_claimed_of_true"] = (sum(bool(x["claimed"]) for x in ok) / len(ok)
                                       if ok else None)
    rows.append(row)
  return rows


def summary_table(rows: list[dict[str, Any]]) -> str:
  """The summary as Markdown (TE of a kind "all" row mixes metres and mr: left empty)."""
  o3d = any("open3d_true" in r for r in rows)
  head = ("| split | kind | overlap | n | lrf true | lrf false succ. | lrf claimed of true | "
          "lrf med RE / TE | lrf med s | lrf errors |")
  rule = "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"
  if o3d:
    head += " o3d true | o3d med RE / TE | o3d med s | o3d errors |"
    rule += "---:|---:|---:|---:|"
  kiss = any("kiss_true" in r for r in rows)
  if kiss:
    head += " KISS true | KISS valid | KISS false valid | KISS med s |"
    rule += "---:|---:|---:|---:|"
  lines = [head, rule]
  for r in rows:
    unit = {"room": " m", "object": " mr"}.get(r["kind"])
    te = (lambda m: f"{_f(r[f'{m}_median_re'])} / {_f(r[f'{m}_median_te'])}{unit}"  # noqa: B023,E731
          if unit and r[f"{m}_median_re"] is not None else _f(r[f"{m}_median_re"]))  # noqa: B023 (called in this iteration)
    cot = r["lrf_claimed_of_true"]
    line = (f"| {r['split']} | {r['kind']} | {r['bin']} | {r['n']} | {r['lrf_true']} | "
            f"{r['lrf_false']} | {'' if cot is None else f'{cot:.0%}'} | {te('lrf')} | "
            f"{_f(r['lrf_median_s'], '.1f')} | {r['lrf_errors']} |")
    if o3d:
      line += (f" {r['open3d_true']} | {te('open3d')} | {_f(r['open3d_median_s'], '.1f')} | "
               f"{r['open3d_errors']} |")
    if kiss:
      line += (f" {r['kiss_true']} | {r['kiss_claimed']} | {r['kiss_false']} | "
               f"{_f(r['kiss_median_s'], '.1f')} |")
    lines.append(line)
  return "\n".join(lines)


def _clean(obj: Any) -> Any:
  """JSON-safe: NaN/inf -> None, numpy -> Python."""
  if isinstance(obj, dict):
    return {k: _clean(v) for k, v in obj.items()}
  if isinstance(obj, (list, tuple)):
    return [_clean(v) for v in obj]
  if isinstance(obj, np.ndarray):
    return _clean(obj.tolist())
  if isinstance(obj, (np.floating, float)):
    return float(obj) if np.isfinite(obj) else None
  if isinstance(obj, np.integer):
    return int(obj)
  if isinstance(obj, np.bool_):
    return bool(obj)
  return obj


def write_json(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
  """Writes `payload` as JSON atomically (a temporary file in the same folder, then
  os.replace), so a reader never sees a half-written file."""
  out = Path(path)
  out.parent.mkdir(parents=True, exist_ok=True)
  fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
  try:
    with os.fdopen(fd, "w") as f:
      json.dump(_clean(payload), f, indent=1)
    os.replace(tmp, out)
  except BaseException:
    Path(tmp).unlink(missing_ok=True)
    raise
  return out


def select(cases: list[Case], split: str = "all", only: str | None = None,
           limit: int | None = None) -> list[Case]:
  """The cases of a split ("tune", "test" or "all") whose name contains `only`, at most
  `limit` of them (in order)."""
  if split not in ("tune", "test", "all"):
    raise ValueError(f"split: expected 'tune', 'test' or 'all', found {split!r}")
  out = [c for c in cases if split in ("all", c.split) and (not only or only in c.name)]
  return out if limit is None else out[:limit]


def main(argv: list[str] | None = None) -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--split", default="all", choices=("tune", "test", "all"))
  ap.add_argument("--kinds", default="room,object", help="comma-separated: room,object")
  ap.add_argument("--only", default=None, help="only the cases whose name contains this")
  ap.add_argument("--limit", type=int, default=None, help="at most N cases")
  ap.add_argument("--lrf-kw", default="{}", help="JSON object of lrf_jax.register keywords")
  ap.add_argument("--skip-open3d", action="store_true")
  ap.add_argument("--kiss", action="store_true",
                  help="also run KISS-Matcher with ICP (pip install kiss-matcher)")
  ap.add_argument("--inits", action="store_true",
                  help="also register every case from its truth (as published) and from the "
                       "truth turned 3, 30 and 20 deg (held unmoved), and count the claims")
  ap.add_argument("--turns", action="store_true",
                  help="also register every case from its truth turned 5-120 deg about a "
                       "seeded axis (ICP on) and count the claims per angle")
  ap.add_argument("--hints", action="store_true",
                  help="run every 'not sure' again with the step its reason names, and count "
                       "what each step settles")
  ap.add_argument("--probe", action="store_true",
                  help="also run every case under each of PROBE_OPTIONS and count false claims")
  ap.add_argument("--viewpoints", action="store_true",
                  help="give lrf_jax each scan's sensor position where the case knows it (the "
                       "first pass only; not --inits, --probe or --hints)")
  ap.add_argument("--seed", type=int, default=0, help="seed of the cases and of both methods")
  ap.add_argument("--json", default=None, help="write every record here (JSON)")
  args = ap.parse_args(argv)
  try:
    lrf_kw = json.loads(args.lrf_kw)
  except json.JSONDecodeError as e:
    ap.error(f"--lrf-kw: expected a JSON object, found {args.lrf_kw!r} ({e})")
  if not isinstance(lrf_kw, dict):
    ap.error(f"--lrf-kw: expected a JSON object, found {args.lrf_kw!r}")
  kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
  bad = [k for k in kinds if k not in ("room", "object")]
  if bad or not kinds:
    ap.error(f"--kinds: expected room and/or object, found {args.kinds!r}")
  if args.limit is not None and args.limit < 1:
    ap.error(f"--limit: expected a positive count, found {args.limit}")

  import jax
  machine = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
             f"jax {jax.__version__} on {jax.default_backend()}")
  t0 = time.perf_counter()
  all_cases = make_cases(args.data, args.seed, kinds=kinds)
  cases = select(all_cases, args.split, args.only, args.limit)
  print(f"# bench_scenes ({machine})\n\nCases (seed {args.seed}, built in "
        f"{time.perf_counter() - t0:.1f} s); split by group:\n\n{split_table(all_cases)}\n\n"
        f"Running {len(cases)} of them (split {args.split}"
        + (f", names containing {args.only!r}" if args.only else "")
        + (f", first {args.limit}" if args.limit else "") + f"); lrf_jax.register kw {lrf_kw}"
        + (", with the scans' viewpoints." if args.viewpoints else "."),
        flush=True)
  notes = []
  if not args.skip_open3d and not have_open3d():
    notes.append("open3d is not installed (pip install -r benchmarks/requirements-bench.txt): "
                 "the Open3D baseline was skipped")
  t1 = time.perf_counter()
  if args.kiss and not have_kiss_matcher():
    notes.append("kiss_matcher is not installed (pip install kiss-matcher): skipped")
  records = run_cases(cases, lrf_kw, open3d=not args.skip_open3d, seed=args.seed,
                      kiss=args.kiss, viewpoints=args.viewpoints)
  rows = summarize(records)
  print("\n" + "\n".join(f"- {n}" for n in notes))
  print("\n## Per case (RE deg, TE m for rooms / mr for objects)\n\n" + case_table(records))
  print("\n## Summary (true success: rooms RE < 15 deg and TE < 0.3 m; objects RE < 5 deg and "
        "TE < 10 mr; medians over true successes)\n\n" + summary_table(rows))
  print(f"\n{len(records)} cases in {time.perf_counter() - t1:.0f} s.")
  inits = None
  if args.inits:
    inits = run_inits(records, cases, lrf_kw, args.seed)
    print("\n## Inits\n\n" + ", ".join(f"{k} {v}" for k, v in inits.items()))
  turns = None
  if args.turns:
    named = {c.name: c for c in cases}
    turns = run_turns([named[r["case"]] for r in records], lrf_kw, args.seed)
    print("\n## Inits turned (ICP on)\n\n| degrees | runs | right | claimed right | claimed "
          "wrong |\n|---:|---:|---:|---:|---:|\n"
          + "\n".join(f"| {d} | {' | '.join(map(str, row))} |"
                      for d, row in turns["per_degrees"].items())
          + "".join(f"\n- false claim: {name} turned {d:g} deg: RE {re:.2f}, TE {te:.2f}"
                    for name, d, re, te in turns["false"]))
  probe = None
  if args.probe:
    named = {c.name: c for c in cases}
    probe = run_probe([named[r["case"]] for r in records], lrf_kw, args.seed)
    print(f"\n## Options probed\n\n{probe['runs']} runs ({len(PROBE_OPTIONS)} options), "
          f"{probe['claimed']} claimed, {len(probe['false'])} false claims"
          + "".join(f"\n- {name} {kw}: RE {re:.2f}, TE {te:.2f}"
                    for name, kw, re, te in probe["false"])
          + "\n\n| option | split | cases | right | claimed right | claimed wrong |\n"
            "|---|---|---:|---:|---:|---:|\n"
          + "\n".join(f"| `{kw}` | {split} | {' | '.join(map(str, row))} |"
                      for kw, by in probe["per_option"].items()
                      for split, row in sorted(by.items())))
  hints = None
  if args.hints:
    hints = settled_by_hints(records, cases, lrf_kw, args.seed)
    print("\n## The next steps 'not sure' names (pairs named for / then claimed right / "
          "claimed wrong)\n\n" + "\n".join(f"- {k}: {v[0]} / {v[1]} / {v[2]}"
                                          for k, v in hints.items()))
  if args.json:
    out = write_json(args.json, {"machine": machine, "args": vars(args), "lrf_kw": lrf_kw,
                                 "notes": notes, "records": records, "summary": rows,
                                 "hints": hints, "inits": inits, "turns": turns,
                                 "probe": probe})
    print(f"wrote {out}")


if __name__ == "__main__":
  main()
