"""lrf-frames' computation as a library function: one scan's keypoints, their frames (and a
descriptor), and with a second scan and the ground truth their repeatability. `lrf-frames` and
the data-set layer's frames items (`lrf_jax.batch.items`) both call `frames_of_scan`; its options
are a frozen `FrameOptions`, whose fields the command lines' flags are derived from.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from lrf_jax.checks import validate_seed
from lrf_jax.defaults import DEFAULT_METHOD, RADIUS_MR
from lrf_jax.io.sweeps import BIN_LAYOUTS
from lrf_jax.registration.options import option_field

# Smallest --keypoint-voxel-mr: voxels of a tenth of the spacing already hold one point each.
MIN_VOXEL_MR = 0.1
# Keypoints drawn when neither a count nor a rule is given.
DEFAULT_KEYPOINTS = 1000
_ASCII_DIGITS = frozenset("0123456789")
# The files a scan may be (`lrf_jax.io.read_cloud`), as the command lines' help names them.
INPUT_FORMATS = "PLY, PCD, XYZ/TXT(.gz), NPY, .bin sweep, LAS/LAZ or E57"


def _renamed(field: Any, *old: str) -> Any:
  """The `option_field` `field` whose flag keeps its names of before 0.9 (`old`) as aliases for
  this release: the metadata's `aliases`, further names of the same flag
  (`lrf_jax.cli.options.add_option_flags`)."""
  return dataclasses.field(default=field.default, metadata={**field.metadata, "aliases": old})


@dataclasses.dataclass(frozen=True)
class FrameOptions:
  """What lrf-frames computes for one scan: each field is the flag of the same name in kebab case
  (`cloud` the positional argument; `voxel_mr` is `--keypoint-voxel-mr`, `--voxel-mr` before
  0.9, still accepted: `frame_flag`), with its default and help; `lrf-frames` and `lrf-batch
  frames` derive their flags from the fields (`lrf_jax.cli.options.add_option_flags`).

  Attributes:
    cloud: the scan's path (any file `lrf_jax.io.read_cloud` reads).
    keypoints: a count of seeded random points, "all" or "iss" (None: `DEFAULT_KEYPOINTS`).
    voxel_mr: instead, one keypoint per voxel of this edge in mr (the point nearest its centre):
      it picks keypoints, and thins nothing (`--keypoint-voxel-mr`).
    voxel_size: thin the support (every frame's neighbours) by voxel averaging, as
      `compute_frames(voxel_size=)` and `register` do: None chooses (an uneven cloud such as a
      raw LiDAR sweep is thinned to its working resolution, clean clouds and meshes are not), 0
      keeps every point, a positive number is the voxel edge in cloud units. The keypoints stay
      the input cloud's points; each frame is its keypoint's voxel's (`compute_frames`).
    method: a key of `lrf_jax.METHODS`.
    weights: a learned method's weights (`compute_frames`' `weights`: "objects", "rooms",
      "streets" or a parameter file's path).
    radius_mr: the support radius in mr.
    viewpoint: the scan's sensor position (3 numbers) or None.
    descriptor: also this descriptor on the frames (a key of `DESCRIPTORS`) or None.
    seed: seed of keypoints and subsamples.
    pair, gt, pair_viewpoint: a second scan, the 4x4 transform mapping the cloud onto it (a
      text file or .npy) and its sensor position: frames at the corresponding points too.
    bin_layout: the layout of `.bin` inputs ("xyzi", "xyz"; None: `read_cloud`'s default,
      checked; `lrf_jax.io.sweeps`).
  """

  cloud: str = option_field("", INPUT_FORMATS + " file", flag=None)
  keypoints: str | None = option_field(
      None, "N seeded random points, 'all', or 'iss' (ISS keypoints); none given: "
      f"{DEFAULT_KEYPOINTS}")
  voxel_mr: float | None = _renamed(option_field(
      None, f"keypoints: the point nearest each voxel centre, voxels of S mr, S >= "
      f"{MIN_VOXEL_MR:g} (instead of --keypoints; it picks keypoints and thins nothing: "
      "--voxel-size thins the support)", flag="--keypoint-voxel-mr", metavar="S"), "--voxel-mr")
  voxel_size: float | None = option_field(
      None, "thin the support by voxel averaging, voxels of V (cloud units; 0: keep every "
      "point); none given: an uneven cloud (a raw LiDAR sweep) is thinned to its working "
      "resolution, clean clouds and meshes are kept, as lrf-register does", metavar="V")
  method: str = option_field(DEFAULT_METHOD, "a key of lrf_jax.METHODS (print(lrf_jax.METHODS) "
                             "lists them)")
  weights: str = option_field(
      "objects", "weights of a learned method: objects (the paper's training data), rooms "
      "(RGB-D room fragments), streets (LiDAR sweeps), or a parameter file's path",
      metavar="KIND|PATH")
  radius_mr: float = option_field(RADIUS_MR,
                                  "support radius in mesh resolutions (15: the paper's)")
  viewpoint: tuple[float, float, float] | None = option_field(
      None, "sensor position of a single-view scan (orients normals and z)",
      metavar=("X", "Y", "Z"))
  descriptor: str | None = option_field(
      None, "also a descriptor on the frames (snapshots, shot, rops, toldi)")
  seed: int = option_field(0, "seed of keypoints and subsamples")
  pair: str | None = option_field(
      None, "a second scan of the same object: frames at the corresponding points and their "
      "MeanCos (needs --gt)", metavar="B")
  gt: str | None = option_field(
      None, "the 4x4 transform mapping CLOUD onto B (text as read_xf reads, or .npy)",
      metavar="T")
  pair_viewpoint: tuple[float, float, float] | None = option_field(
      None, "sensor position of the scan B", metavar=("X", "Y", "Z"))
  bin_layout: str | None = option_field(
      None, "the layout of the .bin sweeps among the inputs: xyzi (16 bytes a point: float32 "
      "x, y, z, reflectance; KITTI's) or xyz (12 bytes a point: x, y, z); none given: xyzi, "
      "and a file whose size fits both is refused when its values look like xyz",
      choices=tuple(BIN_LAYOUTS))

  @classmethod
  def from_args(cls, args: Any) -> FrameOptions:
    """The request of an argparse namespace (or any object) with these fields' names."""
    return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
                  if hasattr(args, f.name)})

  def problem(self) -> str | None:
    """What is wrong with the options (named by lrf-frames' flags), before any work (None:
    fine). The inputs' paths are checked to exist; the cloud's is read later."""
    from lrf_jax.descriptors import DESCRIPTORS
    from lrf_jax.frames import METHODS
    if self.method not in METHODS:
      return f"--method: unknown method {self.method!r}; expected one of {sorted(METHODS)}"
    if self.weights != "objects":
      from lrf_jax.frames.weights import learned_weights_file
      try:
        learned_weights_file(METHODS[self.method], self.weights)
      except ValueError as e:
        return f"--{e}"
    if self.descriptor is not None and self.descriptor not in DESCRIPTORS:
      return f"--descriptor: unknown {self.descriptor!r}; expected one of {sorted(DESCRIPTORS)}"
    if self.bin_layout is not None and self.bin_layout not in BIN_LAYOUTS:
      return (f"--bin-layout: expected one of {', '.join(BIN_LAYOUTS)}, got "
              f"{self.bin_layout!r}")
    voxel_flag = frame_flag("voxel_mr")
    if self.voxel_mr is not None and self.keypoints is not None:
      return (f"{voxel_flag} and --keypoints: give one of them ({voxel_flag} picks one keypoint "
              "per voxel, --keypoints a number, 'all' or 'iss')")
    kp = self.keypoints
    if kp is not None and kp not in ("all", "iss") and (
        not kp or not set(kp) <= _ASCII_DIGITS or int(kp) < 1):
      return f"--keypoints: expected a positive integer, 'all' or 'iss', got {kp!r}"
    for name in ("radius_mr", "voxel_mr"):
      v = getattr(self, name)
      if v is not None and not (np.isfinite(v) and v > 0):
        return f"{frame_flag(name)}: expected a positive number, got {v!r}"
    vs = self.voxel_size
    if vs is not None and not (np.isfinite(vs) and vs >= 0):
      return (f"--voxel-size: expected 0 (keep every point) or a positive voxel edge in cloud "
              f"units, got {vs!r}")
    if self.voxel_mr is not None and self.voxel_mr < MIN_VOXEL_MR:
      return (f"{voxel_flag}: {self.voxel_mr:g} mr is below {MIN_VOXEL_MR:g} mr (voxels that "
              "small hold one point each; use --keypoints all)")
    try:
      validate_seed(self.seed, "--seed")
    except ValueError as e:
      return str(e)
    for name in ("viewpoint", "pair_viewpoint"):
      vp = getattr(self, name)
      if vp is not None and not np.all(np.isfinite(np.asarray(vp, np.float64))):
        return (f"--{name.replace('_', '-')}: expected three finite numbers (the sensor's "
                f"position), got {' '.join(map(str, vp))}")
    return self._pair_problem()

  def _pair_problem(self) -> str | None:
    from lrf_jax.io.atomic import path_problem
    if (self.pair is None) != (self.gt is None):
      return ("--pair and --gt go together: --pair B names the second scan, --gt T the 4x4 "
              "transform mapping the cloud onto it")
    for name, value in (("--pair", self.pair), ("--gt", self.gt)):
      if value is not None and path_problem(value):
        return f"{name}: {value} {path_problem(value)}"
      if value is not None and not Path(value).expanduser().is_file():
        return f"{name}: {value} is not a file"
    return None


