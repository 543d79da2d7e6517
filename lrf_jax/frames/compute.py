"""`compute_frames`: the one public call for every LRF method (the search, the method's inputs,
its host kernel or jitted function over chunks of keypoints), and `mesh_resolution`, the length
unit of its `radius_mr`."""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any, cast

from lrf_jax._jax import backend_is_cpu, jax, jnp
import numpy as np

from lrf_jax.search import engine
from lrf_jax.search.chunks import map_chunks
from lrf_jax.geometry.resolution import mesh_resolution as _mesh_resolution
from lrf_jax.frames.spec import DEFAULT_METHOD, METHODS, MethodSpec, method_spec
from lrf_jax.frames.host_path import host_frames_in_budget
from lrf_jax.frames.normals_rule import method_normals, orients, prepare_extra
from lrf_jax.frames.patch_frames import cached_weight_table, check_options, patch_frames_checked
from lrf_jax.geometry.cloud import CheckedCloud, as_cloud
from lrf_jax.geometry.sampling import thin_cloud, thinning_voxel_size
from lrf_jax.frames.weights import learned_weights_file, weights_options, weights_params
from lrf_jax.checks import (validate_choice, validate_keypoints, validate_radius, validate_seed,
                            validate_viewpoint, validate_voxel_size)
from lrf_jax.search.neighborhoods import Patches, SearchIndex, build_patches, unit_scaled

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# Ball sizes outside these bounds (median over a sample of keypoints) draw a warning.
MIN_MEDIAN_BALL = 10
MAX_BALL_FRACTION = 0.5


def mesh_resolution(points: Any, faces: Any = None) -> float:
  """The length unit of support radii and noise: mean edge length of a mesh (with `faces`), mean
  nearest-neighbor distance of a cloud (without), as the datasets measure it.

  Args:
    points: any cloud input `compute_frames` takes (an (n, 3) array, a `Cloud`, a path, ...).
    faces: optional (f, 3) triangles (default: those the input carries).

  Returns:
    mr in the cloud's units. `compute_frames(..., radius_mr=15)` is the paper's support radius
    (measured in the working resolution, which is this mr on every mesh and clean cloud and the
    area-weighted spacing on an uneven one: `lrf_jax.geometry.resolution.working_resolution`).
  """
  return float(as_cloud(points, "points", faces=faces).resolution)


def _resolve_radius(cloud: CheckedCloud, radius: Any, radius_mr: Any) -> float:
  if (radius is None) == (radius_mr is None):
    raise ValueError("radius, radius_mr: expected exactly one of them (radius in cloud units, "
                     f"or radius_mr in mesh resolutions), got radius={radius!r}, "
                     f"radius_mr={radius_mr!r}")
  if radius is not None:
    return validate_radius(radius)
  radius_mr = validate_radius(radius_mr, "radius_mr")
  return validate_radius(radius_mr * cloud.working_resolution.mr)


def _thinned(cloud: CheckedCloud, keypoints: np.ndarray, voxel_size: float | None,
             spec: MethodSpec) -> tuple[CheckedCloud, np.ndarray, np.ndarray | None]:
  """The cloud `compute_frames` works on (`voxel_size`, `thinning_voxel_size`'s rule), each
  distinct keypoint's point in it and, where it was thinned, each keypoint's row among those
  (None: the cloud and keypoints as given)."""
  if voxel_size == 0 or (voxel_size is None and cloud.faces is not None):
    return cloud, keypoints, None  # no resolution to measure: nothing is thinned
  res = cloud.working_resolution if voxel_size is None else None
  voxel = voxel_size if res is None else thinning_voxel_size(cloud.points, res, res.mr)
  if not voxel:
    return cloud, keypoints, None
  if spec.needs_mesh:
    raise ValueError(f"voxel_size: thinning drops the faces method {spec.name!r} needs; pass "
                     "voxel_size=0 to keep the mesh")
  thin, _, inverse = thin_cloud(cloud.points, voxel)
  kp, back = np.unique(inverse[keypoints], return_inverse=True)
  return CheckedCloud(thin, name="thinned cloud"), kp, back.ravel()


