"""Register two scans with LRF-Net frames: `python -m lrf_jax.register_cli SRC TGT [--out T.txt]`.

Prints the 4 x 4 transform that maps SRC onto TGT (rows, 9 significant digits), the inlier count
of the coarse estimate, the final overlap (fitness) and RMSE and the verdict
(`Registration.success`; exit code 3 when it failed, 2 for bad input); `--out` also writes the matrix as
text (`numpy.loadtxt` reads it back). Inputs: any cloud or mesh `lrf_jax.io.read_cloud` reads
(PLY, PCD, XYZ/TXT(.gz), NPY). Every length is in mesh resolutions of SRC unless `--mr` is given.
This file is intentionally thin; the pipeline is `lrf_jax.registration.register`.

    python -m lrf_jax.register_cli bun000.ply bun045.ply --out bun000_to_bun045.txt
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(prog="lrf-register",
                               description="Rigid registration of two scans with learned LRFs "
                                           "(LRF-Net frames, TOLDI matching, one-point RANSAC, "
                                           "ICP).")
  ap.add_argument("source", help="the cloud to move (PLY, PCD, XYZ/TXT(.gz), NPY)")
  ap.add_argument("target", help="the cloud to align it to")
  ap.add_argument("--out", default=None, help="write the 4x4 source->target matrix here")
  ap.add_argument("--mr", type=float, default=None,
                  help="mesh resolution in the clouds' units (default: measured on SOURCE)")
  ap.add_argument("--radius-mr", type=float, default=15.0, help="support radius in mr (15)")
  ap.add_argument("--keypoints", type=int, default=3000, help="keypoints per cloud (3000)")
  ap.add_argument("--correspondences", type=int, default=1000,
                  help="correspondences kept after matching (1000)")
  ap.add_argument("--inlier-mr", type=float, default=5.0, help="inlier distance in mr (5)")
  ap.add_argument("--estimator", choices=("lrf", "3point"), default="lrf",
                  help="one correspondence per hypothesis (lrf) or classic 3-point RANSAC")
  ap.add_argument("--iterations", type=int, default=1000, help="3-point RANSAC hypotheses")
  ap.add_argument("--icp-iterations", type=int, default=50, help="ICP iterations (0: none)")
  ap.add_argument("--checkpoint", default=None,
                  help="a train.py workdir whose best LRF-Net parameters to use "
                       "(default: the shipped weights)")
  ap.add_argument("--method", default="lrf_net_plus",
                  help="LRF method, a key of lrf_jax.METHODS (default lrf_net_plus, the most "
                       "repeatable; lrf_net is the paper's LRF-Net)")
  ap.add_argument("--source-viewpoint", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                  help="sensor position of a single-view SOURCE scan (orients its normals)")
  ap.add_argument("--target-viewpoint", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                  help="sensor position of a single-view TARGET scan")
  ap.add_argument("--seed", type=int, default=0)
  return ap


def _check_paths(args: argparse.Namespace) -> str | None:
  """What is wrong with --out or --checkpoint, checked before any work is done (None: fine)."""
  from pathlib import Path
  if args.out:
    parent = Path(args.out).expanduser().resolve().parent
    if not parent.is_dir():
      return f"--out: the folder {parent} does not exist (create it, or pick another path)"
  if args.checkpoint and not Path(args.checkpoint).expanduser().is_dir():
    return (f"--checkpoint: {args.checkpoint} is not a folder; expected a train.py workdir "
            "(the one passed to train.py --workdir)")
  return None


def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  problem = _check_paths(args)
  if problem:
    print(f"error: {problem}", file=sys.stderr)
    return 2
  from lrf_jax import compilation_cache
  compilation_cache.enable()  # a second run loads the compiled functions instead of recompiling
  from lrf_jax.registration import register

  params = None
  if args.checkpoint:
    from lrf_jax.checkpoints import restore_params
    params, _ = restore_params(args.checkpoint, "best")
  try:
    reg = register(args.source, args.target, mr=args.mr, radius_mr=args.radius_mr,
                   n_keypoints=args.keypoints, n_correspondences=args.correspondences,
                   inlier_mr=args.inlier_mr, estimator=args.estimator,
                   iterations=args.iterations, icp_iterations=args.icp_iterations,
                   params=params, seed=args.seed, method=args.method,
                   source_viewpoint=args.source_viewpoint,
                   target_viewpoint=args.target_viewpoint)
  except (ValueError, FileNotFoundError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  text = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in reg.transform)
  print(text)
  print(f"# inliers {reg.n_inliers}/{len(reg.correspondences)} (coarse; chance level "
        f"{reg.chance_inliers}), overlap contrast {reg.overlap_contrast:.2f}, fitness "
        f"{reg.fitness:.3f}, rmse {reg.rmse / reg.mr:.3f} mr, mr {reg.mr:.6g}, "
        f"{reg.seconds:.1f} s", file=sys.stderr)
  print(f"# verdict: {'success' if reg.success else 'FAILED (do not trust this transform)'}",
        file=sys.stderr)
  if args.out:
    np.savetxt(args.out, reg.transform, fmt="%.9g")
  return 0 if reg.success else 3


if __name__ == "__main__":
  sys.exit(main())
