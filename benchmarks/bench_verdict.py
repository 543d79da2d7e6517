"""Registration verdict: `lrf_jax.register(...).success` on pairs that must register (the 9
consecutive Stanford bunny scans, BR scenes at 0.3 mr) and pairs that must not (two Gaussian blobs,
a mirrored scan, two different BR models, two disjoint halves of one scan); prints a Markdown table.

    LRF_DATA=/path/to/data python benchmarks/bench_verdict.py
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from lrf_jax import datasets  # noqa: E402
from lrf_jax.registration import register, rotation_error_deg  # noqa: E402
print("| pair | expected | inliers | chance | rival | fitness | err_r deg | success | reason |")
print("|---|---|---:|---:|---:|---:|---:|---|---|")
def run(name, a, b, expect, gt=None, **kw):
  r = register(a, b, **kw)
  e = f"{rotation_error_deg(r.transform[:3,:3], gt[:3,:3]):.2f}" if gt is not None else "-"
  print(f"| {name} | {expect} | {r.n_inliers} | {r.chance_inliers} | {r.rival_inliers} | {r.fitness:.3f} | {e} | {r.success} | {r.reason} |", flush=True)
pairs = datasets.load_bunny_pairs(None)
for p in pairs:
  run("bunny " + p.name, p.model_points, p.scene_points, "success", p.transform)
for p in datasets.load_br(None, 0.3)[:6]:
  run("BR " + p.name, p.model_points, p.scene_points, "success", p.transform)
rng = np.random.default_rng(0)
a = rng.normal(size=(20000, 3))
b = rng.normal(size=(20000, 3))
run("two Gaussian blobs", a, b, "failure", mr=float(datasets.mesh_resolution(a)[0]))
p0 = pairs[0]
run("bun000 -> mirrored bun045", p0.model_points, p0.scene_points * [-1, 1, 1], "failure")
m1 = datasets.load_br_model("bunny", None).points
m2 = datasets.load_br_model("dragon", None).points
run("BR bunny -> BR dragon", m1, m2, "failure")
m3 = datasets.load_br_model("armadillo", None).points
run("BR armadillo -> BR bunny", m3, m1, "failure")
pts = p0.model_points
half = pts[:, 0] < np.median(pts[:, 0])
run("bun000: disjoint halves", pts[half], pts[~half], "failure")
