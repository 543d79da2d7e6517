"""Raw data with the defaults: raw KITTI sweeps, their subsamples and crops, and room fragments
at 2.5 cm and at a denser stand-in, against Open3D's tutorial pipeline in the same run.

    LRF_DATA=/path/to/data python benchmarks/bench_lidar.py [--out out/bench_lidar] [--seed 0]
        [--no-kiss] [--viewpoints] [--lrf-kw '{"weights": "streets"}']
        [--sets sweeps subsampled cropped rooms dense mixed far]
        [--fused DIR --sets fused fused25 fusedmixed fusedratio]
        [--fused-frames 40] [--fused-voxel 0.006]

lrf_jax: `lrf_jax.register(source, target)` with its defaults: no resolution, no voxel size.
Open3D 0.20: its global registration tutorial (`benchmarks/_open3d_pipeline.py`: voxel
downsampling, FPFH, RANSAC, point-to-plane ICP at 0.4 voxel on the full clouds) at a 0.3 m voxel
for the sweeps and 5 cm for the rooms, the voxels its users pick for such data. KISS-Matcher
(`pip install kiss-matcher`; `benchmarks/_kiss_matcher_pipeline.py`: its estimate, then
point-to-plane ICP, as its README pipes it) at the same voxels, where it is installed
(`--no-kiss` skips it); its "valid" is its own verdict, counted as a claim.

Sets (every pair both pipelines, after one warm-up call each):

* sweeps: the 15 pairs of the six raw KITTI sweeps (`lidar_kitti00`, 124k points, sweep j onto
  sweep i for i < j: 0.7-3.5 m apart), truth `poses_DERIVED.txt` (about 1 cm / 0.1 deg);
* subsampled: the same pairs, each sweep a seeded random half of its points;
* cropped: the same pairs, each sweep cut to the half-space in front of its sensor (x > -5 m);
* rooms: the two 3DMatch fragment pairs (2.5 cm voxels) both ways;
* dense: the same, each fragment upsampled 4x by jitter in its tangent plane (a stand-in for a
  full-density fused fragment, 6 mm spacing: this data holds none);
* mixed: a dense fragment against a 2.5 cm one, both ways;
* far: sweeps 3 and 5 as a sensor 10, 20 or 30 m further along the road or back would return
  them (`resweep`: an HDL-64E's beams and azimuth step, the nearest point of each kept, 80 m
  range), against sweep 0: simulated pairs 6-34 m apart (a surface the first sensor missed
  never appears, so they are easier than real far pairs);
* fused, fused25, fusedmixed, fusedratio (with `--fused DIR`, not by default): full-density
  TSDF fragments fused from the depth frames under DIR (`benchmarks/_fused_fragments.py`:
  Open3D's livingroom1_clean_micro test data makes 5 fragments of 242k-300k points, 3-4 mm
  spacing; `--fused-frames` and `--fused-voxel` fuse other fragments, e.g. 30 frames at 4 or
  10 mm TSDF voxels: 7 fragments, extent / spacing 680-960 or 260-370), every pair (i, j),
  i < j: at full density, both voxelized at 2.5 cm, the
  full-density source against the 2.5 cm target, and both voxelized at extent / 136
  (`RATIO_VOXEL`: the ratio of extent to spacing of 3DMatch's 2.5 cm fragments).

Right: rotation error < 5 deg and translation error < 2 m (the KITTI benchmarks' rule) for the
sweeps, < 1 deg and 10 cm as well ("strict"); rooms: < 15 deg and 30 cm, as
`bench_scenes.py` counts them (the hotel3 pair's ground truth is about 2 deg off: both pipelines
land 2.2-2.3 deg from it). A false claim is a success that is not right. Writes results.json,
report.md and report.png (the table as bars) under --out and prints the report.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lrf_jax.io import read_cloud  # noqa: E402
from lrf_jax.io.atomic import save_figure, write_text  # noqa: E402
from lrf_jax.registration import register, rotation_error_deg  # noqa: E402

from benchmarks._kiss_matcher_pipeline import have_kiss_matcher, kiss_registration  # noqa: E402
from benchmarks._open3d_pipeline import global_registration, have_open3d  # noqa: E402

SETS = ("sweeps", "subsampled", "cropped", "rooms", "dense", "mixed", "far", "fused", "fused25",
        "fusedmixed", "fusedratio")
DEFAULT_SETS = SETS[:7]
# far: a Velodyne HDL-64E's beams (64 rows over +2 to -24.8 deg elevation) and azimuth step.
HDL64_ELEVATION = (-24.8, 2.0)
HDL64_ROWS = 64
HDL64_AZIMUTH_STEP = 0.17  # deg
FAR_SHIFTS = (-30.0, -20.0, -10.0, 10.0, 20.0, 30.0)  # m along the road
# fusedratio's voxel, as a fraction of each fragment's extent (`cloud_extent`): it leaves the
# fused fragments at extent / mean spacing 160-170, the ratio of 3DMatch's 2.5 cm fragments
# (162-183; the fused ones at 2.5 cm: about 103). register is scale-free, so this is a 2.5 cm
# 3DMatch fragment's analogue to compare the full-density time with.
RATIO_VOXEL = 1 / 136


def homogeneous(p: np.ndarray) -> np.ndarray:
  return np.vstack([p.reshape(3, 4), [0, 0, 0, 1]])


def sweep_pairs(data: Path, rng: np.random.Generator, variant: str) -> list[dict]:
  folder = data / "lidar_kitti00"
  poses = [homogeneous(p) for p in np.loadtxt(folder / "poses_DERIVED.txt")]
  clouds = [read_cloud(folder / f"{k:06d}.bin").points for k in range(6)]
  if variant == "subsampled":
    clouds = [c[np.sort(rng.choice(len(c), len(c) // 2, replace=False))] for c in clouds]
  elif variant == "cropped":
    clouds = [c[c[:, 0] > -5.0] for c in clouds]
  return [dict(name=f"{j}->{i}", source=clouds[j], target=clouds[i],
               gt=np.linalg.inv(poses[i]) @ poses[j], lidar=True)
          for j in range(6) for i in range(j)]


def resweep(points: np.ndarray, sensor: np.ndarray, max_range: float = 80.0) -> np.ndarray:
  """The points of a sweep (n, 3) that a spinning LiDAR at `sensor` (3,) would return: binned by
  its beams (`HDL64_ROWS` rows over `HDL64_ELEVATION`, `HDL64_AZIMUTH_STEP` deg columns), the
  nearest point of each bin kept (what stands in front hides the rest), between 2 m (the car
  itself) and `max_range` m; (k, 3) in the new sensor's frame (axes as the input's). Only
  surfaces the first sweep saw can be returned."""
  rel = points - sensor
  r = np.linalg.norm(rel, axis=1)
  el = np.degrees(np.arcsin(np.clip(rel[:, 2] / np.maximum(r, 1e-9), -1, 1)))
  az = np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) + 180.0
  lo, hi = HDL64_ELEVATION
  row = np.floor((el - lo) / (hi - lo) * HDL64_ROWS).astype(np.int64)
  col = np.floor(az / HDL64_AZIMUTH_STEP).astype(np.int64)
  ok = (row >= 0) & (row < HDL64_ROWS) & (r > 2.0) & (r < max_range)
  idx = np.flatnonzero(ok)
  key = row[idx] * 10_000 + col[idx]
  order = np.lexsort((r[idx], key))  # by bin, nearest first
  first = np.r_[True, key[order][1:] != key[order][:-1]]
  return rel[idx[order][first]]


def far_pairs(data: Path) -> list[dict]:
  """Sweeps 3 and 5 as a sensor `FAR_SHIFTS` m further along the road or back would return
  them (`resweep`), against sweep 0: simulated far-apart pairs (no surface the first sensor
  missed appears)."""
  folder = data / "lidar_kitti00"
  poses = [homogeneous(p) for p in np.loadtxt(folder / "poses_DERIVED.txt")]
  heading = poses[5][:3, 3] / np.linalg.norm(poses[5][:3, 3])  # the car's way, sweep 0's frame
  target = read_cloud(folder / "000000.bin").points
  out = []
  for k in (3, 5):
    points = read_cloud(folder / f"{k:06d}.bin").points
    for shift in FAR_SHIFTS:
      sensor = poses[k][:3, :3].T @ (shift * heading)  # in sweep k's frame
      move = np.eye(4)
      move[:3, 3] = sensor
      gt = np.linalg.inv(poses[0]) @ poses[k] @ move
      out.append(dict(name=f"{k}{shift:+.0f}m->0 ({np.linalg.norm(gt[:3, 3]):.0f} m)",
                      source=resweep(points, sensor), target=target, gt=gt, lidar=True))
  return out


def upsample(points: np.ndarray, factor: int, rng: np.random.Generator) -> np.ndarray:
  """`factor` jittered copies of each point in its tangent plane (normals by PCA over 16
  neighbors), spread over about the point spacing: a denser sampling of the same surface."""
  from scipy.spatial import cKDTree
  d, idx = cKDTree(points).query(points, k=16)
  spacing = float(np.mean(d[:, 1]))
  nb = points[idx] - points[idx].mean(1, keepdims=True)
  _, _, vt = np.linalg.svd(nb, full_matrices=False)
  u, v = vt[:, 0], vt[:, 1]
  out = [points]
  for _ in range(factor - 1):
    a, b = rng.uniform(-0.5, 0.5, (2, len(points), 1)) * spacing
    out.append(points + a * u + b * v)
  return np.concatenate(out)


def room_pairs(data: Path, rng: np.random.Generator, variant: str) -> list[dict]:
  folder = data / "threedmatch_scenes"
  out = []
  for a, b, gt_file in (("hotel3_15", "hotel3_8", "gt_hotel3_8_15.txt"),
                        ("home_at_41", "home_at_38", "gt_home_at_38_41.txt")):
    gt = np.loadtxt(folder / gt_file).reshape(4, 4)
    pa, pb = read_cloud(folder / f"{a}.ply").points, read_cloud(folder / f"{b}.ply").points
    da, db = (upsample(p, 4, rng) for p in (pa, pb)) if variant != "rooms" else (pa, pb)
    if variant == "mixed":
      out += [dict(name=f"{a}(dense)->{b}", source=da, target=pb, gt=gt, lidar=False),
              dict(name=f"{b}->{a}(dense)", source=pb, target=da, gt=np.linalg.inv(gt),
                   lidar=False)]
    else:
      out += [dict(name=f"{a}->{b}", source=da, target=db, gt=gt, lidar=False),
              dict(name=f"{b}->{a}", source=db, target=da, gt=np.linalg.inv(gt), lidar=False)]
  return out


_FRAGMENTS: dict[tuple[Path, Path], list[dict]] = {}


def fused_pairs(folder: Path, cache: Path, variant: str) -> list[dict]:
  """Every pair (i, j), i < j, of the fused fragments of `folder`: source i, target j."""
  from benchmarks._fused_fragments import fused_fragments
  if (folder, cache) not in _FRAGMENTS:  # fused once for the four variants
    _FRAGMENTS[(folder, cache)] = fused_fragments(folder, cache)
  frags = _FRAGMENTS[(folder, cache)]
  if variant == "fusedratio":
    from lrf_jax.geometry.resolution import cloud_extent
    from lrf_jax.geometry.sampling import voxel_downsample
    for f in frags:
      if "ratio" not in f:
        f["ratio"] = voxel_downsample(f["full"], RATIO_VOXEL * cloud_extent(f["full"]))
  src_key = {"fused25": "coarse", "fusedratio": "ratio"}.get(variant, "full")
  dst_key = {"fused": "full", "fusedratio": "ratio"}.get(variant, "coarse")
  return [dict(name=f"fragment {i}->{j}", source=frags[i][src_key], target=frags[j][dst_key],
               gt=np.linalg.inv(frags[j]["pose"]) @ frags[i]["pose"], lidar=False)
          for i in range(len(frags)) for j in range(i + 1, len(frags))]


def errors(t: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
  return (float(rotation_error_deg(t[:3, :3], gt[:3, :3])),
          float(np.linalg.norm(t[:3, 3] - gt[:3, 3])))


def run_set(pairs: list[dict], seed: int, o3d: bool, kiss: bool = False,
            viewpoints: bool = False, lrf_kw: dict | None = None) -> list[dict]:
  rows = []
  for p in pairs:
    views = dict(lrf_kw or {})
    if viewpoints:  # every set's clouds are in their sensor's frame (a fragment: 1st camera)
      views.update(source_viewpoint=(0.0, 0.0, 0.0), target_viewpoint=(0.0, 0.0, 0.0))
    t0 = time.perf_counter()
    reg = register(p["source"], p["target"], seed=seed, **views)
    secs = time.perf_counter() - t0
    re, te = errors(reg.transform, p["gt"])
    row = dict(name=p["name"], n=(len(p["source"]), len(p["target"])), re=re, te=te,
               success=bool(reg.success), seconds=secs, mr=reg.mr, voxel=reg.voxel_size,
               reason=reg.reason, transform=np.asarray(reg.transform).tolist())
    if o3d:
      voxel = 0.3 if p["lidar"] else 0.05
      res = global_registration(p["source"], p["target"], voxel=voxel, seed=seed)
      row.update(o3d_re=errors(res["final"], p["gt"])[0], o3d_te=errors(res["final"], p["gt"])[1],
                 o3d_seconds=res["seconds"], o3d_transform=np.asarray(res["final"]).tolist())
    if kiss:
      km = kiss_registration(p["source"], p["target"], voxel=0.3 if p["lidar"] else 0.05)
      km_re, km_te = errors(km["final"], p["gt"])
      row.update(km_re=km_re, km_te=km_te, km_valid=km["valid"], km_seconds=km["seconds"])
    rows.append(row)
    print(f"  {p['name']}: RE {re:.3f} TE {te:.3f} {'claimed' if reg.success else 'not sure'} "
          f"{secs:.2f} s (mr {reg.mr:.3g}, voxel {reg.voxel_size:.3g})"
          + (f"; Open3D RE {row['o3d_re']:.3f} TE {row['o3d_te']:.3f} {row['o3d_seconds']:.2f} s"
             if o3d else ""), file=sys.stderr, flush=True)
  return rows


def right(re: float, te: float, lidar: bool, strict: bool = False) -> bool:
  if lidar:
    return (re < 1 and te < 0.1) if strict else (re < 5 and te < 2)
  return re < 15 and te < 0.3  # rooms: bench_scenes.py's rule


def summarize(name: str, rows: list[dict]) -> str:
  lidar = name in ("sweeps", "subsampled", "cropped")
  ok = [right(r["re"], r["te"], lidar) for r in rows]
  strict = [right(r["re"], r["te"], lidar, True) for r in rows]
  claimed = [r["success"] for r in rows]
  false = sum(c and not o for c, o in zip(claimed, ok))
  med = lambda xs: float(np.median(xs)) if len(xs) else float("nan")  # noqa: E731
  line = (f"| {name} | {len(rows)} | {sum(ok)} ({sum(strict)}) | {sum(claimed)} | {false} | "
          f"{med([r['re'] for r, o in zip(rows, ok) if o]):.3f} / "
          f"{med([r['te'] for r, o in zip(rows, ok) if o]):.3f} | "
          f"{med([r['seconds'] for r in rows]):.2f}")
  if "o3d_re" in rows[0]:
    ok3 = [right(r["o3d_re"], r["o3d_te"], lidar) for r in rows]
    st3 = [right(r["o3d_re"], r["o3d_te"], lidar, True) for r in rows]
    ratio = med([r["seconds"] / r["o3d_seconds"] for r in rows])
    line += (f" | {sum(ok3)} ({sum(st3)}) | "
             f"{med([r['o3d_re'] for r, o in zip(rows, ok3) if o]):.3f} / "
             f"{med([r['o3d_te'] for r, o in zip(rows, ok3) if o]):.3f} | "
             f"{med([r['o3d_seconds'] for r in rows]):.2f} | {ratio:.2f}")
  if "km_re" in rows[0]:
    okk = [right(r["km_re"], r["km_te"], lidar) for r in rows]
    valid = [r["km_valid"] for r in rows]
    line += (f" | {sum(okk)} / {sum(valid)} / {sum(v and not o for v, o in zip(valid, okk))} | "
             f"{med([r['km_seconds'] for r in rows]):.2f}")
  return line + " |"


def loop_errors(rows: list[dict], key: str) -> tuple[float, float, int]:
  """Median rotation (deg) and translation (m) error over every loop k -> j -> i (i < j < k)
  of the six sweeps: inv(T(k->i)) T(j->i) T(k->j), the identity for exact pairwise
  transforms. No ground truth enters: a precision measure free of the truth's own bias (the
  sweeps' truth is Open3D's ICP, which Open3D's pipeline converges to)."""
  t = {r["name"]: np.asarray(r[key]) for r in rows}
  re, te = [], []
  for k in range(6):
    for j in range(k):
      for i in range(j):
        names = (f"{k}->{i}", f"{j}->{i}", f"{k}->{j}")
        if all(n in t for n in names):
          e = np.linalg.inv(t[names[0]]) @ t[names[1]] @ t[names[2]]
          re.append(rotation_error_deg(e[:3, :3], np.eye(3)))
          te.append(float(np.linalg.norm(e[:3, 3])))
  if not re:
    return float("nan"), float("nan"), 0
  return float(np.median(re)), float(np.median(te)), len(re)


