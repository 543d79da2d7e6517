"""Where the device path's time goes: the device search, the jitted frames and the whole
`compute_frames` call, each timed alone on the same keypoints (warm, synchronised).

    LRF_DATA=/path/to/data python benchmarks/bench_device_split.py [--points 1000000]
        [--keypoints 1000000] [--chunks 4096 65536] [--methods lrf_net lrf_net_plus]

The cloud is `bench_scale.py`'s (points sampled on the BR dragon's triangles, r = 15 mr of the
mesh; `--points 0`: the mesh's vertices). For each chunk size: the `DeviceIndex` build (host
grids and their upload), the search of every chunk (`build_patches_device`, its result brought
back: the device search's own cost, the host fallback included), the method's jitted frame
function on patches already on the device (`frames_from_patches`, with the prepared `extra`
for methods that have one, prepared outside the clock), and `compute_frames(search="device")`
end to end. Each figure is the median of `--repeat` calls after a compiling one. On a CPU it
runs too (the device is then the CPU: slow, but the split is the same program's).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import jax  # noqa: E402

import lrf_jax  # noqa: E402
from lrf_jax.frames.normals_rule import method_normals, prepare_extra  # noqa: E402
from lrf_jax.search.device import DeviceIndex, build_patches_device  # noqa: E402
from bench_scale import dragon_cloud  # noqa: E402


def _cloud(n_points: int, data: str | None) -> tuple[np.ndarray, float]:
  _, mr, pts = dragon_cloud(n_points, data, np.random.default_rng(0))
  return pts, 15 * mr


def _median(fn, repeat: int) -> float:
  fn()  # compiles
  times = []
  for _ in range(repeat):
    t0 = time.perf_counter()
    fn()
    times.append(time.perf_counter() - t0)
  return float(np.median(times))


def _split(pts: np.ndarray, kp: np.ndarray, r: float, method: str, chunk: int,
           repeat: int) -> dict[str, float]:
  spec = lrf_jax.METHODS[method]
  k = spec.default_k
  t0 = time.perf_counter()
  index = DeviceIndex(pts, r, k, 0, spec.z_ratio)
  out = {"index": time.perf_counter() - t0}
  parts = [kp[i:i + chunk] for i in range(0, len(kp), chunk)]

  def search() -> list:
    found = [build_patches_device(pts, p, r, k, z_ratio=spec.z_ratio, index=index)[0]
             for p in parts]
    jax.block_until_ready(found)
    return found

  out["search"] = _median(search, repeat)
  patches = search()
  normals = method_normals(spec, pts, r)  # as compute_frames: the points-only view's normals
  extras = [prepare_extra(spec, pts, p, q, radius=r, normals=normals) for p, q in
            zip(parts, patches)]

  def frames() -> None:
    jax.block_until_ready([lrf_jax.frames_from_patches(q, method, extra=e)
                           for q, e in zip(patches, extras)])

  out["frames"] = _median(frames, repeat)
  out["compute_frames"] = _median(lambda: jax.block_until_ready(lrf_jax.compute_frames(
      pts, kp, r, method, search="device", chunk_size=chunk, progress=False)), repeat)
  return out


def main() -> None:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--points", type=int, default=1_000_000)
  ap.add_argument("--keypoints", type=int, default=1_000_000)
  ap.add_argument("--chunks", type=int, nargs="+", default=[4096, 65536])
  ap.add_argument("--methods", nargs="+", default=["lrf_net", "lrf_net_plus"])
  ap.add_argument("--repeat", type=int, default=2)
  args = ap.parse_args()
  pts, r = _cloud(args.points, args.data)
  kp = np.random.default_rng(1).choice(len(pts), args.keypoints,
                                       replace=args.keypoints > len(pts))
  print(f"jax {jax.__version__} on {jax.devices()[0].platform}; {len(pts):,} points, "
        f"{len(kp):,} keypoints, r = {r:.4g}; seconds (median of {args.repeat}), and "
        "keypoints/s of the whole call\n")
  print("| method | chunk | index build | search | frames | compute_frames | frames/s |")
  print("|---|---:|---:|---:|---:|---:|---:|")
  for method in args.methods:
    for chunk in args.chunks:
      s = _split(pts, kp, r, method, chunk, args.repeat)
      print(f"| {method} | {chunk:,} | {s['index']:.2f} | {s['search']:.2f} | "
            f"{s['frames']:.2f} | {s['compute_frames']:.2f} | "
            f"{len(kp) / s['compute_frames']:,.0f} |", flush=True)


if __name__ == "__main__":
  main()
