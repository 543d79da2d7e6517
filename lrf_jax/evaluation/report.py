"""Tables (Markdown, JSON) and figures (PNG) from repeatability records."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Iterable

import numpy as np

from lrf_jax.defaults import RADIUS_MR
from lrf_jax.extras import matplotlib_module, pyplot
from lrf_jax.io import atomic

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# What the paper states in its text and tables (its figures are missing from our copy).
PAPER_STATED = {
    "repeatability": "LRF-Net: best on UWA3M (MeanCos 0.686, stated in the text) and UWAOR; "
                     "decent on BR together with Tombari (SHOT), Petrelli and Yang (TOLDI).",
    "noise": "LRF-Net and Tombari (SHOT) comparably stable on BR; LRF-Net best at every level on "
             "UWA3M and UWAOR (figure only).",
    "decimation": "LRF-Net best at 1/2, 1/4 and 1/8 on all datasets (figure only).",
    "radius": "LRF-Net stable on BR; best on UWA3M/UWAOR above 7.5 mr (figure only).",
    "rotation": "LRF-Net, Normal+Max and Normal+Sum2 stable under 30-120 deg about z (figure).",
    "plus_ablation": "(not in the paper) lrf_net_plus, beyond the paper: each switch on and off.",
    "points_only": "(not in the paper) every cloud moved by a seeded random rigid motion; "
                   "lrf_net_plus with the sensor position vs from the points alone. In "
                   "parentheses the z flip rate: the share of keypoints valid on both sides "
                   "whose z axes, mapped by the ground truth, have a negative cosine.",
}
PAPER_ABLATION = {  # MeanCos, z-axis x x-axis (tables analyse_BR / _UWA3M / _UWAOR)
    "BR": {"Normal": {"Sum1": 0.999, "Sum2": 0.999, "DR": 0.775, "Max": 0.720},
           "DR": {"Sum1": 0.737, "Sum2": 0.778, "DR": 0.582, "Max": 0.471}},
    "UWA3M": {"Normal": {"Sum1": 0.690, "Sum2": 0.429, "DR": 0.574, "Max": 0.412},
              "DR": {"Sum1": 0.390, "Sum2": 0.495, "DR": 0.323, "Max": 0.287}},
    "UWAOR": {"Normal": {"Sum1": 0.624, "Sum2": 0.432, "DR": 0.528, "Max": 0.380},
              "DR": {"Sum1": 0.408, "Sum2": 0.490, "DR": 0.467, "Max": 0.366}},
}


def _setting_key(setting: dict[str, Any]) -> str:
  keys = [k for k in setting if k not in ("synthetic", "model_stand_in", "scene", "motion_seed")]
  return ", ".join(f"{k}={setting[k]:g}" if isinstance(setting[k], float) else
                   f"{k}={setting[k]}" for k in keys) or "-"


def summarise(records: Iterable[dict[str, Any]]) -> dict[tuple, dict[str, dict[str, Any]]]:
  """{(experiment, dataset, setting): {method: {"meancos", "frac_above_0.97", "n_pairs",
  "n_valid_frac", "z_flip"}}}: per-pair values averaged per dataset (the paper's averaging);
  z_flip is None for records without it."""
  groups: dict[tuple, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
  for r in records:
    groups[(r["experiment"], r["dataset"], _setting_key(r["setting"]))][r["method"]].append(r)
  out: dict[tuple, dict[str, dict[str, Any]]] = {}  # floats, counts, None where undefined
  for key, by_method in groups.items():
    out[key] = {}
    for method, rs in by_method.items():
      vals = [r["meancos"] for r in rs if r["meancos"] is not None]
      if not vals:
        out[key][method] = {"meancos": None, "n_pairs": len(rs)}
        continue
      ok = [r for r in rs if r["meancos"] is not None]
      flips = [r["z_flip"] for r in ok if r.get("z_flip") is not None]
      out[key][method] = {
          "meancos": float(np.mean(vals)),
          "frac_above_0.97": float(np.mean([r["frac_above_0.97"] for r in ok])),
          "n_pairs": len(ok),
          "n_valid_frac": float(np.sum([r["n_valid"] for r in ok]) /
                                max(1, np.sum([r["n_keypoints"] for r in ok]))),
          "z_flip": float(np.nanmean(flips)) if flips else None,
      }
  return out


def markdown_report(records: list[dict[str, Any]], *, title: str = "lrf_jax evaluation",
                    notes: list[str] | None = None) -> str:
  """A Markdown report: one table per experiment (rows dataset x setting, columns methods,
  MeanCos with the fraction above 0.97 in parentheses), the paper's stated results beside it."""
  summary = summarise(records)
  methods = list(dict.fromkeys(r["method"] for r in records))
  lines = [f"# {title}", ""]
  for n in notes or []:
    lines.append(f"- {n}")
  if notes:
    lines.append("")
  for exp in dict.fromkeys(k[0] for k in summary):
    lines += [f"## {exp}", ""]
    if exp in PAPER_STATED:
      lines += [f"Paper (stated): {PAPER_STATED[exp]}", ""]
    if exp == "points_only":  # its own columns only
      methods = list(dict.fromkeys(r["method"] for r in records if r["experiment"] == exp))
    else:
      methods = list(dict.fromkeys(r["method"] for r in records
                                   if r["experiment"] != "points_only"))
    lines.append("| dataset | setting | pairs | " + " | ".join(methods) + " |")
    lines.append("|---|---|---:|" + "---:|" * len(methods))
    for (e, ds, setting), by_method in summary.items():
      if e != exp:
        continue
      best = max((v["meancos"] for v in by_method.values() if v.get("meancos") is not None),
                 default=None)
      cells = []
      for m in methods:
        v = by_method.get(m)
        if v is None:
          cells.append("")
        elif v["meancos"] is None:
          cells.append("n/a")
        elif exp == "points_only":
          flip = "-" if v.get("z_flip") is None else f"{v['z_flip']:.1%}"
          txt = f"{v['meancos']:.3f} ({flip})"
          cells.append(f"**{txt}**" if v["meancos"] == best else txt)
        else:
          txt = f"{v['meancos']:.3f} ({v['frac_above_0.97']:.2f})"
          cells.append(f"**{txt}**" if v["meancos"] == best else txt)
      n_pairs = max(v["n_pairs"] for v in by_method.values())
      lines.append(f"| {ds} | {setting} | {n_pairs} | " + " | ".join(cells) + " |")
    lines.append("")
  abl = summary_ablation(summary)
  if abl:
    lines += ["## ablation: ours vs the paper's tables (MeanCos)", "",
              "| dataset | z \\ x | Sum1 | Sum2 | DR | Max |", "|---|---|---:|---:|---:|---:|"]
    for ds, table in abl.items():
      paper = PAPER_ABLATION.get(ds, {})
      for z in ("Normal", "DR"):
        cells = []
        for x in ("Sum1", "Sum2", "DR", "Max"):
          ours = table.get(f"{z}+{x}")
          ref = paper.get(z, {}).get(x)
          cells.append(("—" if ours is None else f"{ours:.3f}") +
                       ("" if ref is None else f" (paper {ref:.3f})"))
        lines.append(f"| {ds} | {z} | " + " | ".join(cells) + " |")
    lines.append("")
  lines += ["MeanCos = (cos x + cos z) / 2 averaged over keypoints per pair, then over pairs; "
            "invalid frames count as 0; in parentheses the fraction of keypoints above 0.97 "
            "(points_only: the z flip rate). Bold: best in the row.", ""]
  return "\n".join(lines)


def summary_ablation(summary) -> dict[str, dict[str, float]]:
  """{dataset: {"Normal+Sum1": meancos, ...}} for the ablation experiment."""
  out: dict[str, dict[str, float]] = {}
  for (exp, ds, _), by_method in summary.items():
    if exp == "ablation":
      out[ds] = {m: v["meancos"] for m, v in by_method.items() if v.get("meancos") is not None}
  return out


def write_results(records: list[dict[str, Any]], out: Path, *, notes: list[str] | None = None,
                  meta: dict[str, Any] | None = None) -> None:
  """results.json ({"records": [...], "meta": ...}), report.md and the PNG figures."""
  out.mkdir(parents=True, exist_ok=True)
  clean = [{k: v for k, v in r.items() if not k.startswith("_")} for r in records]
  atomic.write_text(out / "results.json", json.dumps({"records": clean, "meta": meta or {}},
                                                    indent=1))
  atomic.write_text(out / "report.md", markdown_report(clean, notes=notes))
  plot_figures(clean, out)


HATCHES = ("", "//", "..", "xx", "\\\\", "++")
AXIS_LABELS = {"noise_mr": "Gaussian noise (mr)", "decimation": "fraction of vertices kept",
               "radius_mr": "support radius (mr)", "rotation_deg": "scene rotation about z (deg)"}


def method_styles(methods: list[str]) -> dict[str, tuple[Any, str]]:
  """A distinct (colour, hatch) per method for any number of methods: the 20 colours of
  matplotlib's tab20 (dark shades first), then the same colours again with a hatch."""
  matplotlib = matplotlib_module("eval", "evaluate.py's figures")
  cmap = matplotlib.colormaps["tab20"]
  order = list(range(0, 20, 2)) + list(range(1, 20, 2))
  return {m: (cmap(order[i % 20]), HATCHES[(i // 20) % len(HATCHES)])
          for i, m in enumerate(methods)}


def plot_figures(records: list[dict[str, Any]], out: Path) -> list[Path]:
  """Bars per dataset (repeatability) and curves per dataset for the nuisance sweeps."""
  plt = pyplot("eval", "evaluate.py's figures")

  summary = summarise(records)
  methods = list(dict.fromkeys(r["method"] for r in records))
  style = method_styles(methods)
  written = []
  for bar_exp, title in (("repeatability", "Repeatability (r = 15 mr)"),
                         ("plus_ablation", "lrf_net_plus: each switch (r = 15 mr)"),
                         ("points_only", "From the points alone (clouds moved at random)")):
    rep = {k: v for k, v in summary.items() if k[0] == bar_exp}
    if not rep:
      continue
    exp_methods = list(dict.fromkeys(r["method"] for r in records if r["experiment"] == bar_exp))
    keys = list(rep)
    panels: list[tuple[str, str, tuple[int, int] | None]] = [
        ("meancos", "MeanCos (1: identical frames)", (0, 1))]
    if bar_exp == "points_only":
      panels.append(("z_flip", "z flip rate (0: every z repeatable)", None))
    fig, axes = plt.subplots(len(panels), 1, squeeze=False,
                             figsize=(max(6, 1.4 * len(keys)) + 2.5, 4 * len(panels)))
    width = 0.8 / max(1, len(exp_methods))
    bar_style = method_styles(exp_methods)
    for ax, (field, ylabel, ylim) in zip(axes[:, 0], panels):
      for i, m in enumerate(exp_methods):
        vals = [rep[k].get(m, {}).get(field) or 0.0 for k in keys]
        colour, hatch = bar_style[m]
        ax.bar(np.arange(len(keys)) + i * width, vals, width, label=m, color=colour,
               hatch=hatch, edgecolor="0.25", linewidth=0.4)
      ax.set_xticks(np.arange(len(keys)) + 0.4 - width / 2, [k[1] for k in keys], rotation=20)
      ax.set(xlabel="dataset", ylabel=ylabel, title=title if field == "meancos" else None)
      if ylim:
        ax.set_ylim(*ylim)
    axes[0, 0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), title="method")
    fig.tight_layout()
    path = out / f"{bar_exp}.png"
    atomic.save_figure(fig, path, dpi=120)
    plt.close(fig)
    written.append(path)
  for exp, key in (("noise", "noise_mr"), ("decimation", "decimation"), ("radius", "radius_mr"),
                   ("rotation", "rotation_deg")):
    rows = [r for r in records if r["experiment"] == exp and r["meancos"] is not None]
    if not rows:
      continue
    dsets = list(dict.fromkeys(r["dataset"] for r in rows))
    fig, axes = plt.subplots(1, len(dsets), figsize=(4.2 * len(dsets), 3.6), squeeze=False)
    for ax, ds in zip(axes[0], dsets):
      for m in methods:
        pts = defaultdict(list)
        for r in rows:
          if r["dataset"] == ds and r["method"] == m:
            pts[r["setting"][key]].append(r["meancos"])
        if pts:
          xs = sorted(pts)
          colour, hatch = style[m]
          ax.plot(xs, [np.mean(pts[x]) for x in xs], marker="o", label=m, color=colour,
                  linestyle="--" if hatch else "-")
      if exp == "decimation":
        ax.set_xscale("log", base=2)
      ax.set(title=f"{ds}", xlabel=AXIS_LABELS.get(key, key), ylabel="MeanCos", ylim=(0, 1))
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), title="method")
    fig.suptitle(f"Robustness: {exp}")
    fig.tight_layout()
    path = out / f"{exp}.png"
    atomic.save_figure(fig, path, dpi=120)
    plt.close(fig)
    written.append(path)
  return written


def plot_weights(patches_xyz: list[AnyArray], weights: list[np.ndarray], frames: list[np.ndarray],
                 out: Path) -> Path:
  """Sample patches (in their LRF) with points coloured by learned weight and the x axis drawn."""
  plt = pyplot("eval", "evaluate.py's figures")

  n = len(patches_xyz)
  fig, axes = plt.subplots(1, n, figsize=(3.4 * n + 1.0, 3.6), squeeze=False,
                           layout="constrained")
  lim = max((float(np.abs(w).max()) for w in weights), default=1.0) or 1.0  # one scale
  for ax, xyz, w, f in zip(axes[0], patches_xyz, weights, frames):
    r = np.linalg.norm(xyz, axis=1).max() or 1.0
    local = xyz @ f.T / r  # coordinates in the LRF, in units of r: x right, y up (seen from +z)
    sc = ax.scatter(local[:, 0], local[:, 1], c=w, cmap="coolwarm", vmin=-lim, vmax=lim, s=6)
    ax.arrow(0, 0, 0.6, 0, width=0.01, color="k")
    ax.text(0.65, 0, "x", fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("x in the LRF (r)")
  axes[0][0].set_ylabel("y in the LRF (r)")
  fig.colorbar(sc, ax=list(axes[0]), shrink=0.8, label="learned weight (shared scale)")
  fig.suptitle("LRF-Net weights per neighbor (seen from +z, x axis drawn)")
  path = out / "weights.png"
  atomic.save_figure(fig, path, dpi=120)
  plt.close(fig)
  return path


def weights_figure(pair: Any, params: Any, out: Path, *, n: int = 4, radius_mr: float = RADIUS_MR,
                   seed: int = 0) -> Path:
  """The paper's weight visualisation: `n` model patches of `pair` in their LRF-Net frames with
  every neighbor coloured by its learned weight (figure `fig_weight`)."""
  import jax
  import jax.numpy as jnp

  from lrf_jax.datasets import repeatability_keypoints
  from lrf_jax.frames.lrf_net import frames_with_weight_fn, lrf_net_weights
  from lrf_jax.frames.weights import default_params
  from lrf_jax.search.neighborhoods import build_patches

  params = default_params() if params is None else params
  mi, _ = repeatability_keypoints(pair, n, seed)
  patches = build_patches(pair.model_points, mi, radius_mr * pair.mr, 256, seed=seed)
  frames, valid, w = frames_with_weight_fn(jax.tree.map(jnp.asarray, patches),
                                           lrf_net_weights(params))
  xyz = [patches.offsets[i][patches.mask[i]] for i in range(len(mi))]
  ws = [np.asarray(w[i])[patches.mask[i]] for i in range(len(mi))]
  return plot_weights(xyz, ws, [np.asarray(f) for f in frames], out)


def weight_maps_figure(out: Path, maps: dict[str, tuple[Any, str]] | None = None,
                       size: int = 101) -> Path:
  """The learned weight maps as images over the attribute plane (|pq|/r, cos(z, pq)): LRF-Net's
  linear weights scaled to a maximum |w| of 1, and lrf_net_plus's log-weights s - max s (its
  weights are exp of that; clipped at -20). Writes `weight_maps.png`.

  Args:
    out: output folder.
    maps: {title: (params, "sum" | "softmax")}; default: the shipped lrf_net and lrf_net_plus.
    size: grid points per axis.
  """
  import jax.numpy as jnp
  plt = pyplot("eval", "evaluate.py's figures")

  from lrf_jax.frames.weights import apply_weights, default_params

  if maps is None:
    maps = {"LRF-Net (linear weights)": (default_params("lrf_net"), "sum"),
            "lrf_net_plus (softmax weights)": (default_params("lrf_net_plus"), "softmax")}
  d, c = np.linspace(0.0, 1.0, size), np.linspace(-1.0, 1.0, size)
  grid = jnp.asarray(np.stack(np.meshgrid(d, c, indexing="ij"), -1), jnp.float32)
  fig, axes = plt.subplots(1, len(maps), figsize=(4.6 * len(maps), 3.8), squeeze=False)
  for ax, (title, (params, mode)) in zip(axes[0], maps.items()):
    s = np.asarray(apply_weights(params, grid), np.float64)
    if mode == "softmax":  # log-weights: the weights themselves span many decades
      im = ax.imshow(np.maximum(s - s.max(), -20.0).T, origin="lower", extent=(0, 1, -1, 1),
                     aspect="auto", cmap="viridis", vmin=-20.0, vmax=0.0)
      title = f"{title}\nlog w = s - max s"
    else:
      im = ax.imshow((s / (np.abs(s).max() or 1.0)).T, origin="lower", extent=(0, 1, -1, 1),
                     aspect="auto", cmap="coolwarm", vmin=-1.0, vmax=1.0)
    ax.set_xlabel("|pq| / r")
    ax.set_ylabel("cos(z, pq)")
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, shrink=0.8)
  fig.suptitle("Learned x-axis weight per neighbor over the attribute plane")
  fig.tight_layout()
  path = Path(out) / "weight_maps.png"
  atomic.save_figure(fig, path, dpi=110)
  plt.close(fig)
  return path
