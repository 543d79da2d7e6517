"""The paper's repeatability experiments (sections 3.2.1 and 3.3) over datasets and nuisances.

Each experiment yields records (see `repeatability.evaluate_pair`); `report.py` turns them into
tables and figures. Datasets are looked up by name in `DATASETS`; a dataset whose files are
absent is skipped with a message, never silently. The user's own scan sets
(`lrf_jax.datasets.scan_sets`, `EvalOptions.scans`) are data sets of their own, named by their
folders (`scan_set_names`): every experiment runs on them as on the others (their pairs, being
noise-free real scans as far as we know, are also their "clean" versions for the sweeps).
"""

from __future__ import annotations

import dataclasses
import zlib
from typing import Any, cast
from collections.abc import Callable, Iterable, Iterator

from lrf_jax.defaults import RADIUS_MR
from lrf_jax import datasets
from lrf_jax.datasets import Pair
from lrf_jax.datasets.scan_sets import folder_name
from lrf_jax.evaluation.repeatability import (EXACT_NETWORK, MAX_NEIGHBORS, MethodRun,
                                              PatchCache, evaluate_pair)

NOISE_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5)
DECIMATIONS = (1 / 2, 1 / 4, 1 / 8, 1 / 16)
RADII_MR = (5.0, 7.5, 10.0, 12.5, 15.0, 20.0, 25.0)
ROTATIONS_DEG = (30.0, 60.0, 90.0, 120.0)
EXPERIMENTS = ("repeatability", "noise", "decimation", "radius", "rotation", "ablation",
               "plus_ablation", "points_only")
# Experiments run on the named datasets as they are (the others on their noise-free versions).
AS_NAMED = ("repeatability", "plus_ablation", "points_only")
# The points_only experiment: its datasets when none are named, the pairs per dataset when no
# cap is given (a run of a few minutes on 2 CPU cores), the hand-crafted methods it runs when
# none are named, and the labels of lrf_net_plus's two columns.
POINTS_ONLY_DATASETS = ("UWA3M", "UWAOR", "bunny", "3DMatch")
POINTS_ONLY_PAIRS = 2
POINTS_ONLY_HANDCRAFTED = ("toldi", "shot", "flare", "board")
WITH_VIEWPOINT = "lrf_net_plus (viewpoint)"
POINTS_ALONE = "lrf_net_plus (points only)"
BALL_SIGN = "lrf_net_plus (points only, ball sign)"


def plus_ablation_runs() -> list[MethodRun]:
  """lrf_net_plus with each of its switches off in turn (beyond the paper):
  `oriented_sign` (z towards the sensor / the mesh's oriented normals; off = the ball sign only),
  `density` (weights times the area per point), the softmax x with its own weights (off = the
  paper's linear weights with the LRF-Net weights) and its patch size (512; 256 = LRF-Net's).
  LRF-Net as published is the reference."""
  from lrf_jax.frames.weights import default_params

  paper_x = dict(params=default_params("lrf_net"), options=(("x_mode", "sum"),))
  return [MethodRun("LRF-Net (paper)", "lrf_net", options=EXACT_NETWORK),
          MethodRun("plus: ball sign only", "lrf_net_plus",
                    options=(("density", False), ("oriented_sign", False))),
          MethodRun("plus: + oriented sign", "lrf_net_plus", options=(("density", False),)),
          MethodRun("plus: + density", "lrf_net_plus", options=(("oriented_sign", False),)),
          MethodRun("plus: linear x, LRF-Net weights", "lrf_net_plus", **paper_x),
          MethodRun("plus: K = 256", "lrf_net_plus", k=256),
          MethodRun("lrf_net_plus (shipped)", "lrf_net_plus")]


