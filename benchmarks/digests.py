"""Digests of what the library computes, to show that a restructuring changed nothing: sha256 of
every method's frames on a demo mesh, of the registrations of real pairs (clean bunny scans,
raw KITTI sweeps, 3DMatch rooms) and of a multiway model, each printed as one line.

    python benchmarks/digests.py > after.txt      # then the same at another commit, and diff

Run the same script at two commits (`git worktree add /tmp/base REV`, then
`PYTHONPATH=/tmp/base python benchmarks/digests.py`) and compare: a line that differs names
what moved. Needs the real data (LRF_DATA or ../shared/data) for the registrations.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import numpy as np


def _digest(*arrays) -> str:
  h = hashlib.sha256()
  for a in arrays:
    a = np.ascontiguousarray(np.asarray(a))
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
  return h.hexdigest()[:16]


def frames_digests() -> dict[str, str]:
  import lrf_jax
  from lrf_jax.datasets.synthetic import make_demo_mesh
  mesh = make_demo_mesh("blob", seed=0)
  verts, faces = np.asarray(mesh[0], np.float32), np.asarray(mesh[1])
  rng = np.random.default_rng(0)
  keys = np.sort(rng.choice(len(verts), 200, replace=False))
  mr = float(lrf_jax.mesh_resolution(verts, faces))
  out = {}
  for method in sorted(lrf_jax.METHODS):
    spec = lrf_jax.METHODS[method]
    kw = dict(faces=faces) if getattr(spec, "needs_mesh", False) else {}
    try:
      frames, valid = lrf_jax.compute_frames(verts, keys, 15 * mr, method=method, **kw)
    except (ValueError, TypeError) as e:
      out[f"frames {method}"] = f"error {type(e).__name__}"
      continue
    out[f"frames {method}"] = _digest(frames, valid)
  return out


def registration_digests(data: Path) -> dict[str, str]:
  import lrf_jax
  bunny = data / "stanford_bunny_scans"
  kitti = data / "lidar_kitti00"
  rooms = data / "threedmatch_scenes"
  pairs = [("bunny 000-045", bunny / "bun000.ply", bunny / "bun045.ply"),
           ("bunny 045-090", bunny / "bun045.ply", bunny / "bun090.ply"),
           ("bunny 315-000", bunny / "bun315.ply", bunny / "bun000.ply"),
           ("kitti 0-1", kitti / "000000.bin", kitti / "000001.bin"),
           ("kitti 2-4", kitti / "000002.bin", kitti / "000004.bin"),
           ("room home_at 38-41", rooms / "home_at_38.ply", rooms / "home_at_41.ply"),
           ("room hotel3 8-15", rooms / "hotel3_8.ply", rooms / "hotel3_15.ply")]
  out = {}
  for label, s, t in pairs:
    if not (s.exists() and t.exists()):
      continue
    reg = lrf_jax.register(str(s), str(t))
    out[f"register {label}"] = (f"{_digest(np.asarray(reg.transform, np.float64))} "
                                f"success={reg.success}")
  scans = [str(bunny / f"{n}.ply") for n in ("bun000", "bun045", "bun090")]
  if all(Path(p).exists() for p in scans):
    res = lrf_jax.register_all(scans)
    out["register_all bunny 000 045 090"] = _digest(res.poses)
  return out


def main() -> int:
  root = Path(__file__).resolve().parents[1]
  data = Path(os.environ.get("LRF_DATA") or root.parent / "shared" / "data")
  lines = {**frames_digests(), **(registration_digests(data) if data.is_dir() else {})}
  for key, value in lines.items():
    print(f"{key}\t{value}")
  sys.stdout.flush()
  return 0


if __name__ == "__main__":
  sys.exit(main())