def loop_line(name: str, rows: list[dict]) -> str:
  """A report line of `loop_errors` for lrf_jax and, when it ran, Open3D."""
  re, te, n = loop_errors(rows, "transform")
  line = f"{name}: loop closure, median of {n} loops: lrf_jax {re:.3f} deg / {te:.4f} m"
  if "o3d_transform" in rows[0]:
    re3, te3, _ = loop_errors(rows, "o3d_transform")
    line += f", Open3D {re3:.3f} deg / {te3:.4f} m"
  return line


def plot(results: dict[str, list[dict]], out: Path) -> None:
  """report.png: per set, the pairs right and claimed (lrf_jax) and right (Open3D, where it
  ran), and the median seconds a pair of both."""
  try:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
  except ImportError:
    return
  names = list(results)
  x = np.arange(len(names))
  fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.5))
  for name_k, rows in enumerate(results.values()):
    lidar = names[name_k] in ("sweeps", "subsampled", "cropped")
    ok = [right(r["re"], r["te"], lidar) for r in rows]
    n = len(rows)
    ax.bar(name_k - 0.25, sum(ok) / n, 0.25, color="#27a", label="lrf_jax right" * (name_k == 0))
    ax.bar(name_k, sum(o and r["success"] for o, r in zip(ok, rows)) / n, 0.25, color="#3a7",
           label="lrf_jax right and claimed" * (name_k == 0))
    bx.bar(name_k - 0.2, np.median([r["seconds"] for r in rows]), 0.4, color="#27a",
           label="lrf_jax" * (name_k == 0))
    if "o3d_re" in rows[0]:
      ok3 = [right(r["o3d_re"], r["o3d_te"], lidar) for r in rows]
      ax.bar(name_k + 0.25, sum(ok3) / n, 0.25, color="#999",
             label="Open3D right" * (name_k == 0))
      bx.bar(name_k + 0.2, np.median([r["o3d_seconds"] for r in rows]), 0.4, color="#999",
             label="Open3D" * (name_k == 0))
  for axis, label in ((ax, "fraction of pairs"), (bx, "median s a pair")):
    axis.set_xticks(x, names, rotation=20)
    axis.set_ylabel(label)
    axis.legend(fontsize=7)
  ax.set_title("register's defaults on raw data")
  fig.tight_layout()
  save_figure(fig, out / "report.png", dpi=120)