def points_only_runs(methods: Iterable[MethodRun] = ()) -> list[MethodRun]:
  """The columns of the points_only experiment: lrf_net_plus with the sensor position (and the
  faces, where the dataset has them), lrf_net_plus from the points alone, the same with the
  sign of the patch alone (`oriented_sign=False`: `lrf_net.ball_sign`, the rule used before z
  was oriented from the whole cloud), and the hand-crafted methods among `methods` that take a
  bare cloud (`POINTS_ONLY_HANDCRAFTED` when `methods` names none), from the points alone."""
  from lrf_jax.frames import METHODS
  plus = [r for r in methods if r.method == "lrf_net_plus"]
  base = plus[0] if plus else MethodRun("lrf_net_plus", "lrf_net_plus")
  hand = [r for r in methods if not METHODS[r.method].needs_params
          and not METHODS[r.method].needs_mesh]
  if not hand:
    hand = [MethodRun(m, m) for m in POINTS_ONLY_HANDCRAFTED]
  ball = dataclasses.replace(base, label=BALL_SIGN,
                             options=tuple(dict(base.options, oriented_sign=False).items()))
  return ([dataclasses.replace(base, label=WITH_VIEWPOINT),
           dataclasses.replace(base, label=POINTS_ALONE), ball]
          + [dataclasses.replace(r, label=f"{r.label} (points only)") for r in hand])


def motion_seed(seed: int, pair_name: str) -> int:
  """The seed of a pair's random rigid motions: the run's seed mixed with the pair's name (the
  same pair moves the same way in every run with that seed)."""
  return (zlib.crc32(pair_name.encode()) ^ (int(seed) * 0x9E3779B1)) & 0xFFFFFFFF


def points_only_pair(pair: Pair, runs: list[MethodRun], *, setting: dict[str, Any],
                     opts: EvalOptions, cache: PatchCache) -> list[dict[str, Any]]:
  """Records of one pair of the points_only experiment (beyond the paper).

  Both clouds are first moved by their own seeded random rigid motions
  (`datasets.with_random_motion`, seed `motion_seed`), so that no rule can lean on a sensor
  position hidden in the files' coordinates. The first run (`WITH_VIEWPOINT`) sees the moved
  pair as the dataset gives it (sensor positions moved with their clouds, faces where there
  are); every other run sees the bare clouds (`datasets.points_only`: no faces, no sensor
  position). A pair without a sensor position on either side has no viewpoint column (a record
  with meancos None). Records carry MeanCos and z_flip (`repeatability.z_flip_rate`).
  """
  moved = datasets.with_random_motion(pair, motion_seed(opts.seed, pair.name))
  common: dict[str, Any] = dict(experiment="points_only", n_keypoints=opts.n_keypoints, seed=opts.seed,
                radius_mr=opts.radius_mr, cache=cache, max_neighbors=opts.max_neighbors)
  setting = dict(setting, motion_seed=motion_seed(opts.seed, pair.name))
  records = []
  view_run, rest = runs[0], runs[1:]
  if moved.model_viewpoint is None and moved.scene_viewpoint is None:
    records.append({"experiment": "points_only", "dataset": pair.dataset, "pair": pair.name,
                    "setting": setting, "method": view_run.label, "meancos": None,
                    "frac_above_0.97": None, "z_flip": None, "n_keypoints": 0, "n_valid": 0,
                    "note": "n/a: the pair records no sensor position"})
  else:
    records += evaluate_pair(moved, [view_run], setting=setting, **common)
  records += evaluate_pair(datasets.points_only(moved), rest, setting=setting, **common)
  return records


ABLATION_Z = ("Normal", "DR")
ABLATION_X = ("Sum1", "Sum2", "DR", "Max")


def ablation_runs() -> list[MethodRun]:
  """The 8 variants of the paper's section 3.3 with the shipped ablation weights
  (lrf_jax/weights/ablation/, reduced schedule); "Max" reuses the Sum1 weights of its z."""
  from lrf_jax.frames.weights import WEIGHTS_DIR, load_params

  runs = []
  for z in ABLATION_Z:
    for x in ABLATION_X:
      file_x = {"Sum1": "sum", "Sum2": "sum2", "DR": "dr", "Max": "sum"}[x]
      params = load_params(WEIGHTS_DIR / "ablation" / f"{z.lower()}_{file_x}.msgpack")
      runs.append(MethodRun(f"{z}+{x}", "lrf_net_variant", params=params,
                            options=(("x_mode", x.lower() if x != "Sum1" else "sum1"),
                                     ("z_mode", z.lower()))))
  return runs


