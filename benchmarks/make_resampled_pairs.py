"""A scan set of resampled copies: more training pairs from a few scans (rooms' fragments).

    python benchmarks/make_resampled_pairs.py OUT_DIR SCAN [SCAN ...] [--pairs-from DIR]
        [--copies 3] [--noise-mr 0.25] [--keep 0.6] [--seed 0]

Each SCAN (any file `lrf_jax.io.read_cloud` reads) and `--copies` copies of it go into OUT_DIR
as a 3DMatch-layout scan set (`cloud_bin_<k>.ply` and `gt.log`, `lrf_jax.datasets.scan_sets`),
one `gt.log` record per (scan, copy). A copy is what another scan of the same surface gives:

* the scan voxel-averaged again on a grid shifted by a random offset (voxel = 2 mr, the scan's
  working resolution: a 2.5 cm fragment's own voxel), so no point keeps its position;
* Gaussian noise of `--noise-mr` mr on every coordinate;
* cut by a random plane through the cloud keeping at least `--keep` of its points (a scan's
  boundary);
* moved by a random rotation and translation (the ground truth of its record).

`--pairs-from DIR` also copies a scan set's real pairs (its scans and `gt.log` records) in,
renumbered. Train with `scan_match_mr=1.0` (the copies' points lie within a voxel of the
originals', not within 0.5 mr). Seeded: the same files on every run. Every file goes to a
temporary name and is renamed into place; an OUT_DIR that holds an input is refused.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
  sys.path.insert(0, str(REPO))

from lrf_jax.datasets.scan_sets import read_scan_set  # noqa: E402
from lrf_jax.geometry.resolution import working_resolution  # noqa: E402
from lrf_jax.geometry.sampling import voxel_downsample  # noqa: E402
from lrf_jax.io import read_cloud  # noqa: E402
from lrf_jax.io.atomic import write_text  # noqa: E402
from lrf_jax.io.ply import write_ply  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402


def resampled_copy(points: np.ndarray, mr: float, rng: np.random.Generator, *,
                   noise_mr: float, keep: float) -> tuple[np.ndarray, np.ndarray]:
  """(copy (m, 3), transform (4, 4) mapping `points`' frame onto the copy's)."""
  voxel = 2.0 * mr
  offset = rng.uniform(0.0, voxel, size=3)
  copy = np.asarray(voxel_downsample(points + offset, voxel)) - offset
  copy = copy + rng.normal(scale=noise_mr * mr, size=copy.shape)
  normal = rng.normal(size=3)
  normal /= np.linalg.norm(normal)
  h = (copy - copy.mean(0)) @ normal
  cut = np.quantile(h, rng.uniform(0.0, 1.0 - keep))  # drop at most 1 - keep of the points
  copy = copy[h >= cut]
  transform = np.eye(4)
  transform[:3, :3] = Rotation.random(random_state=rng).as_matrix()
  transform[:3, 3] = rng.normal(scale=np.ptp(points, axis=0).max() / 4, size=3)
  return copy @ transform[:3, :3].T + transform[:3, 3], transform


def main(argv: list[str] | None = None) -> int:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
  ap.add_argument("out", help="the scan set folder to write (created)")
  ap.add_argument("scans", nargs="+", help="the scans to copy")
  ap.add_argument("--pairs-from", default=None, metavar="DIR",
                  help="also this scan set's real pairs (scans and gt.log records)")
  ap.add_argument("--copies", type=int, default=3, help="copies per scan")
  ap.add_argument("--noise-mr", type=float, default=0.25, help="Gaussian noise, in mr")
  ap.add_argument("--keep", type=float, default=0.6, help="a copy keeps at least this share")
  ap.add_argument("--seed", type=int, default=0)
  args = ap.parse_args(argv)
  out = Path(args.out)
  inputs = [Path(s) for s in args.scans] + ([Path(args.pairs_from)] if args.pairs_from else [])
  for p in inputs:  # its cloud_bin_<k>.ply and gt.log would overwrite them
    if out.resolve() == p.resolve() or out.resolve() in p.resolve().parents:
      ap.error(f"OUT_DIR {out}: holds the input {p}; write the scan set elsewhere")
  out.mkdir(parents=True, exist_ok=True)
  rng = np.random.default_rng(args.seed)
  records, k = [], 0
  for scan in args.scans:
    points = read_cloud(scan).points
    mr = working_resolution(points).mr
    write_ply(out / f"cloud_bin_{k}.ply", points)
    source = k
    k += 1
    for _ in range(args.copies):
      copy, transform = resampled_copy(points, mr, rng, noise_mr=args.noise_mr, keep=args.keep)
      write_ply(out / f"cloud_bin_{k}.ply", copy)
      # gt.log "i j n" maps fragment j onto fragment i: the copy (j) back onto its scan (i)
      records.append((source, k, np.linalg.inv(transform)))
      k += 1
  if args.pairs_from:
    real = read_scan_set(args.pairs_from, min_overlap=1e-6)
    first = k
    for name in real.scans:
      write_ply(out / f"cloud_bin_{k}.ply", read_cloud(Path(args.pairs_from) / name).points)
      k += 1
    kept = [c for c in real.candidates if c[2] >= 1e-6]  # the pairs, in their order
    for (source, target, _), pair in zip(kept, real.pairs):
      records.append((first + target, first + source, np.asarray(pair.transform)))
  lines = []
  for i, j, t in records:
    lines.append(f"{i} {j} {k}")
    lines += [" ".join(f"{v:.9e}" for v in row) for row in t]
  write_text(out / "gt.log", "\n".join(lines) + "\n")
  print(f"{out}: {k} scans, {len(records)} pairs")
  return 0


if __name__ == "__main__":
  sys.exit(main())
