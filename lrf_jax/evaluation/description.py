"""Local shape description (paper section 3.2.2): descriptors on their original LRF vs LRF-Net.

Protocol per model/scene pair (as the repeatability experiment):

* keypoints: the repeatability protocol's 1000 seeded model points and their ground-truth scene
  correspondences (`repeatability.correspondences`: by index for BR, by ground truth plus nearest
  neighbor within 0.5 mr for partial scans), so every scene keypoint has exactly one
  corresponding model feature (N_corr = number of scene keypoints);
* frames by each LRF method on both sides (one absolute radius, 15 mr of the noise-free model),
  descriptors on every neighbor within the same radius;
* matching: each scene descriptor is matched to its nearest model descriptor (L2) with the score
  ratio = d1 / d2 (`descriptors.match_descriptors`); a match is correct when the matched model
  keypoint lies within `correct_mr` mr (default 1) of the true corresponding model keypoint
  (exact for BR's index correspondence);
* curve: for each ratio threshold tau, N_match(tau) = matches with ratio <= tau and N_true(tau)
  the correct ones; recall = N_true / N_corr (eq. `eq_recall`), 1 - precision =
  (N_match - N_true) / N_match (eq. `eq_prec`). Counts are pooled over the pairs of a dataset.

Normals (SHOT, and the LRFs that need them) are `lrf_jax.geometry.normals`' defaults (PCA over 0.2 r,
oriented by the mesh winding or by propagation), estimated once per side and pair.

Invalid descriptors (invalid frame, too few points) are never matched on the model side and never
match on the scene side (they count in N_corr). Records carry the counts at `RATIO_THRESHOLDS`,
so the per-dataset curve is exact; summaries: `recall_max` (tau = 1: the fraction of scene
keypoints whose nearest model descriptor is correct) and `recall_at_0.1` (the largest recall with
1 - precision <= 0.1).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any
from collections.abc import Iterable, Iterator

import numpy as np

from lrf_jax.defaults import RADIUS_MR
from lrf_jax.extras import pyplot
from lrf_jax.frames.patch_frames import frames_from_patches
from lrf_jax.datasets import Pair
from lrf_jax.descriptors import DESCRIPTORS, describe_patches, match_descriptors
from lrf_jax.evaluation.repeatability import (EXACT_NETWORK, MethodRun, PatchCache, correspondences,
                                              group_records)
from lrf_jax.frames import METHODS
from lrf_jax.io import atomic
from lrf_jax.geometry.normals import default_normals
from lrf_jax.frames.normals_rule import orients, prepare_extra

RATIO_THRESHOLDS = np.round(np.linspace(0.0, 1.0, 101), 2)
# What the paper states (its figure `fig_RPC` is missing from our copy).
PAPER_STATED = ("All four descriptors (snapshots, SHOT, RoPS, TOLDI) match better with LRF-Net "
                "than with their original LRF (Mian, Tombari, Guo, Yang) on BR, UWA3M and UWAOR; "
                "snapshots improves dramatically on BR, SHOT clearly on UWA3M and UWAOR "
                "(figure only, no numbers).")


@dataclasses.dataclass(frozen=True)
class DescriptionRun:
  """One curve: a descriptor on the frames of one LRF run.

  Attributes:
    descriptor: a key of `lrf_jax.descriptors.DESCRIPTORS`.
    lrf: the LRF (a `MethodRun`: method, parameters, options, K).
    options: static descriptor options, e.g. (("grid", 20),).
  """

  descriptor: str
  lrf: MethodRun
  options: tuple[tuple[str, Any], ...] = ()

  @property
  def label(self) -> str:
    return f"{self.descriptor}+{self.lrf.label}"


def default_runs(params: Any = None,
                 descriptors: Iterable[str] = ("snapshots", "shot", "rops", "toldi"),
                 learned_label: str = "lrf_net") -> list[DescriptionRun]:
  """Each descriptor with its original LRF and with LRF-Net (the paper's comparison).

  Args:
    params: LRF-Net parameters (None: the shipped weights).
    descriptors: which descriptors.
    learned_label: the label of the LRF-Net run.

  Returns:
    [DescriptionRun] in the order descriptor x (original, LRF-Net).
  """
  runs = []
  for name in descriptors:
    if name not in DESCRIPTORS:
      raise ValueError(f"descriptors: unknown descriptor {name!r}; expected some of "
                       f"{sorted(DESCRIPTORS)}")
    orig = DESCRIPTORS[name].original_lrf
    runs.append(DescriptionRun(name, MethodRun(orig, orig)))
    runs.append(DescriptionRun(name, MethodRun(learned_label, "lrf_net", params=params,
                                               options=EXACT_NETWORK)))
  return runs


def rpc_counts(ratio: np.ndarray, correct: np.ndarray,
               thresholds: np.ndarray = RATIO_THRESHOLDS) -> tuple[np.ndarray, np.ndarray]:
  """(N_match, N_true) at each ratio threshold.

  Args:
    ratio: (m,) match scores d1 / d2 (inf where a query has no match).
    correct: (m,) bool, whether each query's match is correct.
    thresholds: (T,) ascending thresholds.

  Returns:
    (n_match (T,), n_true (T,)) int64.
  """
  ratio = np.asarray(ratio, np.float64)
  correct = np.asarray(correct, bool)
  n_match = np.array([(ratio <= t).sum() for t in thresholds], np.int64)
  n_true = np.array([((ratio <= t) & correct).sum() for t in thresholds], np.int64)
  return n_match, n_true


def rpc_curve(n_match: np.ndarray, n_true: np.ndarray,
              n_corr: int) -> tuple[np.ndarray, np.ndarray]:
  """Recall (eq. `eq_recall`) and 1 - precision (eq. `eq_prec`) from the counts.

  Args:
    n_match: (T,) matches accepted per threshold.
    n_true: (T,) correct ones among them.
    n_corr: number of corresponding features (scene keypoints with a true counterpart).

  Returns:
    (recall (T,), one_minus_precision (T,)); 1 - precision is NaN where nothing is matched.
  """
  n_match = np.asarray(n_match, np.float64)
  n_true = np.asarray(n_true, np.float64)
  recall = n_true / max(int(n_corr), 1)
  with np.errstate(invalid="ignore", divide="ignore"):
    omp = np.where(n_match > 0, (n_match - n_true) / n_match, np.nan)
  return recall, omp


def recall_at(recall: np.ndarray, omp: np.ndarray, level: float = 0.1) -> float:
  """The largest recall whose 1 - precision is <= `level` (0 when none)."""
  ok = np.isfinite(omp) & (omp <= level)
  return float(recall[ok].max()) if ok.any() else 0.0


def _frames(pts, faces, idx, radius, run: MethodRun, seed: int, cache: PatchCache, normals,
            viewpoint=None):
  spec = METHODS[run.method]
  patches = cache.get(pts, idx, radius, run.patch_k, seed, spec.z_ratio)
  extra = prepare_extra(spec, pts, idx, patches, faces=faces, radius=radius, viewpoint=viewpoint,
                        normals=normals, oriented=orients(dict(run.options)))
  f, v = frames_from_patches(patches, run.method, params=run.params, extra=extra,
                             **dict(run.options))
  return np.asarray(f), np.asarray(v)


def evaluate_description_pair(pair: Pair, runs: Iterable[DescriptionRun], *,
                              n_keypoints: int = 1000, seed: int = 0, radius_mr: float = RADIUS_MR,
                              correct_mr: float = 1.0, cache: PatchCache | None = None,
                              setting: dict[str, Any] | None = None,
                              thresholds: np.ndarray = RATIO_THRESHOLDS) -> list[dict[str, Any]]:
  """Recall vs 1-precision counts of every descriptor run on one pair.

  Args:
    pair: model-scene pair.
    runs: descriptor runs (`default_runs()`).
    n_keypoints: keypoints per pair (1000).
    seed: keypoint and subsample seed.
    radius_mr: support radius of the LRFs and descriptors, in mr.
    correct_mr: a match is correct within this distance (mr) of the true model keypoint.
    cache: shared patch cache.
    setting: stored in the records (e.g. {"noise_mr": 0.3}).
    thresholds: ratio thresholds of the curve.

  Returns:
    One record per run: experiment "description", dataset, pair, method (= run label), setting
    (with "descriptor" and "lrf"), n_keypoints, n_corr, n_valid_model, n_valid_scene, thresholds,
    n_match, n_true, recall_max, recall_at_0.1, seconds; recall_max is None (and "note" says
    why) when the pair cannot feed the LRF (a mesh LRF on a cloud).
  """
  cache = cache or PatchCache()
  mi, si = correspondences(pair, n_keypoints, seed)
  radius = radius_mr * pair.mr
  sides = (("model", pair.model_points, pair.model_faces, mi),
           ("scene", pair.scene_points, pair.scene_faces, si))
  viewpoints = {"model": pair.model_viewpoint, "scene": pair.scene_viewpoint}
  desc_patches = {tag: cache.get(pts, idx, radius, None, seed, 1.0 / 3.0)
                  for tag, pts, _, idx in sides}
  frames: dict[str, Any] = {}
  normal_cache: dict[str, np.ndarray] = {}

  def normals_of(tag, pts, faces):  # the default normals, estimated once per side
    def get():
      if tag not in normal_cache:
        normal_cache[tag] = default_normals(pts, radius, faces, None, viewpoints[tag])
      return normal_cache[tag]
    return get

  records = []
  for run in runs:
    t0 = time.perf_counter()
    rec = {"experiment": "description", "dataset": pair.dataset, "pair": pair.name,
           "method": run.label,
           "setting": {**(setting or {}), "descriptor": run.descriptor, "lrf": run.lrf.label},
           "radius": radius, "n_keypoints": int(len(mi)), "n_corr": int(len(si))}
    spec = METHODS[run.lrf.method]
    if spec.needs_mesh and (pair.model_faces is None or pair.scene_faces is None):
      records.append(dict(rec, recall_max=None, **{"recall_at_0.1": None},
                          note="n/a: the LRF needs a mesh, the pair has a cloud side"))
      continue
    if run.lrf.label not in frames:
      frames[run.lrf.label] = {tag: _frames(pts, faces, idx, radius, run.lrf, seed, cache,
                                            normals_of(tag, pts, faces), viewpoints[tag])
                               for tag, pts, faces, idx in sides}
    desc = {}
    for tag, pts, faces, idx in sides:
      f, v = frames[run.lrf.label][tag]
      nrm = normals_of(tag, pts, faces)() if DESCRIPTORS[run.descriptor].prepare else None
      d, ok = describe_patches(desc_patches[tag], f, v, run.descriptor, points=pts,
                               keypoints=idx, radius=radius, faces=faces, normals=nrm,
                               **dict(run.options))
      desc[tag] = (np.asarray(d), np.asarray(ok))
    (dm, okm), (ds, oks) = desc["model"], desc["scene"]
    matches = match_descriptors(ds, dm, oks, okm)
    hit = matches.nearest >= 0
    true_model = pair.model_points[mi]
    gap = np.full(len(si), np.inf)
    gap[hit] = np.linalg.norm(pair.model_points[mi[matches.nearest[hit]]] - true_model[hit],
                              axis=1)
    correct = gap <= correct_mr * pair.mr
    n_match, n_true = rpc_counts(matches.ratio, correct, thresholds)
    recall, omp = rpc_curve(n_match, n_true, len(si))
    rec.update(n_valid_model=int(okm.sum()), n_valid_scene=int(oks.sum()),
               thresholds=[float(t) for t in thresholds], n_match=n_match.tolist(),
               n_true=n_true.tolist(), recall_max=float(recall[-1]),
               **{"recall_at_0.1": recall_at(recall, omp, 0.1)},
               seconds=time.perf_counter() - t0)
    records.append(rec)
  return records


def run_description(dataset_names: list[str], opts: Any, cache: PatchCache, *,
                    runs: list[DescriptionRun] | None = None, params: Any = None,
                    correct_mr: float = 1.0) -> Iterator[dict[str, Any]]:
  """Yield the description records over datasets (names of `evaluation.experiments.DATASETS`).

  Args:
    dataset_names: e.g. ["BR@0.3", "UWA3M", "UWAOR"] (the paper: BR, UWA3M, UWAOR).
    opts: `evaluation.EvalOptions` (data_root, n_keypoints, seed, radius_mr, max_pairs).
    cache: shared `PatchCache`.
    runs: descriptor runs (None: `default_runs(params)`).
    params: LRF-Net parameters for the default runs.
    correct_mr: correctness distance of a match, in mr.

  Yields:
    Records of `evaluate_description_pair`, "dataset" set to the dataset name.
  """
  from lrf_jax.evaluation.experiments import iter_pairs
  runs = runs or default_runs(params)
  for ds, setting, pair in iter_pairs(dataset_names, opts):
    for rec in evaluate_description_pair(pair, runs, n_keypoints=opts.n_keypoints,
                                         seed=opts.seed, radius_mr=opts.radius_mr,
                                         correct_mr=correct_mr, cache=cache, setting=setting):
      rec["dataset"] = ds
      yield rec


def summarise_description(records: Iterable[dict[str, Any]]) -> dict[tuple, dict[str, Any]]:
  """{(dataset, run label): {"recall", "omp", "thresholds", "recall_max", "recall_at_0.1",
  "n_pairs", "descriptor", "lrf"}} with the counts pooled over the dataset's pairs."""
  groups = group_records(records, "description")
  out = {}
  for key, rs in groups.items():
    ok = [r for r in rs if r.get("n_match") is not None]
    base = {"descriptor": rs[0]["setting"]["descriptor"], "lrf": rs[0]["setting"]["lrf"],
            "n_pairs": len(ok)}
    if not ok:
      out[key] = dict(base, recall_max=None, **{"recall_at_0.1": None},
                      note=rs[0].get("note", ""))
      continue
    n_match = np.sum([r["n_match"] for r in ok], axis=0)
    n_true = np.sum([r["n_true"] for r in ok], axis=0)
    recall, omp = rpc_curve(n_match, n_true, sum(r["n_corr"] for r in ok))
    out[key] = dict(base, recall=recall, omp=omp, thresholds=np.asarray(ok[0]["thresholds"]),
                    recall_max=float(recall[-1]), **{"recall_at_0.1": recall_at(recall, omp)})
  return out


def description_report(records: list[dict[str, Any]]) -> str:
  """Markdown: per dataset, each descriptor with its original LRF and with LRF-Net."""
  summary = summarise_description(records)
  if not summary:
    return ""
  lines = ["## description (recall vs 1-precision)", "", f"Paper (stated): {PAPER_STATED}", "",
           "| dataset | descriptor | LRF | pairs | recall (tau = 1) | recall at 1-p <= 0.1 |",
           "|---|---|---|---:|---:|---:|"]
  for (ds, _), v in summary.items():
    if v["recall_max"] is None:
      cells = "n/a | n/a"
    else:
      cells = f"{v['recall_max']:.3f} | {v['recall_at_0.1']:.3f}"
    lines.append(f"| {ds} | {v['descriptor']} | {v['lrf']} | {v['n_pairs']} | {cells} |")
  lines += ["", "Scene keypoints matched to their nearest model descriptor (L2), scored by the "
            "ratio d1/d2; counts pooled over the pairs of a dataset; recall = N_true / N_corr, "
            "1-precision = N_false / N_match. n/a: the LRF needs a mesh.", ""]
  return "\n".join(lines)


def plot_rpc(records: list[dict[str, Any]], out: Path) -> list[Path]:
  """One PNG per dataset (`rpc_<dataset>.png`): a panel per descriptor, one curve per LRF."""
  plt = pyplot("eval", "evaluate.py's figures")

  summary = summarise_description(records)
  out = Path(out)
  out.mkdir(parents=True, exist_ok=True)
  written = []
  for ds in dict.fromkeys(k[0] for k in summary):
    descs = list(dict.fromkeys(v["descriptor"] for (d, _), v in summary.items() if d == ds))
    fig, axes = plt.subplots(1, len(descs), figsize=(3.6 * len(descs), 3.4), squeeze=False)
    for ax, desc in zip(axes[0], descs):
      for (d, _label), v in summary.items():
        if d != ds or v["descriptor"] != desc:
          continue
        if v["recall_max"] is None:
          ax.plot([], [], label=f"{v['lrf']} (n/a)")
          continue
        ok = np.isfinite(v["omp"])
        ax.plot(v["omp"][ok], v["recall"][ok], label=v["lrf"])
      ax.set(title=desc, xlabel="1 - precision", ylabel="recall", xlim=(0, 1), ylim=(0, 1))
      ax.legend(fontsize=7)
    fig.suptitle(f"Descriptor matching on {ds} (r = 15 mr)")
    fig.tight_layout()
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in ds)
    path = out / f"rpc_{safe}.png"
    atomic.save_figure(fig, path, dpi=120)
    plt.close(fig)
    written.append(path)
  return written