@dataclasses.dataclass(frozen=True)
class EvalOptions:
  """Knobs shared by every experiment.

  Attributes:
    data_root: where the data lives (None: LRF_DATA, then data/).
    n_keypoints: keypoints per pair (1000 in the paper).
    seed: keypoint, subsample and nuisance seed.
    radius_mr: support radius in mr (15).
    max_pairs: at most this many pairs per dataset and setting (None: all), for quick runs.
    max_neighbors: cap on all-neighbor patches (see `evaluate_pair`; None: no cap).
    scans: scan-set folders (`datasets.read_scan_set`), each a data set named by its folder
      (`scan_set_names`); a name in a list of data sets refers to one of them first.
    min_overlap: the overlap a scan-set pair needs (`datasets.read_scan_set`; 0.3).
  """

  data_root: str | None = None
  n_keypoints: int = 1000
  seed: int = 0
  radius_mr: float = RADIUS_MR
  max_pairs: int | None = None
  max_neighbors: int | None = MAX_NEIGHBORS
  scans: tuple[str, ...] = ()
  min_overlap: float = 0.3


def _br(root, noise=0.3, seed=0):
  return datasets.load_br(root, noise, seed=seed)


# name -> (loader(root, seed) for the "repeatability" experiment, the setting it stands for)
DATASETS: dict[str, tuple[Callable[..., list[Pair]], dict[str, Any]]] = {
    "BR@0.1": (lambda root, seed: datasets.load_br(root, 0.1), {"noise_mr": 0.1}),
    "BR@0.3": (lambda root, seed: datasets.load_br(root, 0.3), {"noise_mr": 0.3}),
    "BR@0.5": (lambda root, seed: datasets.load_br(root, 0.5), {"noise_mr": 0.5}),
    "UWA3M": (lambda root, seed: datasets.load_uwa3m(root, kind="consecutive"), {}),
    "UWA3M-model": (lambda root, seed: datasets.load_uwa3m(root, kind="view_to_model"),
                    {"model_stand_in": "UWAOR model"}),
    "UWAOR": (lambda root, seed: datasets.load_uwaor(root, scene="rs1"), {"scene": "rs1"}),
    "bunny": (lambda root, seed: datasets.load_bunny_pairs(root), {}),
    "3DMatch": (lambda root, seed: datasets.load_threedmatch_scenes(root), {}),
    "demo": (lambda root, seed: datasets.load_demo(4, seed=seed, noise_mr=0.3, partial=True),
             {"noise_mr": 0.3, "synthetic": True}),
}
# Noise-free versions for the nuisance sweeps (noise, decimation, radius, rotation).
CLEAN = {
    "BR": lambda root, seed: datasets.load_br(root, 0.0),
    "UWA3M": lambda root, seed: datasets.load_uwa3m(root, kind="consecutive"),
    "UWAOR": lambda root, seed: datasets.load_uwaor(root, scene="rs1"),
    "bunny": lambda root, seed: datasets.load_bunny_pairs(root),
    "demo": lambda root, seed: datasets.load_demo(4, seed=seed, noise_mr=0.0, partial=True),
}


FOLDERS = {"BR": "bologna_retrieval", "UWA3M": "uwa_3d_modeling_views",
           "UWAOR": "uwa_object_recognition", "bunny": "stanford_bunny_scans",
           "3DMatch": "threedmatch_scenes"}


def scan_set_names(folders: Iterable[str]) -> dict[str, str]:
  """{data set name: folder} of scan-set folders: each named by its folder's name.

  Raises:
    ValueError: two folders of the same name, or a name of a built-in data set (`DATASETS`,
      the sweeps' `CLEAN` names), naming the folders.
  """
  names: dict[str, str] = {}
  for folder in folders:
    name = folder_name(folder)
    base = name.split("@")[0].split("-")[0]
    if name in DATASETS or base in CLEAN or base in DATASETS:
      raise ValueError(f"--scans {folder}: its name {name!r} reads as the built-in data set "
                       f"{base!r}; rename the folder (or link it under another name)")
    if name in names:
      raise ValueError(f"--scans: {names[name]} and {folder} are both named {name!r}; data sets "
                       "are named by their folders: rename or link one")
    names[name] = folder
  return names


def dataset_pairs(ds: str, opts: EvalOptions) -> tuple[list[Pair], dict[str, Any]]:
  """(pairs, setting) of data set `ds`: a scan set of `opts.scans` (setting {}), else the
  loader of `DATASETS` (all pairs; `limit_pairs` caps them)."""
  folders = scan_set_names(opts.scans)
  if ds in folders:
    return datasets.load_scan_set(folders[ds], min_overlap=opts.min_overlap), {}
  loader, setting = DATASETS[ds]
  return loader(opts.data_root, opts.seed), setting