def main() -> int:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--out", default="out/bench_lidar")
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--viewpoints", action="store_true",
                  help="give register each cloud's origin as its viewpoint (a sweep's sensor, "
                       "a 3DMatch fragment's first camera)")
  ap.add_argument("--lrf-kw", default="{}",
                  help="JSON object of lrf_jax.register keywords, e.g. '{\"weights\": \"streets\"}'")
  ap.add_argument("--no-kiss", action="store_true",
                  help="skip KISS-Matcher (run where `pip install kiss-matcher` installed it)")
  ap.add_argument("--sets", nargs="+", default=list(DEFAULT_SETS), choices=SETS)
  ap.add_argument("--fused", help="a folder of depth frames and their trajectory "
                  "(benchmarks/_fused_fragments.py), for the fused sets")
  ap.add_argument("--fused-frames", type=int, default=40,
                  help="depth frames fused per fragment (benchmarks/_fused_fragments.py)")
  ap.add_argument("--fused-voxel", type=float, default=0.006,
                  help="the fusion's TSDF voxel (m)")
  args = ap.parse_args()
  if args.fused_frames < 2 or not args.fused_voxel > 0:
    ap.error("--fused-frames: at least 2; --fused-voxel: a positive length (m)")
  import benchmarks._fused_fragments as fusion  # its settings key its cache
  fusion.FRAMES, fusion.VOXEL = args.fused_frames, args.fused_voxel
  if any(name.startswith("fused") for name in args.sets) and not args.fused:
    ap.error("--sets fused, fused25, fusedmixed, fusedratio need --fused DIR")
  data = Path(os.environ.get("LRF_DATA", REPO.parent / "shared" / "data"))
  out = Path(args.out)
  inputs = [Path(args.fused).resolve()] if args.fused else []
  if any(out.resolve() == p or p in out.resolve().parents for p in inputs):
    ap.error(f"--out {out}: inside the input folder --fused {args.fused}; write elsewhere")
  out.mkdir(parents=True, exist_ok=True)
  o3d = have_open3d()
  kiss = have_kiss_matcher() and not args.no_kiss
  sets = {}
  for name in args.sets:
    if name.startswith("fused"):
      sets[name] = fused_pairs(Path(args.fused), out / "fused_cache", name)
    elif name == "far":
      sets[name] = far_pairs(data)
    else:
      make = sweep_pairs if name in ("sweeps", "subsampled", "cropped") else room_pairs
      sets[name] = make(data, np.random.default_rng(args.seed), name)
    if not sets[name]:
      ap.error(f"--sets {name}: no pairs")
  warm = sets[args.sets[0]][0]
  register(warm["source"], warm["target"])  # compile and load the kernels before timing
  if o3d:
    global_registration(warm["source"], warm["target"], voxel=0.3 if warm["lidar"] else 0.05)
  if kiss:
    kiss_registration(warm["source"], warm["target"], voxel=0.3 if warm["lidar"] else 0.05)
  results = {}
  for name, pairs in sets.items():
    print(f"{name}:", file=sys.stderr)
    results[name] = run_set(pairs, args.seed, o3d, kiss, args.viewpoints,
                            json.loads(args.lrf_kw))
  head = ("| set | pairs | right (strict) | claimed | false claims | median RE deg / TE m | "
          "median s")
  head += (" | Open3D right (strict) | Open3D median RE / TE | Open3D median s | time ratio"
           if o3d else "")
  head += (" | KISS-Matcher + ICP right / valid / false valid | KISS-Matcher median s |"
           if kiss else " |")
  lines = [f"# bench_lidar: raw data with register's defaults "
           f"({platform.processor() or platform.machine()}, {os.cpu_count()} cores)", "",
           head, "|" + "---|" * (head.count("|") - 1)]
  lines += [summarize(name, rows) for name, rows in results.items()]
  loops = [loop_line(name, rows) for name, rows in results.items()
           if name in ("sweeps", "subsampled", "cropped") and len(rows) == 15]
  lines += [""] + loops if loops else []
  report = "\n".join(lines) + "\n"
  write_text(out / "results.json", json.dumps(results, indent=1, default=str))
  write_text(out / "report.md", report)
  plot(results, out)
  print(report)
  return 0


if __name__ == "__main__":
  sys.exit(main())