# The name of `FrameOptions` before 0.9, kept for this release.
FramesRequest = FrameOptions


def frame_flag(name: str) -> str:
  """The flag of lrf-frames (and lrf-batch frames) that sets the `FrameOptions` field `name`: its
  metadata's `flag`, else the name in kebab case (`voxel_mr`: "--keypoint-voxel-mr")."""
  field = {f.name: f for f in dataclasses.fields(FrameOptions)}[name]
  return field.metadata["flag"] or "--" + name.replace("_", "-")


def select_keypoints(points: np.ndarray, how: str, voxel: float | None, seed: int,
                     mr: float | None = None) -> np.ndarray:
  """Sorted keypoint indices: every point ('all'), ISS keypoints ('iss', at resolution `mr`),
  N seeded random ones, or with `voxel` (cloud units) the point nearest the centre of each
  occupied voxel.

  Raises:
    ValueError: `voxel` too small for the cloud's extent; 'iss' where this version has no ISS
      detector."""
  n = len(points)
  if voxel is not None:
    cells = np.floor((points - points.min(0)) / voxel)
    if not (np.isfinite(voxel) and voxel > 0 and np.all(np.isfinite(cells))
            and cells.max(initial=0) < 2**40):
      raise ValueError(f"{frame_flag('voxel_mr')}: a voxel of {voxel:g} (cloud units) is too "
                       f"small for a cloud of extent {np.ptp(points, axis=0).max():g}")
    cells = cells.astype(np.int64)
    centre = (cells + 0.5) * voxel + points.min(0)
    d = np.linalg.norm(points - centre, axis=1)
    _, inv = np.unique(cells, axis=0, return_inverse=True)
    order = np.lexsort((d, inv.ravel()))
    first = np.r_[True, np.diff(inv.ravel()[order]) != 0]
    return np.sort(order[first])
  if how == "all":
    return np.arange(n)
  if how == "iss":
    try:
      from lrf_jax.geometry.keypoints import iss_keypoints
    except ImportError:
      raise ValueError("--keypoints iss: this version of lrf_jax has no ISS detector "
                       "(lrf_jax.geometry.keypoints.iss_keypoints)") from None
    return np.sort(np.asarray(iss_keypoints(points, mr=mr), np.int64))
  m = min(int(how), n)
  return np.sort(np.random.default_rng(seed).choice(n, m, replace=False))