def clean_datasets(dataset_names: Iterable[str], opts: EvalOptions) -> list[str]:
  """The noise-free data sets the sweeps (noise, decimation, radius, rotation, ablation) run
  on for `dataset_names`: `clean_name`'s, then the scan sets among them, each once."""
  names = list(dataset_names)
  scans = [ds for ds in names if ds in scan_set_names(opts.scans)]
  clean = sorted(cast("set[str]", {clean_name(ds) for ds in names if ds not in scans} - {None}))
  return clean + scans


def clean_pairs(ds: str, opts: EvalOptions) -> list[Pair]:
  """The pairs of a name of `clean_datasets` (at most `opts.max_pairs`)."""
  if ds in scan_set_names(opts.scans):
    return limit_pairs(dataset_pairs(ds, opts)[0], opts)
  return limit_pairs(CLEAN[ds](opts.data_root, opts.seed), opts)


def available(names: Iterable[str], root: str | None, table: dict, *,
              full: bool = False) -> tuple[list[str], list[str]]:
  """Split dataset names into those whose data folder is found and messages for the others.

  With `full`, each message is the whole data-not-found text (where it looked, the LRF_DATA
  variable, how to get the data), once per missing folder; else one line per dataset.
  """
  ok, missing, seen = [], [], set()
  for name in names:
    if name not in table:
      raise ValueError(f"--datasets: unknown dataset {name!r}; expected some of {sorted(table)}")
    base = name.split("@")[0].split("-")[0]
    if base == "demo":
      ok.append(name)
      continue
    try:
      if base == "3DMatch":  # its own finder (the folder holds no other data set's layout)
        datasets.threedmatch.threedmatch_dir(root)
      else:
        datasets.find_data_root(root, FOLDERS[base])
      ok.append(name)
    except datasets.DataNotFoundError as e:
      if not full:
        missing.append(f"{name}: skipped, data not found ({str(e).splitlines()[0]})")
      elif base not in seen:
        seen.add(base)
        missing.append(f"{name}: {e}")
  return ok, missing


def limit_pairs(pairs: list[Pair], opts: EvalOptions) -> list[Pair]:
  return pairs if opts.max_pairs is None else pairs[:opts.max_pairs]


def iter_pairs(dataset_names: Iterable[str],
               opts: EvalOptions) -> Iterator[tuple[str, dict[str, Any], Pair]]:
  """(dataset name, its setting, pair) for every pair of the named `DATASETS` and scan sets
  (`dataset_pairs`), at most `opts.max_pairs` per dataset (shared by the repeatability, description and pose runs)."""
  for ds in dataset_names:
    pairs, setting = dataset_pairs(ds, opts)
    for pair in limit_pairs(pairs, opts):
      yield ds, setting, pair


@dataclasses.dataclass(frozen=True, eq=False)
class PairJob:
  """One pair of one experiment at one setting: a picklable payload whose records
  `job_records` computes (a pure function of the job: the same records in any process).

  Attributes:
    experiment: a name of `EXPERIMENTS`, or "description" / "pose" (`runner.pair_records`).
    dataset: the dataset name its records carry (a sweep's: the noise-free set's, e.g. "BR").
    pair: the model-scene pair, arrays included (a sweep's: the noise-free pair).
    setting: the setting its records carry (e.g. {"noise_mr": 0.3}).
    runs: the method columns.
    options: the knobs shared by every experiment.
    nuisance: what the sweep does to `pair` before the frames, as (kind, value): ("noise",
      sigma in mr; BR reads its noisy scene from `options.data_root`), ("decimation",
      fraction), ("radius", support radius in mr), ("rotation", degrees about z); None: none.
    params: LRF-Net parameters of the description and pose experiments (None: shipped).
  """

  experiment: str
  dataset: str
  pair: Pair
  setting: dict[str, Any]
  runs: tuple[MethodRun, ...]
  options: EvalOptions
  nuisance: tuple[str, float] | None = None
  params: Any = None

  def describe(self) -> str:
    """The job in words, for messages: "experiment on dataset, pair name (setting)"."""
    setting = ", ".join(f"{k}={v}" for k, v in self.setting.items())
    return (f"{self.experiment} on {self.dataset}, pair {self.pair.name}"
            + (f" ({setting})" if setting else ""))


