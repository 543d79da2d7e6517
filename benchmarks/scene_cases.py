"""Registration cases with known truth from the real data: rooms (3DMatch) and objects (scans).

    from benchmarks.scene_cases import make_cases
    cases = make_cases("/path/to/data", seed=0)     # deterministic given the seed

Every `Case` is a source cloud, a target cloud and the ground truth `gt` (4x4, maps the source
onto the target: target ≈ R source + t), built from real scans whose alignment is known:

* rooms (`kind="room"`, metres, `unit` = 1 m): the 3DMatch fragment pairs
  (`lrf_jax.datasets.load_threedmatch_scenes`) as they are ("pair"); crops of both fragments of a
  pair by random half-spaces or oriented boxes, kept when the overlap lands in the wanted bin
  ("crop"); and pairs cut from ONE fragment ("fragment"): two overlapping half-spaces of it, each
  side an independent random 70 % of the points plus Gaussian noise of 0.1 x spacing, so that no
  point is shared exactly (the truth is then the identity).
* objects (`kind="object"`, `unit` = the source's mr, `lrf_jax.datasets.mesh_resolution`): the
  consecutive Stanford bunny scans (`load_bunny_pairs`, ground truth bun.conf) and the consecutive
  UWA3M views (`load_uwa3m`, pseudo ground truth), as they are and cropped the same way. Scans
  over `MAX_POINTS` points are first reduced to a seeded random `MAX_POINTS` of them.

Every case's source then gets a uniformly random rotation about its centroid and a translation of
length U(0.5, 1) x the source's bounding-box diagonal, folded into `gt`.

Overlap (`overlap_fraction`): the fraction of source points that have a target point within
3 x spacing once mapped by `gt`, spacing = the source's mean nearest-neighbor distance (its mr
as a cloud). Bins: "10-30%" (0.10 <= overlap < 0.30) and ">30%"; a crop is drawn again (up to
`MAX_TRIES` times) until its overlap lands in the bin it was made for, and every case keeps at
least `MIN_POINTS` points on each side (a crop of a pair also a quarter of each scan).

Split by group (the scene or object a case comes from), never by crop:

* "tune": 3DMatch scene hotel3, the bunny, UWA3M chef;
* "test": 3DMatch scene home_at, UWA3M parasaurolophus and T-rex.

With seed 0 this gives 68 cases (`python benchmarks/scene_cases.py` prints them all):

    split  kind    10-30%  >30%   groups
    tune   room         8     7   hotel3
    tune   object       8    12   bunny, chef
    test   room         9     6   home_at
    test   object       8    10   parasaurolophus, T-rex

Each case's random draws come from `np.random.SeedSequence([seed, crc32(case name)])`, so a case
does not depend on which other cases were built.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import zlib
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
  sys.path.insert(0, str(REPO))

from lrf_jax import datasets  # noqa: E402
from lrf_jax.datasets.pair import transform_points  # noqa: E402

MAX_POINTS = 30_000
MIN_POINTS = 2_000
MAX_TRIES = 400
NEAR_K = 8                    # target neighbors per source point in the crop search
OVERLAP_RADIUS = 3.0          # in source spacings
FRAGMENT_KEEP = 0.7           # fraction of points kept on each side of a one-fragment pair
FRAGMENT_NOISE = 0.1          # Gaussian sigma of a one-fragment pair, in source spacings
BINS = ("10-30%", ">30%")
# Where a crop aims, per bin: the cheap neighbor-list overlap must land here (a margin inside the
# bin, so the exact overlap of the final clouds lands in the bin too).
_AIM = {"10-30%": (0.12, 0.28), ">30%": (0.35, 1.0)}

TUNE_GROUPS = ("hotel3", "bunny", "chef")
TEST_GROUPS = ("home_at", "parasaurolophus", "T-rex")

# Cases per source, by group: raw pairs used as they are, and crops per bin.
#   rooms:   the pair, pair crops per bin, fragment crops per fragment and bin.
#   objects: indices of the consecutive pairs used raw, crops per bin (cycled over the others).
_ROOM_PLAN = {"pair_crops": {"10-30%": 4, ">30%": 4}, "fragment_crops": {"10-30%": 2, ">30%": 1}}
_OBJECT_PLAN = {
    "bunny": {"raw": (0, 2, 4, 6, 8), "crops": {"10-30%": 4, ">30%": 2}},
    "chef": {"raw": (0, 3, 6), "crops": {"10-30%": 4, ">30%": 2}},
    "parasaurolophus": {"raw": (0, 3, 6), "crops": {"10-30%": 4, ">30%": 2}},
    "T-rex": {"raw": (0, 3, 6), "crops": {"10-30%": 4, ">30%": 2}},
}


@dataclasses.dataclass(frozen=True, eq=False)
class Case:
  """One registration problem with known truth.

  Attributes:
    name: unique, e.g. "hotel3/crop-10-30%-1" or "bunny/bun000->bun045".
    group: the scene or object it comes from ("hotel3", "home_at", "bunny", "chef", ...).
    split: "tune" or "test" (by group).
    kind: "room" or "object".
    source: (n, 3) float64, cloud units (metres for rooms and the bunny, mm for UWA3M).
    target: (m, 3) float64, same units.
    gt: (4, 4) float64, maps the source onto the target: target ≈ R source + t.
    overlap: fraction of source points with a target point within 3 x spacing under gt.
    unit: length unit of the translation error, in cloud units: 1.0 (metres) for rooms, the
      source's mr for objects.
    unit_name: "m" or "mr".
    spacing: the source's mean nearest-neighbor distance (cloud units).
    origin: "pair" (as in the data set), "crop" (both sides of a pair cropped) or "fragment"
      (two crops of one fragment).
    meta: provenance (data set pair, crop shapes, motion).
  """

  name: str
  group: str
  split: str
  kind: str
  source: np.ndarray
  target: np.ndarray
  gt: np.ndarray
  overlap: float
  unit: float
  unit_name: str
  spacing: float
  origin: str
  meta: dict[str, Any] = dataclasses.field(default_factory=dict)

  @property
  def overlap_bin(self) -> str:
    """"<10%", "10-30%" or ">30%"."""
    return overlap_bin(self.overlap)


def overlap_bin(overlap: float) -> str:
  """The bin of an overlap fraction: "<10%", "10-30%" (0.10 <= o < 0.30) or ">30%"."""
  return "<10%" if overlap < 0.10 else ("10-30%" if overlap < 0.30 else ">30%")


def spacing_of(points: np.ndarray) -> float:
  """Mean nearest-neighbor distance of a cloud (its mr as a cloud), cloud units."""
  return float(datasets.mesh_resolution(points)[0])


def overlap_fraction(source: np.ndarray, target: np.ndarray, gt: np.ndarray,
                     spacing: float | None = None) -> float:
  """Fraction of source points within `OVERLAP_RADIUS` x spacing of the target under gt.

  Args:
    source: (n, 3).
    target: (m, 3).
    gt: (4, 4) source -> target.
    spacing: the unit (None: the source's mean nearest-neighbor distance).

  Returns:
    The fraction in [0, 1].
  """
  spacing = spacing_of(source) if spacing is None else spacing
  dist, _ = cKDTree(target).query(transform_points(gt, source),
                                  distance_upper_bound=OVERLAP_RADIUS * spacing, workers=-1)
  return float(np.isfinite(dist).mean())


def _rng(seed: int, name: str) -> np.random.Generator:
  return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(name.encode())]))


def _limit(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
  """At most MAX_POINTS points: a seeded random subset (in index order) when there are more."""
  pts = np.asarray(points, np.float64)
  if len(pts) <= MAX_POINTS:
    return np.array(pts)
  return pts[np.sort(rng.choice(len(pts), MAX_POINTS, replace=False))]


def _random_motion(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
  """(4, 4): a uniform random rotation about the centroid, then a translation of length
  U(0.5, 1) x the bounding-box diagonal in a uniform random direction."""
  r = Rotation.random(random_state=rng).as_matrix()
  c = points.mean(0)
  d = rng.normal(size=3)
  t = d / np.linalg.norm(d) * rng.uniform(0.5, 1.0) * np.linalg.norm(np.ptp(points, 0))
  m = np.eye(4)
  m[:3, :3] = r
  m[:3, 3] = c - r @ c + t
  return m


def _crop_mask(points: np.ndarray, rng: np.random.Generator,
               centre: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
  """A random crop: a half-space through a point, or an oriented box about a point."""
  c = points[rng.integers(len(points))] if centre is None else centre
  if rng.random() < 0.5:
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    return (points - c) @ n < 0, {"shape": "half-space", "point": c.tolist(), "normal": n.tolist()}
  r = Rotation.random(random_state=rng).as_matrix()
  local = (points - c) @ r.T
  half = rng.uniform(0.3, 0.6, size=3) * np.ptp(local, 0)
  return np.all(np.abs(local) <= half, axis=1), {"shape": "box", "centre": c.tolist(),
                                                  "axes": r.tolist(), "half": half.tolist()}


class _NearTarget:
  """For each source point (mapped by gt), its `NEAR_K` nearest target points within the overlap
  radius, so the overlap of any pair of crops is one gather (no tree per crop). It can miss a
  source point whose near target points were all cropped away but a farther one (still within
  the radius) was kept: crops are checked again exactly (`overlap_fraction`)."""

  def __init__(self, source: np.ndarray, target: np.ndarray, gt: np.ndarray, spacing: float):
    _, self.index = cKDTree(target).query(transform_points(gt, source), k=NEAR_K,
                                          distance_upper_bound=OVERLAP_RADIUS * spacing,
                                          workers=-1)
    self.n_target = len(target)
    self.overlapping = self.index[:, 0] < self.n_target

  def overlap(self, keep_source: np.ndarray, keep_target: np.ndarray) -> float:
    """The approximate overlap fraction of the source points kept."""
    if not keep_source.any():
      return 0.0
    kept = np.append(keep_target, False)  # index n_target: no neighbor
    return float(kept[self.index[keep_source]].any(axis=1).mean())


def _enough(mask: np.ndarray) -> bool:
  return int(mask.sum()) >= max(MIN_POINTS, len(mask) // 4)


def _crop_pair(source, target, gt, spacing, bin_name, rng) -> tuple[np.ndarray, np.ndarray, dict]:
  """Crops of both sides of a pair whose overlap lands in `bin_name` (rejection sampling)."""
  near = _NearTarget(source, target, gt, spacing)
  lo, hi = _AIM[bin_name]
  mapped = transform_points(gt, source)
  for attempt in range(MAX_TRIES):
    centre = None
    if rng.random() < 0.5 and near.overlapping.any():  # both crops about one overlapping place
      i = rng.choice(np.flatnonzero(near.overlapping))
      centre = source[i]
    ks, ms = _crop_mask(source, rng, centre)
    kt, mt = _crop_mask(target, rng, None if centre is None else mapped[i])
    if not (_enough(ks) and _enough(kt)):
      continue
    if lo <= near.overlap(ks, kt) < hi and overlap_bin(
        overlap_fraction(source[ks], target[kt], gt)) == bin_name:
      return ks, kt, {"source_crop": ms, "target_crop": mt, "attempts": attempt + 1}
  raise RuntimeError(f"no crop with overlap in {bin_name} after {MAX_TRIES} tries")


def _fragment_pair(points, spacing, bin_name, rng) -> tuple[np.ndarray, np.ndarray, dict]:
  """Two overlapping half-spaces of one cloud, independently subsampled and noised; the truth is
  the identity. Redrawn until the exact overlap lands in `bin_name`."""
  lo, hi = _AIM[bin_name]
  for attempt in range(MAX_TRIES // 10):
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    s = points @ n
    keep_s = rng.uniform(0.5, 0.8)          # source: the lowest keep_s of the cloud along n
    # The slab shared with the target, as a fraction of the source (the overlap comes out a
    # little larger: points within the overlap radius beyond the cut count too).
    aim = rng.uniform(max(0.05, lo - 0.05), min(hi, 0.8) - 0.05)
    a, b = np.quantile(s, [keep_s, keep_s * (1.0 - aim)])
    side_s, side_t = s < a, s > b
    src = points[side_s & (rng.random(len(points)) < FRAGMENT_KEEP)]
    dst = points[side_t & (rng.random(len(points)) < FRAGMENT_KEEP)]
    if min(len(src), len(dst)) < MIN_POINTS:
      continue
    src = src + rng.normal(scale=FRAGMENT_NOISE * spacing, size=src.shape)
    dst = dst + rng.normal(scale=FRAGMENT_NOISE * spacing, size=dst.shape)
    ov = overlap_fraction(src, dst, np.eye(4))
    if lo <= ov < hi:
      return src, dst, {"normal": n.tolist(), "cut_source": float(a), "cut_target": float(b),
                        "keep": FRAGMENT_KEEP, "noise_spacings": FRAGMENT_NOISE,
                        "attempts": attempt + 1}
  raise RuntimeError(f"no one-fragment pair with overlap in {bin_name} after {MAX_TRIES // 10} "
                     "tries")


def _split(group: str) -> str:
  if group in TUNE_GROUPS:
    return "tune"
  if group in TEST_GROUPS:
    return "test"
  raise ValueError(f"group: expected one of {TUNE_GROUPS + TEST_GROUPS}, found {group!r}")


def _finish(name, group, kind, source, target, gt, origin, meta, rng,
            viewpoints=(None, None)) -> Case:
  """Moves the source by a random rigid motion folded into gt; measures spacing and overlap.
  `viewpoints` (the source's and the target's sensor positions in their own coordinates, None
  where unknown) go into meta as "source_viewpoint" (moved with the source) and
  "target_viewpoint"."""
  spacing = spacing_of(source)
  overlap = overlap_fraction(source, target, gt, spacing)
  motion = _random_motion(source, rng)
  moved = transform_points(motion, source)
  vs, vt = viewpoints
  meta = {**meta,
          "source_viewpoint": None if vs is None else transform_points(
              motion, np.asarray(vs, np.float64)[None])[0].tolist(),
          "target_viewpoint": None if vt is None else np.asarray(vt, np.float64).tolist()}
  unit, unit_name = (1.0, "m") if kind == "room" else (spacing, "mr")
  return Case(name=name, group=group, split=_split(group), kind=kind, source=moved,
              target=np.array(target, np.float64), gt=np.asarray(gt, np.float64)
              @ np.linalg.inv(motion), overlap=overlap, unit=unit, unit_name=unit_name,
              spacing=spacing, origin=origin, meta={**meta, "motion": motion.tolist()})


# A 3DMatch fragment is fused in the coordinates of its first camera: its origin is where that
# camera stood (the loader gives no viewpoint, as a fused cloud has no single one; `--viewpoints`
# of bench_scenes.py passes this one, as a user who knows it would).
_FRAGMENT_ORIGINS = (np.zeros(3), np.zeros(3))


def _room_cases(root, seed: int) -> list[Case]:
  cases = []
  for pair in datasets.load_threedmatch_scenes(root):
    group = pair.name.rsplit("_", 2)[0]
    src, dst, gt = np.array(pair.model_points), np.array(pair.scene_points), pair.transform
    base = {"dataset": "3DMatch", "pair": pair.name, "benchmark": pair.meta["benchmark"]}
    name = f"{group}/pair"
    cases.append(_finish(name, group, "room", src, dst, gt, "pair", base, _rng(seed, name),
                         _FRAGMENT_ORIGINS))
    spacing = spacing_of(src)
    for bin_name, count in _ROOM_PLAN["pair_crops"].items():
      for k in range(count):
        name = f"{group}/crop-{bin_name}-{k}"
        rng = _rng(seed, name)
        ks, kt, meta = _crop_pair(src, dst, gt, spacing, bin_name, rng)
        cases.append(_finish(name, group, "room", src[ks], dst[kt], gt, "crop",
                             {**base, **meta}, rng, _FRAGMENT_ORIGINS))
    for frag, points in ((pair.meta["files"][0], src), (pair.meta["files"][1], dst)):
      stem = Path(frag).stem
      frag_spacing = spacing_of(points)
      for bin_name, count in _ROOM_PLAN["fragment_crops"].items():
        for k in range(count):
          name = f"{group}/fragment-{stem}-{bin_name}-{k}"
          rng = _rng(seed, name)
          a, b, meta = _fragment_pair(points, frag_spacing, bin_name, rng)
          cases.append(_finish(name, group, "room", a, b, np.eye(4), "fragment",
                               {"dataset": "3DMatch", "fragment": frag, **meta}, rng,
                               _FRAGMENT_ORIGINS))
  return cases


def _object_pairs(root) -> dict[str, list[datasets.Pair]]:
  out: dict[str, list[datasets.Pair]] = {"bunny": datasets.load_bunny_pairs(root)}
  for pair in datasets.load_uwa3m(root, kind="consecutive"):
    out.setdefault(pair.meta["object"], []).append(pair)
  return out


def _object_cases(root, seed: int) -> list[Case]:
  cases = []
  for group, pairs in _object_pairs(root).items():
    plan = _OBJECT_PLAN[group]
    others = [i for i in range(len(pairs)) if i not in plan["raw"]] or list(range(len(pairs)))
    jobs = [(i, None, 0) for i in plan["raw"]]
    k = 0
    for bin_name, count in plan["crops"].items():
      for c in range(count):
        jobs.append((others[k % len(others)], bin_name, c))
        k += 1
    for i, bin_name, c in jobs:
      pair = pairs[i]
      label = pair.name.split("/")[-1]
      name = f"{group}/{label}" + ("" if bin_name is None else f"/crop-{bin_name}-{c}")
      rng = _rng(seed, name)
      src, dst = _limit(pair.model_points, rng), _limit(pair.scene_points, rng)
      base = {"dataset": pair.dataset, "pair": pair.name,
              "ground_truth": pair.meta.get("ground_truth", "exact")}
      views = (pair.model_viewpoint, pair.scene_viewpoint)
      if bin_name is None:
        cases.append(_finish(name, group, "object", src, dst, pair.transform, "pair", base, rng,
                             views))
        continue
      ks, kt, meta = _crop_pair(src, dst, pair.transform, spacing_of(src), bin_name, rng)
      cases.append(_finish(name, group, "object", src[ks], dst[kt], pair.transform, "crop",
                           {**base, **meta}, rng, views))
  return cases


def make_cases(root: str | os.PathLike | None = None, seed: int = 0, *,
               kinds: tuple[str, ...] = ("room", "object")) -> list[Case]:
  """Every registration case (see the module docstring), rooms first, then objects.

  Args:
    root: data root (None: $LRF_DATA, then `<repo>/data`).
    seed: the seed of every crop, subsample, noise and motion; the same seed gives the same
      cases.
    kinds: which kinds to build ("room", "object").

  Returns:
    The cases, in a fixed order.

  Raises:
    ValueError: an unknown kind.
    lrf_jax.datasets.DataNotFoundError: a data set is missing.
  """
  bad = [k for k in kinds if k not in ("room", "object")]
  if bad:
    raise ValueError(f"kinds: expected 'room' and/or 'object', found {bad}")
  cases = []
  if "room" in kinds:
    cases += _room_cases(root, seed)
  if "object" in kinds:
    cases += _object_cases(root, seed)
  return cases


def split_table(cases: list[Case]) -> str:
  """A Markdown table of case counts per split x kind x overlap bin, and the groups of each
  split."""
  counts = Counter((c.split, c.kind, c.overlap_bin) for c in cases)
  bins = [b for b in ("<10%",) + BINS if any(k[2] == b for k in counts)]
  lines = ["| split | kind | " + " | ".join(bins) + " | groups |",
           "|---|---|" + "---:|" * len(bins) + "---|"]
  for split in ("tune", "test"):
    for kind in ("room", "object"):
      groups = sorted({c.group for c in cases if c.split == split and c.kind == kind})
      if groups:
        lines.append(f"| {split} | {kind} | " + " | ".join(str(counts[(split, kind, b)])
                                                        for b in bins)
                     + f" | {', '.join(groups)} |")
  return "\n".join(lines) + f"\n\n{len(cases)} cases."


def main() -> None:
  import argparse
  import time
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--seed", type=int, default=0)
  args = ap.parse_args()
  t0 = time.perf_counter()
  cases = make_cases(args.data, args.seed)
  print("| case | split | kind | source | target | overlap | unit |\n"
        "|---|---|---|---:|---:|---:|---:|")
  for c in cases:
    print(f"| {c.name} | {c.split} | {c.kind} | {len(c.source)} | {len(c.target)} | "
          f"{c.overlap:.3f} | {c.unit:.4g} {c.unit_name} |")
  print("\n" + split_table(cases))
  print(f"built in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
  main()
