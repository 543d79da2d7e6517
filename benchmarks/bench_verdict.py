"""Registration verdict: `lrf_jax.register(...).success` on pairs that must register (the 9
consecutive Stanford bunny scans, BR scenes at 0.3 mr) and pairs that must not (two Gaussian blobs,
a mirrored scan, two different BR models, two disjoint halves of one scan, two identical copies of
an object side by side, a plane against the same plane shifted within itself, fragments of two
different 3DMatch rooms both ways, a room against a raw KITTI sweep, a KITTI sweep against a
synthetic street sweep) and pairs that
may register but not a period off (two LiDAR sweeps along a street whose facades repeat,
`datasets.make_street_pair`); prints a Markdown table with the verdict's `reason_code`.

    LRF_DATA=/path/to/data python benchmarks/bench_verdict.py [--options [--only JSON]] [--inits]
        [--multiway] [--failures-only] [--effort fast|normal|high]

With `--options` the must-not pairs run again under every option that chooses the hypotheses
differently (estimator "lrf" and "3point", ratio=0.9, mutual, ISS keypoints, the room and street
weights): the verdict is one for all, so none of them may claim success either; `--only JSON`
runs one option instead of all (`--options --only '{"weights": "rooms"}'`); `--failures-only`
runs the must-not rows alone (and under the options). `--effort high` runs every row with
`register(..., effort="high")` (more keypoints and seeds, pooled). The last lines count the
claims of the must-register rows and the false claims of the must-not rows.

With `--inits` the must-not pairs run again from two wrong inits (`register(..., init=T)`: the
identity, and a seeded random rotation that puts the source's centroid on the target's), and
the streets from those and from the truth shifted one facade period along the street: no init
may be claimed where the pair must not register, nor at a wrong pose on a street.

With `--multiway`, `register_all` on sets of scans that belong together with one or
two foreign scans mixed in (10 bunny scans + UWA3M views in metres or a 3DMatch fragment scaled
to the bunny's size; the 3DMatch hotel pair + the home pair, a T-rex view and a bunny scan scaled
to a room's size), seeds 0-2: a table of the foreign scans placed (must be none), the belonging
scans placed and those placed only through "not sure" edges. Slow: 12 scans are 66 pairs.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from lrf_jax import datasets  # noqa: E402
from lrf_jax.io import read_cloud  # noqa: E402
from lrf_jax.registration import register, rotation_error_deg  # noqa: E402

EFFORT = sys.argv[sys.argv.index("--effort") + 1] if "--effort" in sys.argv else "normal"
# expected -> [claimed, rows]; "ambiguous" (a pose a period off fits about as well as the
# truth): [claimed at a wrong pose, rows]
TALLY = {"success": [0, 0], "failure": [0, 0], "ambiguous": [0, 0]}
OPTIONS = ({"estimator": "lrf"}, {"estimator": "3point"}, {"ratio": 0.9}, {"mutual": True},
           {"keypoints": "iss"}, {"weights": "rooms"}, {"weights": "streets"})
if "--only" in sys.argv:  # one option of OPTIONS (or any), as JSON: --only '{"weights": "rooms"}'
  OPTIONS = (json.loads(sys.argv[sys.argv.index("--only") + 1]),)
print("| pair | options | expected | inliers | chance | rival | fitness | err_r deg | success | "
      "code | reason |")
print("|---|---|---|---:|---:|---:|---:|---:|---|---|---|")


def run(name, a, b, expect, gt=None, init_label=None, **kw):
  opts = ", ".join(f"{k}={v}" for k, v in kw.items() if k not in ("mr", "init")) or "default"
  if init_label:
    opts = f"{opts}, init {init_label}"
  TALLY[expect][1] += 1
  try:
    r = register(a, b, effort=EFFORT, **kw)
  except ValueError as e:
    print(f"| {name} | {opts} | {expect} | - | - | - | - | - | False | error | {e} |", flush=True)
    return
  wrong = gt is not None and (rotation_error_deg(r.transform[:3, :3], gt[:3, :3]) > 2.0 or
                              np.linalg.norm(r.transform[:3, 3] - gt[:3, 3]) > 0.5)
  TALLY[expect][0] += int(r.success and (expect != "ambiguous" or wrong))
  e = f"{rotation_error_deg(r.transform[:3,:3], gt[:3,:3]):.2f}" if gt is not None else "-"
  print(f"| {name} | {opts} | {expect} | {r.evidence_inliers} | {r.chance_inliers} | "
        f"{r.rival_inliers} | {r.fitness:.3f} | {e} | {r.success} | {r.reason_code} | "
        f"{r.reason} |", flush=True)


FAILURES_ONLY = "--failures-only" in sys.argv  # the must-not rows alone (and their options)
pairs = datasets.load_bunny_pairs(None)
for p in pairs if not FAILURES_ONLY else ():
  run("bunny " + p.name, p.model_points, p.scene_points, "success", p.transform)
for p in datasets.load_br(None, 0.3)[:6] if not FAILURES_ONLY else ():
  run("BR " + p.name, p.model_points, p.scene_points, "success", p.transform)


def failures():
  """(name, source, target, keywords) of the pairs that must not register."""
  rng = np.random.default_rng(0)
  a = rng.normal(size=(20000, 3))
  b = rng.normal(size=(20000, 3))
  yield "two Gaussian blobs", a, b, {"mr": float(datasets.mesh_resolution(a)[0])}
  p0 = pairs[0]
  yield "bun000 -> mirrored bun045", p0.model_points, p0.scene_points * [-1, 1, 1], {}
  m1 = datasets.load_br_model("bunny", None).points
  m2 = datasets.load_br_model("dragon", None).points
  yield "BR bunny -> BR dragon", m1, m2, {}
  m3 = datasets.load_br_model("armadillo", None).points
  yield "BR armadillo -> BR bunny", m3, m1, {}
  pts = p0.model_points
  half = pts[:, 0] < np.median(pts[:, 0])
  yield "bun000: disjoint halves", pts[half], pts[~half], {}
  # two identical copies of bun000 side by side: the correspondences split between them; as
  # scanned (independent noise of 0.1 mr on each copy) and as exact digital copies (then ISS
  # picks the same points on both, every descriptor ties and all matches go to one copy)
  r = Rotation.from_euler("xyz", [30, 50, 10], degrees=True).as_matrix()
  copy = pts @ r.T
  shift = 1.5 * float(np.ptp(pts, axis=0).max())
  mr = float(datasets.mesh_resolution(pts)[0])
  g = np.random.default_rng(2)
  scanned = [copy + g.normal(scale=0.1 * mr, size=copy.shape) + [dx, 0, 0] for dx in (0, shift)]
  yield "bun000 -> two scanned copies side by side", pts, np.concatenate(scanned), {}
  yield "bun000 -> two exact copies side by side", pts, np.concatenate([copy, copy + [shift, 0, 0]]), {}
  # a plane against the same plane shifted within itself: every in-plane shift fits
  g = np.random.default_rng(1)
  plane_a = np.c_[g.uniform(-20, 20, size=(20000, 2)), 0.02 * g.normal(size=20000)]
  plane_b = np.c_[g.uniform(-20, 20, size=(20000, 2)) + [8, 0], 0.02 * g.normal(size=20000)]
  yield "plane -> plane shifted within itself", plane_a, plane_b, {}
  # unrelated scenes: two rooms of different 3DMatch scenes (both ways), a room against a raw
  # LiDAR sweep, and a raw KITTI sweep against a synthetic street sweep (this data holds one
  # KITTI sequence only)
  rooms = {p.name: p for p in datasets.load_threedmatch_scenes(None)}
  hotel, home = rooms["hotel3_8_15"].model_points, rooms["home_at_38_41"].model_points
  yield "3DMatch hotel3 -> home_at fragment", hotel, home, {}
  yield "3DMatch home_at -> hotel3 fragment", home, hotel, {}
  sweep = read_cloud(datasets.find_data_root(None) / "lidar_kitti00" / "000000.bin").points
  yield "3DMatch hotel3 fragment -> KITTI sweep", hotel, sweep, {}
  yield "KITTI sweep -> synthetic street sweep", sweep, \
      datasets.make_street_pair(4.0, 4.0, seed=0).scene_points, {}


def streets():
  """(name, pair) of the streets with repeating facades (`datasets.make_street_pair`), metres:
  a pose a period off explains the facades about as well as the true one."""
  for period, shift, kw in ((4.0, 4.0, {}), (4.0, 2.0, {}), (4.0, 8.0, {"both_sides": False}),
                            (5.0, 5.0, {"both_sides": False, "pole_period": 10.0}),
                            (4.0, 12.0, {})):
    for seed in (0, 1, 2):
      pair = datasets.make_street_pair(period, shift, seed=seed, **kw)
      yield f"street: facades every {period:g} m, sweeps {shift:g} m apart, seed {seed}", pair


for name, a, b, kw in failures():
  run(name, a, b, "failure", **kw)
for name, pair in streets() if not FAILURES_ONLY else ():
  run(name, pair.model_points, pair.scene_points, "ambiguous", pair.transform)
if "--options" in sys.argv[1:]:
  for options in OPTIONS:
    for name, a, b, kw in failures():
      run(name, a, b, "failure", **kw, **options)
    for name, pair in streets() if not FAILURES_ONLY else ():
      run(name, pair.model_points, pair.scene_points, "ambiguous", pair.transform, **options)



def guesses(a, b, seed):
  """(label, init) of `--inits`' wrong guesses for a pair: the identity, and a seeded random
  rotation with the translation that puts the source's centroid on the target's."""
  rot = Rotation.random(random_state=seed).as_matrix()
  guess = np.eye(4)
  guess[:3, :3] = rot
  guess[:3, 3] = np.mean(b, axis=0) - rot @ np.mean(a, axis=0)
  yield "identity", np.eye(4)
  yield "random", guess


if "--inits" in sys.argv[1:]:
  for i, (name, a, b, kw) in enumerate(failures()):
    for label, init in guesses(a, b, i):
      run(name, a, b, "failure", **kw, init=init, init_label=label)
  for i, (name, pair) in enumerate(streets() if not FAILURES_ONLY else ()):
    period = float(name.split("every ")[1].split(" m")[0])
    off = pair.transform.copy()
    off[0, 3] += period  # one period along the street (x): a wrong init the facades fit
    run(name, pair.model_points, pair.scene_points, "ambiguous", pair.transform, init=off,
        init_label="the truth a period off")
    for label, init in guesses(pair.model_points, pair.scene_points, 100 + i):
      run(name, pair.model_points, pair.scene_points, "ambiguous", pair.transform, init=init,
          init_label=label)

print(f"\neffort={EFFORT}: must register: {TALLY['success'][0]} of {TALLY['success'][1]} "
      f"claimed; must not: {TALLY['failure'][0]} of {TALLY['failure'][1]} claimed (false "
      f"successes); ambiguous streets: {TALLY['ambiguous'][0]} of {TALLY['ambiguous'][1]} "
      "claimed at a wrong pose (false successes)")


def multiway_sets():
  """(name, scans, names, belonging count) of the mixed sets of `--multiway`."""
  import gzip

  from lrf_jax import io
  root = datasets.find_data_root(None)

  def uwa(name, scale):
    with gzip.open(root / "uwa_3d_modeling_views" / f"{name}.txt.gz") as f:
      return np.loadtxt(f) * scale
  bunny = ["bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "chin", "ear_back",
           "top2", "top3"]
  scans = [io.read_cloud(root / "stanford_bunny_scans" / f"{n}.ply").points for n in bunny]
  hotel = io.read_cloud(root / "threedmatch_scenes" / "hotel3_8.ply").points
  foreign = {"trex1": uwa("T-rex_view001", 1e-3), "chef3": uwa("chef_view003", 1e-3),
             "hotel3_8_x0.06": hotel * 0.06}
  for extra in (["trex1"], ["chef3"], ["hotel3_8_x0.06"], ["trex1", "chef3"]):
    yield ("bunny + " + ", ".join(extra), scans + [foreign[f] for f in extra], bunny + extra,
           len(bunny))
  rooms = ["hotel3_8", "hotel3_15"]
  frags = [io.read_cloud(root / "threedmatch_scenes" / f"{n}.ply").points for n in rooms]
  bun = io.read_cloud(root / "stanford_bunny_scans" / "bun090.ply").points * 15
  home = [io.read_cloud(root / "threedmatch_scenes" / f"{n}.ply").points
          for n in ("home_at_38", "home_at_41")]
  for label, extra, names in (("T-rex view x0.01", [uwa("T-rex_view004", 1e-2)], ["trex4"]),
                              ("bun090 x15, home_at_38", [bun, home[0]], ["bun090_x15",
                                                                          "home_at_38"]),
                              ("home pair", home, ["home_at_38", "home_at_41"])):
    yield f"hotel pair + {label}", frags + extra, rooms + names, len(rooms)


if "--multiway" in sys.argv[1:]:
  from lrf_jax.multiway import register_all
  print("\n| set | seed | foreign placed | belonging placed | placed only through not sure |")
  print("|---|---:|---|---:|---|")
  for name, scans, names, n_belong in multiway_sets():
    for seed in (0, 1, 2):
      res = register_all(scans, names=names, seed=seed, refine=False)
      placed = [n for n, m in zip(names, res.in_model) if m]
      intruders = ", ".join(n for n in placed if n not in names[:n_belong]) or "none"
      print(f"| {name} | {seed} | {intruders} | {sum(n in placed for n in names[:n_belong])}/"
            f"{n_belong} | {', '.join(res.placed_not_sure) or '-'} |", flush=True)