SWEEP_SETTINGS = {"noise": ("noise_mr", NOISE_LEVELS), "decimation": ("decimation", DECIMATIONS),
                  "radius": ("radius_mr", RADII_MR), "rotation": ("rotation_deg", ROTATIONS_DEG)}


def experiment_jobs(name: str, dataset_names: list[str], methods: list[MethodRun],
                    opts: EvalOptions) -> Iterator[PairJob]:
  """The jobs of one experiment over the given datasets, in the order of its records (each
  dataset's pairs loaded when the iteration reaches it)."""
  if name not in EXPERIMENTS:
    raise ValueError(f"--experiments: unknown experiment {name!r}; expected some of "
                     f"{EXPERIMENTS}")
  if name in AS_NAMED:
    runs = tuple(points_only_runs(methods) if name == "points_only"
                 else methods if name == "repeatability" else plus_ablation_runs())
    for ds, setting, pair in iter_pairs(dataset_names, opts):
      yield PairJob(name, ds, pair, setting, runs, opts)
    return
  runs = tuple(ablation_runs() if name == "ablation" else methods)  # ablation: the paper's tables
  for ds in clean_datasets(dataset_names, opts):
    for pair in clean_pairs(ds, opts):
      if name == "ablation":
        yield PairJob(name, ds, pair, {}, runs, opts)
        continue
      key, values = SWEEP_SETTINGS[name]
      for value in values:
        yield PairJob(name, ds, pair, {key: value}, runs, opts, nuisance=(name, value))


def job_records(job: PairJob, cache: PatchCache | None = None) -> list[dict[str, Any]]:
  """The records of one job of `experiment_jobs` (`evaluate_pair` on the pair the nuisance
  makes, or `points_only_pair`), "dataset" set to the job's.

  Args:
    job: the payload.
    cache: a patch cache shared with other jobs (None: one for this job only; the records are
      the same either way).
  """
  cache = PatchCache() if cache is None else cache
  opts = job.options
  if job.experiment == "points_only":
    return _tagged(points_only_pair(job.pair, list(job.runs), setting=job.setting, opts=opts,
                                    cache=cache), job.dataset)
  pair, radius_mr, kind = job.pair, opts.radius_mr, None
  if job.nuisance is not None:
    kind, value = job.nuisance
    if kind == "noise":
      pair = (datasets.load_br_pair(pair.meta["scene"], value, opts.data_root, seed=opts.seed)
              if job.dataset == "BR" else datasets.with_noise(pair, value, opts.seed))
    elif kind == "decimation":
      pair = datasets.with_decimation(pair, value, opts.seed)
    elif kind == "radius":
      radius_mr = value
    elif kind == "rotation":
      pair = datasets.with_rotation(pair, value, "z")
    else:
      raise ValueError(f"PairJob.nuisance: unknown kind {kind!r}; expected one of "
                       f"{tuple(SWEEP_SETTINGS)}")
  return _tagged(evaluate_pair(pair, job.runs, experiment=job.experiment, setting=job.setting,
                               n_keypoints=opts.n_keypoints, seed=opts.seed,
                               radius_mr=radius_mr, scene_first=kind == "decimation",
                               cache=cache, max_neighbors=opts.max_neighbors), job.dataset)


def run_experiment(name: str, dataset_names: list[str], methods: list[MethodRun],
                   opts: EvalOptions, cache: PatchCache) -> Iterator[dict[str, Any]]:
  """Yield the records of one experiment over the given datasets (see module doc): the
  records of its jobs (`experiment_jobs`, `job_records`) one job after another."""
  for job in experiment_jobs(name, dataset_names, methods, opts):
    yield from job_records(job, cache)


def clean_name(ds: str) -> str | None:
  base = ds.split("@")[0].split("-")[0]
  return base if base in CLEAN else None


def _tagged(records: list[dict], ds: str) -> list[dict]:
  for r in records:
    r["dataset"] = ds if r["experiment"] in AS_NAMED else clean_name(ds) or ds
  return records
