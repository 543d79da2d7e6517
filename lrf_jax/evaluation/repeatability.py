"""The paper's repeatability protocol (section 3.2.1) for any LRF method.

For a model-scene pair: 1000 seeded model keypoints and their scene correspondences (by index
for BR; by ground truth plus nearest neighbor within 0.5 mr for partial scans), frames on both
sides with one absolute radius (radius_mr x the noise-free model's mr), MeanCos per keypoint after
mapping the scene frame back by the ground-truth rotation, averaged per pair (invalid frames count
as 0). Records also carry the fraction above 0.97 and the number of valid frames.

Neighborhoods are computed once per (pair, side, K, radius, seed) and shared by every method that
uses the same K (`PatchCache`), so adding a method to a run does not redo the search.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal
from collections.abc import Iterable

import numpy as np
from scipy.spatial import cKDTree

import jax

from lrf_jax.defaults import RADIUS_MR
from lrf_jax.search import engine
from lrf_jax.frames.host_path import host_frames
from lrf_jax.frames.patch_frames import frames_from_patches
from lrf_jax.datasets import Pair, repeatability_keypoints, transform_points
from lrf_jax.frames import METHODS
from lrf_jax.io import atomic
from lrf_jax.frames.metrics import meancos
from lrf_jax.search.neighborhoods import Patches, SearchIndex, build_patches
from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals
from lrf_jax.frames.normals_rule import method_normals, orients, prepare_extra

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# Default cap on all-neighbor patches in evaluations (see `evaluate_pair`).
MAX_NEIGHBORS = 4096
# Options of the paper's LRF-Net in the paper's experiments: the exact network (lut=0), not the
# weight table that `compute_frames` reads by default.
EXACT_NETWORK = (("lut", 0),)


def paper_options(method: str) -> tuple[tuple[str, Any], ...]:
  """The options a paper experiment passes to `method`: `EXACT_NETWORK` for "lrf_net"."""
  return EXACT_NETWORK if method == "lrf_net" else ()


@dataclasses.dataclass(frozen=True)
class MethodRun:
  """One column of a results table: a registered method with its parameters and options.

  Attributes:
    label: the name in tables and records (e.g. "lrf_net", "lrf_net[final]", "toldi").
    method: a key of `lrf_jax.METHODS`.
    params: learned parameters (None: the method's default).
    options: static method options (e.g. {"x_mode": "max"}).
    k: patch size; "default" = the method's own.
  """

  label: str
  method: str
  params: Any = None
  options: tuple[tuple[str, Any], ...] = ()
  k: int | None | Literal["default"] = "default"

  @property
  def patch_k(self) -> int | None:
    return METHODS[self.method].default_k if self.k == "default" else self.k


class PatchCache:
  """Patches keyed by (cloud content, keypoints, K, radius, z_ratio, seed), in memory and
  optionally on disk.

  The disk cache (when `directory` is set) stores the neighbor indices and normal statistics as
  .npz, so a second run of `evaluate.py` with another method does not search again.
  """

  def __init__(self, directory: str | Path | None = None, max_items: int = 4):
    self.directory = Path(directory) if directory else None
    self.max_items = max_items
    self._mem: dict[str, Patches] = {}
    self.hits = self.misses = 0

  def get(self, points: np.ndarray, keypoints: np.ndarray, radius: float, k: int | None,
          seed: int, z_ratio: float, max_k: int | None = None) -> Patches:
    """The patches of `keypoints` of `points` (built on a miss; arguments as `build_patches`)."""
    h = hashlib.sha1(np.ascontiguousarray(points).tobytes())
    h.update(np.ascontiguousarray(keypoints).tobytes())
    h.update(repr((float(radius), k, seed, float(z_ratio), max_k)).encode())
    key = h.hexdigest()[:20]  # content-addressed: BR model sides are shared across scenes
    if key in self._mem:
      self.hits += 1
      return self._mem[key]
    path = self.directory / f"patches_{key}.npz" if self.directory else None
    if path is not None and path.exists():
      self.hits += 1
      patches = Patches(**dict(np.load(path)))
    else:
      self.misses += 1
      patches = build_patches(points, keypoints, radius, k, seed=seed, z_ratio=z_ratio,
                              index=SearchIndex(points, seed), max_k=max_k)
      if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic.atomic_write(path) as f:
          np.savez(f, **patches._asdict())
    if len(self._mem) >= self.max_items:
      self._mem.pop(next(iter(self._mem)))
    self._mem[key] = patches
    return patches


def group_records(records: Iterable[dict[str, Any]], experiment: str) -> dict[tuple, list[dict]]:
  """{(dataset, method): [records]} of one experiment, in order of first appearance."""
  groups: dict[tuple, list[dict]] = {}
  for r in records:
    if r.get("experiment") == experiment:
      groups.setdefault((r["dataset"], r["method"]), []).append(r)
  return groups


def correspondences(pair: Pair, n: int, seed: int, *, scene_first: bool = False,
                    max_dist_mr: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """The protocol's keypoints: (model_idx, scene_idx), each (k,) int64.

  `scene_first` draws the keypoints on the scene and matches them in the model by the inverse
  ground truth and nearest neighbor (within `max_dist_mr`): used for decimated scenes, whose
  vertices are fewer and moved, so that every keypoint has a counterpart within 0.5 mr on the
  full-resolution model.
  """
  if not scene_first:
    return repeatability_keypoints(pair, n, seed, max_dist_mr)
  inv = np.linalg.inv(pair.transform)
  dist, nearest = cKDTree(pair.model_points).query(
      transform_points(inv, pair.scene_points), distance_upper_bound=max_dist_mr * pair.mr,
      workers=-1)
  eligible = np.flatnonzero(np.isfinite(dist))
  rng = np.random.default_rng(seed)
  chosen = np.sort(rng.choice(eligible, size=min(n, len(eligible)), replace=False))
  return nearest[chosen].astype(np.int64), chosen.astype(np.int64)


def z_flip_rate(frames_a: Any, frames_b: Any, transform: np.ndarray, valid_a: Any,
                valid_b: Any) -> float:
  """The share of keypoints valid on both sides whose z axes, the scene's mapped back by the
  ground-truth rotation, point to opposite sides (negative cosine): how often the z sign is not
  repeatable. NaN when no keypoint is valid on both sides.

  Args:
    frames_a: (N, 3, 3) model frames (rows x, y, z).
    frames_b: (N, 3, 3) scene frames.
    transform: (4, 4) ground truth model -> scene (or its (3, 3) rotation).
    valid_a: (N,) bool, the model frames' validity.
    valid_b: (N,) bool, the scene frames'.
  """
  rot = np.asarray(transform, np.float64)[:3, :3]
  cos_z = np.einsum("nc,nc->n", np.asarray(frames_a, np.float64)[:, 2],
                    np.asarray(frames_b, np.float64)[:, 2] @ rot)
  ok = np.asarray(valid_a, bool) & np.asarray(valid_b, bool)
  return float(np.sum((cos_z < 0) & ok) / ok.sum()) if ok.any() else float("nan")


def evaluate_pair(pair: Pair, methods: Iterable[MethodRun], *, experiment: str,
                  setting: dict[str, Any] | None = None, n_keypoints: int = 1000,
                  seed: int = 0, radius_mr: float = RADIUS_MR, scene_first: bool = False,
                  cache: PatchCache | None = None, max_neighbors: int | None = MAX_NEIGHBORS,
                  keep_frames: bool = False, kernel: str = "auto") -> list[dict[str, Any]]:
  """Repeatability records of every method on one pair.

  Args:
    pair: model-scene pair (its `mr` is the noise-free model's).
    methods: the methods to run.
    experiment: experiment name stored in the records.
    setting: the nuisance setting stored in the records (e.g. {"noise_mr": 0.3}).
    n_keypoints: keypoints per pair (1000 in the paper).
    seed: keypoint and subsample seed.
    radius_mr: support radius in mr (one absolute radius on both sides).
    scene_first: draw keypoints on the scene (decimation), see `correspondences`.
    cache: shared patch cache.
    max_neighbors: cap on the patch size of all-neighbor methods (K = None): balls with more
      points keep this many by the seeded priority subsample (`build_patches(max_k=...)`). Only
      dense clouds reach it (UWAOR's full-resolution rs1: 33-50k points per 15 mr ball, from the
      decimated model's mr); None = no cap. Stored in each record as "max_neighbors".
    keep_frames: also return the frames (under "_frames") for figures.
    kernel: "auto": a method with a host fast path (`MethodSpec.host_frames`), every neighbor
      (K = None) and no options runs it on a CPU backend when no ball of the side exceeds
      `max_neighbors` (then the capped patches would hold every neighbor too, so both paths
      compute the same frames, the host one in float64); otherwise, and with "jit", the jitted
      function on the (capped) patches. Stored in each record as "kernel".

  Returns:
    One record per method with keys experiment, dataset, pair, method, setting, meancos,
    frac_above_0.97, n_keypoints, n_valid, z_flip (`z_flip_rate`), radius, kernel, seconds (search, normals and frames
    of both sides, compilation included); meancos is None (and "note" says why) for a
    method the pair cannot feed (a mesh method on a cloud).
  """
  cache = cache or PatchCache()
  setting = dict(setting or {})
  mi, si = correspondences(pair, n_keypoints, seed, scene_first=scene_first)
  radius = radius_mr * pair.mr
  base = {"experiment": experiment, "dataset": pair.dataset, "pair": pair.name,
          "setting": setting, "radius": radius, "mr_definition": pair.mr_definition,
          "max_neighbors": max_neighbors}
  records = []
  side_normals: dict[str, np.ndarray] = {}  # estimated once per side, shared by every method

  side_counts: dict[str, tuple[SearchIndex, np.ndarray]] = {}  # host kernels' index, ball sizes
  if kernel not in ("auto", "jit"):
    raise ValueError(f"kernel: expected 'auto' or 'jit', got {kernel!r}")
  on_cpu = jax.default_backend() == "cpu"

  def normals_of(tag, pts, faces, viewpoint):
    if tag not in side_normals:
      side_normals[tag] = estimate_normals(pts, NORMAL_RADIUS_RATIO * radius, faces, viewpoint)
    return side_normals[tag]

  def host_side(tag, pts, idx):
    """(index, ball counts) of a side when its balls fit `max_neighbors`, else None."""
    if tag not in side_counts:
      index = SearchIndex(pts, seed)
      side_counts[tag] = index, engine.ball_counts(index.grid(radius), pts[idx], radius)
    index, counts = side_counts[tag]
    fits = max_neighbors is None or counts.size == 0 or int(counts.max()) <= max_neighbors
    return (index, counts) if fits else None

  for run in methods:
    spec = METHODS[run.method]
    rec = dict(base, method=run.label)
    if spec.needs_mesh and (pair.model_faces is None or pair.scene_faces is None):
      records.append(dict(rec, meancos=None, **{"frac_above_0.97": None}, n_keypoints=len(mi),
                          n_valid=0, note="n/a: needs a mesh, the pair has a cloud side"))
      continue
    t0 = time.perf_counter()
    sides: list[tuple[AnyArray, AnyArray]]  # numpy from the host kernels, else jax.Array
    sides, kernels = [], []
    may_host = (kernel == "auto" and on_cpu and spec.host_frames is not None
                and run.patch_k is None and not run.options)
    for tag, pts, faces, idx, vp in (
        ("model", pair.model_points, pair.model_faces, mi, pair.model_viewpoint),
        ("scene", pair.scene_points, pair.scene_faces, si, pair.scene_viewpoint)):
      normals = lambda: normals_of(tag, pts, faces, vp)  # noqa: B023,E731 (estimated once, if read)
      host = host_side(tag, pts, idx) if may_host else None
      if host is not None:
        sides.append(host_frames(pts, idx, radius, run.method, index=host[0], faces=faces,
                                 normals=method_normals(spec, pts, radius, faces=faces,
                                                        normals=normals, viewpoint=vp),
                                 ball_counts=host[1]))
        kernels.append("host")
        continue
      patches = cache.get(pts, idx, radius, run.patch_k, seed, spec.z_ratio, max_k=max_neighbors)
      extra = prepare_extra(spec, pts, idx, patches, faces=faces, radius=radius, viewpoint=vp,
                            normals=normals, oriented=orients(dict(run.options)))
      sides.append(frames_from_patches(patches, run.method, params=run.params, extra=extra,
                                       **dict(run.options)))
      kernels.append("jit")
    (fm, vm), (fs, vs) = sides
    rec["kernel"] = kernels[0] if kernels[0] == kernels[1] else "+".join(kernels)
    mc = np.asarray(meancos(fm, fs, pair.transform, vm, vs))
    rec.update(meancos=float(mc.mean()) if mc.size else float("nan"),
               **{"frac_above_0.97": float((mc > 0.97).mean()) if mc.size else float("nan")},
               n_keypoints=int(mc.size), n_valid=int(np.sum(np.asarray(vm) & np.asarray(vs))),
               z_flip=z_flip_rate(fm, fs, pair.transform, vm, vs),
               seconds=time.perf_counter() - t0)
    if keep_frames:
      rec["_frames"] = (np.asarray(fm), np.asarray(fs), mc, mi, si)
    records.append(rec)
  return records