def _warn_on_ball_size(index: SearchIndex, points: np.ndarray, keypoints: np.ndarray,
                       radius: float, unit: float = 1.0) -> None:
  """Warn when the median ball (over up to 256 of the keypoints) holds fewer than
  `MIN_MEDIAN_BALL` points or more than `MAX_BALL_FRACTION` of the cloud. `unit`: the cloud
  units of one unit of `points` (lengths are reported in the caller's units)."""
  sample = keypoints[:: max(1, len(keypoints) // 256)]
  med = float(np.median(engine.ball_counts(index.grid(radius), points[sample], radius)))
  n = len(points)
  if med < MIN_MEDIAN_BALL:
    try:
      mr = f"{_mesh_resolution(points)[0] * unit:.6g}"
    except ValueError:  # no spacing: every point duplicated
      mr = "0"
    warnings.warn(f"radius {radius * unit:.6g}: the median ball holds {med:.0f} points (fewer "
                  f"than {MIN_MEDIAN_BALL}); most frames will be invalid. The paper uses 15 mesh "
                  f"resolutions: radius_mr=15 (this cloud's mr is {mr})", stacklevel=3)
  elif med > MAX_BALL_FRACTION * n:
    warnings.warn(f"radius {radius * unit:.6g}: the median ball holds {med:.0f} of the cloud's {n} "
                  f"points (more than {MAX_BALL_FRACTION:.0%}); the frames are not local. The "
                  "paper uses 15 mesh resolutions: radius_mr=15", stacklevel=3)


def _validate_k(k: Any) -> None:
  if k is None or (isinstance(k, str) and k == "default"):
    return
  if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or k < 1:
    raise ValueError(f"k: expected a positive integer patch size, None (every neighbor) or "
                     f"'default', got {k!r}")


def patch_size_cap(n_points: int) -> int:
  """The largest patch size K `compute_frames` allocates for a cloud of `n_points`: the smallest
  power of two >= n_points. A ball holds at most the whole cloud, so a larger K would only add
  padding (which never changes a frame) and memory (m x K x 21 bytes of patches)."""
  return 1 << max(int(n_points) - 1, 0).bit_length()


def _check_call(spec: MethodSpec, faces: Any, chunk_size: Any, k: Any, options: dict,
                return_confidence: bool) -> None:
  """`compute_frames`' checks of the method's needs and of chunk_size, k, the options and
  return_confidence (a ValueError naming the argument)."""
  method = spec.name
  if spec.needs_mesh and faces is None:
    raise ValueError(f"method {method!r} needs a triangle mesh: pass faces=(f, 3) indices "
                     "(a cloud without faces is not supported by this method)")
  if (isinstance(chunk_size, (bool, np.bool_)) or not isinstance(chunk_size, (int, np.integer))
      or chunk_size < 1):
    raise ValueError(f"chunk_size: expected a positive integer, got {chunk_size!r}")
  _validate_k(k)
  check_options(method, options, spec)
  if return_confidence and spec.confidence is None:
    raise ValueError(f"return_confidence: method {method!r} defines no sign confidence; methods "
                     f"that do: {sorted(n for n, s in METHODS.items() if s.confidence)}")


def _weights_options(spec: Any, params: Any, weights: str | None) -> dict[str, Any]:
  """The options the `weights` of a `compute_frames` call bring (`weights_options`); {} for
  None. Raises a ValueError for weights given with `params` or to a hand-crafted method, or
  that `weights_file` refuses."""
  if weights is None:
    return {}
  path = learned_weights_file(spec, weights)
  if params is not None:
    raise ValueError("weights: given with params; expected one of the two (params are the "
                     "weights themselves)")
  return weights_options(path)


def compute_frames(
    points: Any,
    keypoints: np.ndarray,
    radius: float | None = None,
    method: str = DEFAULT_METHOD,
    *,
    radius_mr: float | None = None,
    params: Any = None,
    weights: str | None = None,
    k: int | None | str = "default",
    seed: int = 0,
    faces: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    viewpoint: Any = None,
    chunk_size: int = 4096,
    progress: bool | None = None,
    search: str = "auto",
    kernel: str = "auto",
    return_confidence: bool = False,
    as_numpy: bool = False,
    voxel_size: float | None = None,
    **options: Any,
) -> tuple[AnyArray, AnyArray] | tuple[AnyArray, AnyArray, AnyArray]:
  """Local reference frames of `keypoints` of a cloud, by any registered method.

  The radius search runs on the host (the compiled engine, `lrf_jax.search.engine`, all cores) or on the
  accelerator (`search`), keypoints are processed in fixed-size chunks (for the jitted functions
  the last one padded) so that memory is bounded and one compiled function serves every chunk;
  the frames are computed by the method's jitted function, or on a CPU backend by its compiled
  host kernel where it has one (`kernel`; these visit the keypoints in grid-cell order).

  Args:
    points: the cloud: an (n, 3) array of finite floats (any units), an `lrf_jax.io.Cloud`, a
      path any `lrf_jax.io` reader opens, or an object with `.points` (or `.vertices` and
      `.triangles`), e.g. Open3D's; its faces and normals are used unless `faces=` /
      `normals=` are given (`lrf_jax.geometry.cloud.CheckedCloud`).
    keypoints: (m,) integer indices into `points`.
    radius: support radius r in the cloud's units (the paper: 15 mesh resolutions); give this or
      `radius_mr`.
    method: a key of `lrf_jax.METHODS`; default "lrf_net_plus", the most repeatable shipped
      method ("lrf_net" is the paper's LRF-Net).
    radius_mr: the support radius in mesh resolutions instead: the input cloud's working
      resolution (`lrf_jax.geometry.resolution.working_resolution` of this call's points and
      faces; `register` also caps it by the cloud's extent, this call does not):
      `lrf_jax.mesh_resolution`'s (mean edge length of a
      mesh, mean nearest-neighbor distance of a cloud) on every mesh and clean cloud, the
      area-weighted spacing on an uneven one (a raw LiDAR sweep); the paper uses 15.
    params: learned parameters for learned methods; None = the weights `weights` names.
    weights: which shipped weights a learned method reads when no `params` are given:
      "objects" (None, the default: what the method was trained on, the paper's BR objects),
      "rooms" (fine-tuned on RGB-D room fragments) or "streets" (fine-tuned on LiDAR sweeps;
      both shipped for lrf_net_plus), or the path of a parameter file (`save_params`, a
      `train.py` run's `best_params.msgpack`). A file's JSON beside it may name options it was
      trained under ("streets": `vote=False`, the ball sign without a viewpoint); options given
      here win.
    k: patch size K; "default" = the method's own (`METHODS[method].default_k`); None = every
      neighbor in the ball. A K above the cloud's size is capped at `patch_size_cap(n)` (the
      power of two >= n): a ball cannot hold more points, and padding never changes a frame.
    seed: seed of the neighbor subsample when a ball holds more than K points.
    faces: (f, 3) triangle indices, for mesh methods.
    normals: (n, 3) per-point normals, for methods that use them; None = estimated
      (`lrf_jax.geometry.normals.estimate_normals`: PCA over 0.2 r, oriented by `faces`, else `viewpoint`,
      else by propagation).
    viewpoint: (3,) sensor position, for a single-view scan without faces: estimated normals are
      oriented towards it (PCL's convention), and so is lrf_net_plus's z. Pass it for range
      scans where it is known. Without it (and without faces or normals) lrf_net_plus orients
      z from the points alone (`lrf_jax.geometry.normals.orient_by_vote`); the other methods' estimated
      normals are oriented by propagation, which cannot know which side of an open scan is out.
    chunk_size: keypoints per jitted call (bounds memory: about chunk_size x K x 16 bytes of
      patches at a time). With several local devices, each chunk is sharded over them.
    progress: show a progress bar over chunks (default: when there are more than 4 chunks).
    search: where the radius search runs: "host" (the compiled engine, all cores), "device" (jitted
      voxel grids on the default device, `lrf_jax.search.device`; integer K only; the same
      patches, keypoints it cannot guarantee are redone on the host), or "auto" (device when the
      default backend is a GPU/TPU and K is an integer, else host).
    kernel: how the frames are computed: "jit" (patches, then the method's jitted function),
      "host" (the method's host fast path, `METHODS[method].host_frames`: compiled engine code
      over every neighbor, float64, no padded patches, for methods that have one, with k=None
      and no options; or, for lrf_net, lrf_net_plus and uniform with table weights (`lut` > 1,
      x_mode "sum" or "softmax"), the same patches' frames in compiled float64 code,
      `METHODS[method].host_patch_frames`), or "auto" (host where it applies and the backend
      is the CPU, else jit).
    return_confidence: also return the confidence of each frame's z sign, for methods that
      define one (`METHODS[method].confidence`: lrf_net_plus, `sign_confidence`).
    as_numpy: return numpy arrays (a host kernel's own: then no JAX is imported) instead of
      JAX arrays.
    voxel_size: thin the cloud by voxel averaging before the search, as `register` does
      (`lrf_jax.geometry.sampling.thinning_voxel_size`): None (default) with `radius_mr`
      thins a cloud whose mean spacing is under half its working resolution (an uneven cloud
      such as a raw LiDAR sweep, at the voxel whose centroids come out one working resolution
      apart) and leaves meshes and clean clouds exactly as they are; None with an explicit
      `radius` thins nothing (no resolution is measured: the call costs what it did); 0 keeps
      every point; a positive number is
      the voxel edge in cloud units (a mesh then loses its faces: refused for mesh methods).
      A thinned cloud loses its normals (estimated again on it, where the method needs them).
      Keypoints stay indices into the input cloud; each keypoint's frame is the frame of its
      voxel's centroid, on the thinned cloud (keypoints in one voxel get the same frame), so a
      frame is centred within half a voxel diagonal of its keypoint.
    **options: method options (e.g. `x_mode`, `signed`).

  Returns:
    (frames, valid), JAX arrays (numpy with `as_numpy`): frames (m, 3, 3) float32, rows x, y, z, det +1 (the identity where invalid);
    valid (m,) bool. With `return_confidence`, (frames, valid, confidence): confidence (m,)
    float32 in [0, 1], dimensionless (0: the sign is a guess, e.g. a flat patch of a cloud
    without a viewpoint, or an invalid frame; 1: certain, e.g. z facing a given sensor).

  Raises:
    ValueError: a cloud that is not a non-empty (n, 3) array of finite floats, an out-of-range or
      non-integer keypoint, a non-positive radius, an unknown method, a missing mesh, a `k` that
      is not a positive integer, None or "default", a non-positive `chunk_size`, a `seed` that is
      not a non-negative integer, a viewpoint that is not a finite (3,) position, an option the
      method does not take (the message lists its options), `return_confidence` for a
      method without a confidence, or a `voxel_size` that is not None, 0 or a positive number
      (or thins a mesh a mesh method needs, or leaves fewer than 10 points).

  Example:
    >>> frames, valid = compute_frames(points, np.arange(100), radius=0.02)
  """
  spec = method_spec(method)
  options = _weights_options(spec, params, weights) | options
  cloud = as_cloud(points, "points", faces=faces, normals=normals)
  keypoints = validate_keypoints(keypoints, cloud.points.shape[0])
  measured = radius is None  # radius_mr: the working resolution is measured (and thins)
  radius = _resolve_radius(cloud, radius, radius_mr)
  _check_call(spec, cloud.faces, chunk_size, k, options, return_confidence)
  seed = validate_seed(seed)
  viewpoint = validate_viewpoint(viewpoint)
  validate_choice("kernel", kernel, ("auto", "host", "jit"))  # also with no keypoints
  validate_choice("search", search, ("auto", "host", "device"))
  voxel_size = validate_voxel_size(voxel_size)
  if voxel_size is None and not measured:  # a length given: no resolution measured, none thinned
    voxel_size = 0.0
  cloud, keypoints, rows = _thinned(cloud, keypoints, voxel_size, spec)
  out = frames_checked(method, cloud, keypoints, radius, params=params, weights=weights or
                       "objects", k=k, seed=seed,
                        viewpoint=viewpoint, chunk_size=chunk_size, progress=progress,
                        search=search, kernel=kernel, return_confidence=return_confidence,
                        options=options)
  if rows is not None:  # each keypoint's voxel's frame
    out = tuple(a[rows] for a in out)
  return cast("tuple[AnyArray, AnyArray] | tuple[AnyArray, AnyArray, AnyArray]",
              tuple(np.asarray(a) if as_numpy else jnp.asarray(a)  # the host paths' too
                    for a in out))


def frames_checked(
    method: str,
    cloud: CheckedCloud,
    keypoints: np.ndarray,
    radius: float,
    *,
    params: Any = None,
    weights: str = "objects",
    k: int | None | str = "default",
    seed: int = 0,
    viewpoint: np.ndarray | None = None,
    chunk_size: int = 4096,
    progress: bool | None = None,
    search: str = "auto",
    kernel: str = "auto",
    return_confidence: bool = False,
    options: dict | None = None,
) -> tuple[AnyArray, ...]:
  """`compute_frames` after its argument checks: the same arguments (and defaults), already
  checked by `compute_frames` (or by `register`, for the clouds it read and the keypoints it
  drew), `search` and `kernel` included.

  Args:
    method: a key of `METHODS`.
    cloud: the `CheckedCloud` ((n, 3) finite float64 points, faces (f, 3) int64 into them or
      None, normals (n, 3) or None).
    keypoints: (m,) int64 indices into `cloud.points`.
    radius: support radius r (cloud units; `validate_radius`'s range).
    seed: a non-negative int.
    viewpoint: None or a finite (3,) float64 position (`validate_viewpoint`).
    params: learned parameters, as `compute_frames` takes them.
    weights: the weights read when `params` is None (`compute_frames`; checked by
      `_weights_options`, whose options the caller merged into `options`).
    k: the patch size (checked by `_check_call` for this method).
    chunk_size: keypoints per call (checked by `_check_call`).
    progress: as `compute_frames` takes it.
    search: "auto", "host" or "device" (`compute_frames`).
    kernel: "auto", "host" or "jit" (`compute_frames`).
    return_confidence: also return the sign confidence (checked by `_check_call`).
    options: the method's options (checked by `_check_call`).

  Returns:
    As `compute_frames`, as numpy arrays where a host kernel computed them (JAX arrays on the
    jitted path): `register` reads them without importing JAX.
  """
  spec = METHODS[method]
  options = {} if options is None else options
  points, faces, normals = cloud.points, cloud.faces, cloud.normals
  # Every method works in units of the radius (frames are directions): the same arithmetic at
  # any scale of cloud and radius (1e-30..1e30, `validate_radius`; `unit_scaled`).
  unit = radius
  points, radius, viewpoint = unit_scaled(points, radius, viewpoint)
  k = spec.default_k if k == "default" else k
  if k is not None:
    k = min(int(k), patch_size_cap(points.shape[0]))
  m = keypoints.shape[0]
  if m == 0:
    empty = jnp.zeros((0, 3, 3), jnp.float32), jnp.zeros((0,), bool)
    return (*empty, jnp.zeros((0,), jnp.float32)) if return_confidence else empty
  on_host = _use_host_kernel(spec, kernel, k, options, search) and not return_confidence
  host_patches = _use_host_patch_kernel(spec, kernel, options, search)
  if spec.needs_params and params is None:  # the host kernels read numpy (no JAX to import)
    params = weights_params(spec.weights, weights, host=on_host or host_patches)
  search_patches = _patch_search(points, spec, radius, k, seed, search, on_host or host_patches)
  _warn_on_ball_size(search_patches.index, points, keypoints, radius, unit)
  normals = method_normals(spec, points, radius, faces=faces, normals=normals,
                           viewpoint=viewpoint)
  host_options = dict(spec.default_options) | options
  if host_patches and spec.needs_params and int(host_options.get("lut", 0) or 0) > 1:
    params = cached_weight_table(params, int(host_options["lut"]), host=True)

  # The host kernels compile no shapes: no padded chunk, and the keypoints visited in grid-cell
  # order, so that a chunk's balls share their points in the caches (frames depend on their
  # keypoint alone; they are returned in the caller's order).
  host = on_host or host_patches
  visit = (engine.query_order(search_patches.index.grid(radius), points[keypoints]) if host
           else np.arange(m))

  def run(idx: np.ndarray, n_real: int) -> tuple[AnyArray, ...]:
    kp = keypoints[visit[idx]]
    if on_host:
      return host_frames_in_budget(spec, points, kp, radius, search_patches.index, faces,
                                   normals)
    patches = search_patches(kp)
    extra = prepare_extra(spec, points, kp, patches, radius=radius, faces=faces,
                          normals=normals, viewpoint=viewpoint,
                          oriented=orients(host_options))
    if host_patches:
      assert spec.host_patch_frames is not None  # host_patches says it applies
      out = spec.host_patch_frames(patches, extra, params, host_options)
    else:
      out = patch_frames_checked(spec, patches, params, extra, options)
    if return_confidence:
      assert spec.confidence is not None  # checked by _check_call
      conf = spec.confidence(patches, extra, out[0], out[1], host_options)
      return (*out, np.asarray(conf) if host_patches else conf)
    return out

  n_dev = 1 if host else jax.local_device_count()
  chunk = min(int(chunk_size), -(-m // n_dev) * n_dev)  # a multiple of the devices: shardable
  show = bool(progress) or (progress is None and -(-m // chunk) > 4)
  out = map_chunks(run, m, chunk, pad=not host, progress=show, desc=f"{method} frames")
  if not host:
    return out
  back = np.empty_like(visit)
  back[visit] = np.arange(m)
  return tuple(np.asarray(a)[back] for a in out)  # numpy, as many as `run` gives


class _PatchSearch:
  """`compute_frames`' radius search, on the host engine or on the device: `self(kp) -> Patches`;
  `index` is the host `SearchIndex` (also behind the device search's fallback)."""

  def __init__(self, points: np.ndarray, spec: MethodSpec, radius: float, k: int | None,
               seed: int, on_device: bool):
    self.points, self.spec, self.radius, self.k, self.seed = points, spec, radius, k, seed
    self.device = None
    if on_device:
      from lrf_jax.search.device import DeviceIndex
      assert k is not None  # the device search takes an integer K (`_patch_search`)
      self.device = DeviceIndex(points, radius, k, seed, spec.z_ratio)
      self.index = self.device.host
    else:
      self.index = SearchIndex(points, seed)

  def __call__(self, kp: np.ndarray) -> Patches:
    spec, k = self.spec, self.k
    if self.device is not None:
      from lrf_jax.search.device import build_patches_device
      assert k is not None  # set with the device index
      patches, _ = build_patches_device(self.points, kp, self.radius, k, seed=self.seed,
                                        z_ratio=spec.z_ratio, index=self.device)
      return patches
    return build_patches(self.points, kp, self.radius, k, seed=self.seed,
                         z_ratio=spec.z_ratio, index=self.index,
                         shells=spec.shells if k is None else None, validate=False)


def _use_host_kernel(spec: MethodSpec, kernel: str, k: int | None, options: dict,
                     search: str) -> bool:
  """Whether `compute_frames(kernel=...)` runs the method's host fast path (`kernel` one of
  "auto", "host", "jit", checked by `compute_frames`; a ValueError for "host" where there is
  none)."""
  applies = spec.host_frames is not None and k is None and not options
  if kernel == "host" and not applies and spec.host_patch_frames is None:
    raise ValueError(f"kernel='host': method {spec.name!r} has no host fast path for these "
                     "arguments (it needs METHODS[method].host_frames, k=None and no options); "
                     "use kernel='jit'")
  return applies and _host_requested(kernel, search)


def _host_requested(kernel: str, search: str) -> bool:
  """A host kernel that applies runs: always with kernel="host", with "auto" on a CPU backend
  unless the search runs on the device."""
  return kernel == "host" or (kernel == "auto" and search != "device"
                              and backend_is_cpu())


def _use_host_patch_kernel(spec: MethodSpec, kernel: str, options: dict, search: str) -> bool:
  """Whether `compute_frames(kernel=...)` computes the frames from the patches on the host
  (`METHODS[method].host_patch_frames`, for these options) instead of the jitted function."""
  host = spec.host_patch_frames
  applies = host is not None and host.supports(dict(spec.default_options) | options)
  if kernel == "host" and spec.host_frames is None and not applies:
    raise ValueError(f"kernel='host': method {spec.name!r} has no host kernel for the options "
                     f"{options} (METHODS[method].host_patch_frames); use kernel='jit'")
  return applies and _host_requested(kernel, search)


def _patch_search(points: np.ndarray, spec: MethodSpec, radius: float, k: int | None, seed: int,
                  search: str, host_kernel: bool = False) -> _PatchSearch:
  """The search `compute_frames(search=...)` asks for ("auto", "host" or "device", checked by
  `compute_frames`; on the host for a host kernel)."""
  if host_kernel:
    return _PatchSearch(points, spec, radius, k, seed, False)
  if search == "device" and k is None:
    raise ValueError(f"search='device' needs an integer patch size; method {spec.name!r} uses "
                     "every neighbor (k=None): use search='host'")
  on_device = k is not None and (search == "device" or (
      search == "auto" and not backend_is_cpu()))
  return _PatchSearch(points, spec, radius, k, seed, on_device)
