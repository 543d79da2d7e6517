"""`lrf-frames CLOUD --out F.npz`: local reference frames for the keypoints of one's own file.

Reads any cloud or mesh `lrf_jax.io.read_cloud` reads (PLY, PCD, XYZ/TXT(.gz), NPY), picks
keypoints (N seeded random points, all points, or one point per voxel of S mr), computes their
frames (and optionally a descriptor) and writes an .npz with `keypoints` (indices), `positions`,
`frames` (m, 3, 3, rows x, y, z), `valid` (m,), `radius`, `mr`, `method`, `weights` and
`descriptors` when asked; `--png` draws the frames on the cloud. This file is intentionally thin:
the work is `lrf_jax.compute_frames`.

    lrf-frames scan.ply --out scan_frames.npz --keypoints 2000 --viewpoint 0 0 0 --png f.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(prog="lrf-frames", description="Local reference frames of the "
                               "keypoints of a cloud or mesh file, written to an .npz.")
  ap.add_argument("cloud", help="PLY, PCD, XYZ/TXT(.gz) or NPY file")
  ap.add_argument("--out", required=True, help="the .npz to write")
  ap.add_argument("--keypoints", default="1000",
                  help="N seeded random points, or 'all' (default 1000)")
  ap.add_argument("--voxel-mr", type=float, default=None,
                  help="keypoints: the point nearest each voxel centre, voxels of S mr "
                       "(instead of --keypoints)")
  ap.add_argument("--method", default="lrf_net_plus",
                  help="a key of lrf_jax.METHODS (default lrf_net_plus)")
  ap.add_argument("--radius-mr", type=float, default=15.0,
                  help="support radius in mesh resolutions (default 15, the paper's)")
  ap.add_argument("--viewpoint", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                  help="sensor position of a single-view scan (orients normals and z)")
  ap.add_argument("--descriptor", default=None,
                  help="also a descriptor on the frames (snapshots, shot, rops, toldi)")
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--png", default=None, help="also draw the frames on the cloud here")
  return ap


def _check(args: argparse.Namespace) -> str | None:
  """What is wrong with the arguments, before any work (None: fine)."""
  from lrf_jax.descriptors import DESCRIPTORS
  from lrf_jax.frames import METHODS
  if args.method not in METHODS:
    return f"--method: unknown method {args.method!r}; expected one of {sorted(METHODS)}"
  if args.descriptor is not None and args.descriptor not in DESCRIPTORS:
    return f"--descriptor: unknown {args.descriptor!r}; expected one of {sorted(DESCRIPTORS)}"
  if args.keypoints != "all" and (not args.keypoints.isdigit() or int(args.keypoints) < 1):
    return f"--keypoints: expected a positive integer or 'all', got {args.keypoints!r}"
  for name in ("radius_mr", "voxel_mr"):
    v = getattr(args, name)
    if v is not None and not (np.isfinite(v) and v > 0):
      return f"--{name.replace('_', '-')}: expected a positive number, got {v!r}"
  for name in ("out", "png"):
    v = getattr(args, name)
    if v is not None and not Path(v).expanduser().resolve().parent.is_dir():
      return f"--{name}: the folder {Path(v).expanduser().resolve().parent} does not exist"
  return None


def select_keypoints(points: np.ndarray, how: str, voxel: float | None, seed: int) -> np.ndarray:
  """Sorted keypoint indices: every point ('all'), N seeded random ones, or with `voxel` (cloud
  units) the point nearest the centre of each occupied voxel."""
  n = len(points)
  if voxel is not None:
    cells = np.floor((points - points.min(0)) / voxel).astype(np.int64)
    centre = (cells + 0.5) * voxel + points.min(0)
    d = np.linalg.norm(points - centre, axis=1)
    _, inv = np.unique(cells, axis=0, return_inverse=True)
    order = np.lexsort((d, inv.ravel()))
    first = np.r_[True, np.diff(inv.ravel()[order]) != 0]
    return np.sort(order[first])
  if how == "all":
    return np.arange(n)
  m = min(int(how), n)
  return np.sort(np.random.default_rng(seed).choice(n, m, replace=False))


def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  problem = _check(args)
  if problem:
    print(f"error: {problem}", file=sys.stderr)
    return 2
  from lrf_jax import compilation_cache
  compilation_cache.enable()
  import lrf_jax
  from lrf_jax.inputs import as_cloud
  try:
    cloud = as_cloud(args.cloud, "cloud")
    mr = lrf_jax.mesh_resolution(cloud.points, cloud.faces)
    kp = select_keypoints(cloud.points, args.keypoints,
                          None if args.voxel_mr is None else args.voxel_mr * mr, args.seed)
    radius = args.radius_mr * mr
    frames, valid = lrf_jax.compute_frames(cloud, kp, radius, args.method, seed=args.seed,
                                           viewpoint=args.viewpoint, progress=len(kp) > 20000)
    out = dict(keypoints=kp, positions=cloud.points[kp], frames=np.asarray(frames),
               valid=np.asarray(valid), radius=radius, mr=mr, method=args.method,
               weights=lrf_jax.METHODS[args.method].weights
               if lrf_jax.METHODS[args.method].needs_params else "")
    if args.descriptor:
      from lrf_jax.descriptors import compute_descriptors
      desc, _ = compute_descriptors(cloud.points, kp, radius, frames, valid, args.descriptor,
                                    faces=cloud.faces, seed=args.seed)
      out["descriptors"] = np.asarray(desc)
  except (ValueError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  np.savez(args.out, **out)
  if args.png:
    from lrf_jax import plot
    plot.frames(cloud.points, kp, out["frames"], args.png, valid=out["valid"],
                title=f"{Path(args.cloud).name}: {args.method} frames at {args.radius_mr:g} mr")
  print(f"{len(kp)} keypoints, {int(out['valid'].sum())} valid frames ({args.method}, r = "
        f"{args.radius_mr:g} mr = {radius:.6g}) -> {args.out}", file=sys.stderr)
  return 0


if __name__ == "__main__":
  sys.exit(main())