def read_transform(path: str, option: str, project: float = 0.0) -> np.ndarray:
  """The (4, 4) rigid transform in `path`: a .npy holding one, else a text file of 4 rows of 4
  numbers (`lrf_jax.io.read_xf`); a rotation block within `project` of orthonormal is
  projected to the nearest rotation (`lrf_jax.io.validation.check_rigid`).

  Raises:
    ValueError: not a readable (4, 4) rigid matrix; the message names `option` and the file.
  """
  from lrf_jax.io import check_rigid, read_xf
  if path.lower().endswith(".npy"):
    try:
      t = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
      raise ValueError(f"{option} {path}: not a readable .npy file ({e})") from None
    if not np.issubdtype(t.dtype, np.number):
      raise ValueError(f"{option} {path}: expected a numeric (4, 4) array, got dtype {t.dtype}")
    return check_rigid(t, path, f"{option} matrix", project=project)
  try:
    return read_xf(path, project=project)
  except ValueError as e:
    raise ValueError(f"{option}: {e}") from None


def pair_keypoints(points: np.ndarray, pair_points: np.ndarray, transform: np.ndarray,
                   mr: float, how: str, voxel: float | None, seed: int,
                   max_dist_mr: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
  """Keypoints of `points` (n, 3) that the other scan `pair_points` (n', 3) also saw, and their
  correspondences: a point is eligible when its image under `transform` (4, 4) has a point of
  the other scan within `max_dist_mr` * `mr` (cloud units); N seeded eligible points for a
  number `how` (the repeatability protocol's draw), else `select_keypoints`' choice
  restricted to the eligible ones.

  Returns:
    (keypoints (m,), pair_keypoints (m,)) int64, keypoints sorted; pair_keypoints[i] is the
    point of the other scan nearest keypoint i's image.

  Raises:
    ValueError: no point of `points` lands near the other scan (wrong --gt?)."""
  from scipy.spatial import cKDTree

  from lrf_jax.datasets.pair import transform_points
  dist, nearest = cKDTree(pair_points).query(transform_points(transform, points),
                                             distance_upper_bound=max_dist_mr * mr, workers=-1)
  eligible = np.isfinite(dist)
  if not eligible.any():
    raise ValueError(f"--gt: no point of the cloud lands within {max_dist_mr:g} mr of a point "
                     "of --pair under this transform (is it the cloud -> pair transform?)")
  if voxel is None and how not in ("all", "iss"):
    idx = np.flatnonzero(eligible)
    kp = np.sort(np.random.default_rng(seed).choice(idx, min(int(how), len(idx)),
                                                    replace=False))
  else:
    kp = select_keypoints(points, how, voxel, seed, mr)
    kp = kp[eligible[kp]]
  return kp.astype(np.int64), nearest[kp].astype(np.int64)


def support_cloud(cloud: Any, keypoints: np.ndarray, voxel: float) -> tuple[Any, np.ndarray]:
  """The cloud frames and descriptors are computed on and the keypoints' points in it: `cloud`
  and `keypoints` as given for `voxel` 0, else the cloud thinned at `voxel`
  (`geometry.sampling.thin_cloud`) and each keypoint's voxel (`compute_frames(voxel_size=)`'s
  rule)."""
  if not voxel:
    return cloud, keypoints
  from lrf_jax.geometry.cloud import CheckedCloud
  from lrf_jax.geometry.sampling import thin_cloud
  thin, _, inverse = thin_cloud(cloud.points, voxel)
  return CheckedCloud(thin, name="thinned cloud"), inverse[keypoints]


def scan_resolution(cloud: Any, request: FrameOptions) -> tuple[float, float]:
  """(mr, voxel): the cloud's working resolution (`CheckedCloud.working_resolution`: the mean
  spacing of a clean cloud, the area-weighted one of an uneven cloud) and the voxel edge its
  support is thinned at (`thinning_voxel_size` of `request.voxel_size`; 0: none).

  Raises:
    ValueError: a cloud without spacing, naming the file.
  """
  from lrf_jax.frames import METHODS
  from lrf_jax.geometry.sampling import thinning_voxel_size
  try:
    res = cloud.working_resolution
  except ValueError as e:  # "points: the cloud has no spacing ...": name the file
    raise ValueError(f"{request.cloud}: {str(e).removeprefix('points: ')}") from None
  voxel = thinning_voxel_size(cloud.points, res, res.mr, faces=cloud.faces,
                              voxel_size=request.voxel_size)
  if voxel and METHODS[request.method].needs_mesh:
    raise ValueError(f"--voxel-size: thinning drops the faces method {request.method!r} needs; "
                     "give --voxel-size 0")
  return float(res.mr), float(voxel)


def weights_label(spec: Any, weights: str) -> str:
  """The "weights" field of lrf-frames' .npz: the parameter file a learned method read (a
  shipped file's stem, e.g. "lrf_net_plus_streets", or the path given), "" for a hand-crafted one."""
  if not spec.needs_params:
    return ""
  from lrf_jax.frames.weights import is_shipped, weights_file
  path = weights_file(spec.weights, weights)
  return path.stem if is_shipped(path) else str(weights)


def frames_of_scan(request: FrameOptions) -> tuple[dict, Any, Any]:
  """Read the inputs and compute what `request` asks for: (the .npz fields lrf-frames writes, the
  `CheckedCloud`, the pair's or None). The pair's support is thinned at the same voxel as the
  cloud's (one radius, one voxel on both sides).

  Raises:
    ValueError: an unreadable input or a failed step, naming the file or the flag.
  """
  from lrf_jax.frames import METHODS
  from lrf_jax.frames.compute import compute_frames
  from lrf_jax.frames.metrics import meancos
  from lrf_jax.geometry.cloud import as_cloud
  from lrf_jax.io.reader import cloud_source
  cloud = as_cloud(cloud_source(request.cloud, request.bin_layout), "cloud")
  mr, voxel_size = scan_resolution(cloud, request)
  voxel = None if request.voxel_mr is None else request.voxel_mr * mr
  how = request.keypoints or str(DEFAULT_KEYPOINTS)
  other = gt = None
  if request.pair is not None:
    assert request.gt is not None  # `problem`: --pair and --gt go together
    gt = read_transform(request.gt, "--gt")
    other = as_cloud(cloud_source(request.pair, request.bin_layout), "--pair")
    kp, kp_b = pair_keypoints(cloud.points, other.points, gt, mr, how, voxel, request.seed)
  else:
    kp = select_keypoints(cloud.points, how, voxel, request.seed, mr)
  radius = request.radius_mr * mr
  spec = METHODS[request.method]
  conf = spec.confidence is not None
  learned_weights = request.weights if spec.needs_params else None
  work, work_kp = support_cloud(cloud, kp, voxel_size)
  frames, valid, *confidence = compute_frames(
      work, work_kp, radius, request.method, seed=request.seed, viewpoint=request.viewpoint,
      progress=len(kp) > 20000, return_confidence=conf, voxel_size=0, weights=learned_weights)
  out = dict(keypoints=kp, positions=cloud.points[kp], frames=np.asarray(frames),
             valid=np.asarray(valid), radius=radius, mr=mr, method=request.method,
             weights=weights_label(spec, request.weights), voxel_size=voxel_size)
  if conf:
    out["confidence"] = np.asarray(confidence[0])
  if request.descriptor:
    from lrf_jax.descriptors import compute_descriptors
    desc, _ = compute_descriptors(work.points, work_kp, radius, frames, valid,
                                  request.descriptor, faces=work.faces, seed=request.seed)
    out["descriptors"] = np.asarray(desc)
  if other is not None:
    work_b, work_kp_b = support_cloud(other, kp_b, voxel_size)
    fb, vb, *conf_b = compute_frames(
        work_b, work_kp_b, radius, request.method, seed=request.seed,
        viewpoint=request.pair_viewpoint, progress=len(kp) > 20000, return_confidence=conf,
        voxel_size=0, weights=learned_weights)
    if conf:
      out["pair_confidence"] = np.asarray(conf_b[0])
    out.update(pair_keypoints=kp_b, pair_frames=np.asarray(fb), pair_valid=np.asarray(vb),
               gt=gt, meancos=np.asarray(meancos(frames, fb, gt, valid, vb)))
  return out, cloud, other
