"""LRF-based local shape descriptors: snapshots, SHOT, RoPS and TOLDI on frames from ANY LRF.

    frames, valid = lrf_jax.compute_frames(points, kp, radius, method="lrf_net")
    desc, ok = lrf_jax.descriptors.compute_descriptors(points, kp, radius, frames, valid,
                                                       descriptor="toldi")

Each descriptor is a pure jnp function of a `Patches` batch (every neighbor within r: `k=None`),
the frames and their validity (plus, for SHOT, the neighbors' normals gathered on the host by a
`prepare` hook), vmapped over keypoints. With an equivariant LRF the descriptors are rotation
invariant: the patch is expressed in the frame before anything is binned.

| name      | dim  | layout (module docstring)                         | original LRF |
|-----------|------|---------------------------------------------------|--------------|
| snapshots | 225  | 15 x 15 height image seen along z                 | mian         |
| shot      | 352  | 32 volumes (8 azimuth x 2 shells x 2 elevation) x 11 cosine bins, L2 = 1 | shot |
| rops      | 135  | 3 axes x 3 rotations x 3 planes x 5 statistics, L1 = 1 | rops (mesh) |
| toldi     | 1200 | 3 views x 20 x 20 min-depth images, empty = 100   | toldi        |

The paper (section 3.2.2) replaces each descriptor's original LRF with LRF-Net's.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any
from collections.abc import Callable

from lrf_jax._jax import backend_is_cpu, jax, jit, jnp
import numpy as np

from lrf_jax.search.chunks import map_chunks
from lrf_jax.descriptors import rops as _rops
from lrf_jax.descriptors import shot as _shot
from lrf_jax.descriptors import snapshots as _snapshots
from lrf_jax.descriptors import toldi as _toldi
from lrf_jax.descriptors.common import ball_patches, bucket_k, local_coordinates, pad_patches
from lrf_jax.descriptors.matching import (Matches, match_descriptors, select_correspondences,
                                          top_correspondences)
from lrf_jax.descriptors.rops import rops_descriptors
from lrf_jax.descriptors.shot import shot_descriptors
from lrf_jax.descriptors.snapshots import snapshot_descriptors
from lrf_jax.descriptors.toldi import toldi_descriptors
from lrf_jax.checks import (validate_choice, validate_cloud, validate_frames, validate_keypoints,
                            validate_radius)
from lrf_jax.search.neighborhoods import Patches, SearchIndex, build_patches, validate_index
from lrf_jax.frames.normal_based import prepare_normals


# Keypoints x neighbor slots per jitted call (bounds the memory of the vmapped descriptors).
MAX_SLOTS = 1 << 20


@dataclasses.dataclass(frozen=True)
class DescriptorSpec:
  """How to compute one descriptor.

  Attributes:
    name: registry key.
    fn: `fn(patches, frames, valid, extra, **options) -> (desc (N, D), valid (N,))`, pure and
      jittable; `extra` is what `prepare` returned (None without a `prepare`).
    dim: descriptor length D with the default options.
    original_lrf: the LRF method the descriptor was published with (a key of `lrf_jax.METHODS`).
    prepare: optional host hook `prepare(points, keypoints, patches, faces=, normals=, radius=)`.
    description: one line for listings.
    host_descriptors: optional host fast path `host_descriptors(points, keypoints, radius,
      frames, valid, index, **options) -> (desc, valid)` over every neighbor (k=None), numpy and
      compiled engine code, the same descriptors as `fn`; `compute_descriptors` runs it by
      default on a CPU backend. Named as `MethodSpec.host_frames` is: `host_` + what it returns.
  """

  name: str
  fn: Callable[..., Any]
  dim: int
  original_lrf: str
  prepare: Callable[..., Any] | None = None
  description: str = ""
  host_descriptors: Callable[..., Any] | None = None


def _snap(patches, frames, valid, extra, **options):
  del extra
  return snapshot_descriptors(patches, frames, valid, **options)


def _shot_fn(patches, frames, valid, extra, **options):
  return shot_descriptors(patches, frames, valid, extra["normals"], **options)


def _rops_fn(patches, frames, valid, extra):
  del extra
  return rops_descriptors(patches, frames, valid)


def _toldi_fn(patches, frames, valid, extra, **options):
  del extra
  return toldi_descriptors(patches, frames, valid, **options)


def _shot_prepare(points, keypoints, patches, *, faces=None, normals=None, radius):
  return {"normals": prepare_normals(points, keypoints, patches, faces=faces, normals=normals,
                                     radius=radius).normals}


DESCRIPTORS: dict[str, DescriptorSpec] = {
    "snapshots": DescriptorSpec(
        "snapshots", _snap, _snapshots.GRID ** 2, "mian",
        description="Snapshots (Malassiotis & Strintzis 2007): height image along the LRF z"),
    "shot": DescriptorSpec(
        "shot", _shot_fn, _shot.DIM, "shot", prepare=_shot_prepare,
        description="SHOT352 (Tombari et al. 2010), PCL's interpolation; needs normals"),
    "rops": DescriptorSpec(
        "rops", _rops_fn, _rops.DIM, "rops",
        description="RoPS (Guo et al. 2013), PCL's statistics; its own LRF needs a mesh"),
    "toldi": DescriptorSpec(
        "toldi", _toldi_fn, 3 * _toldi.GRID ** 2, "toldi",
        description="TOLDI (Yang et al. 2017): three-view local depth images",
        host_descriptors=_toldi.toldi_descriptors_host),
}


def _spec(descriptor: str) -> DescriptorSpec:
  if descriptor not in DESCRIPTORS:
    raise ValueError(f"descriptor: unknown descriptor {descriptor!r}; expected one of "
                     f"{sorted(DESCRIPTORS)}")
  return DESCRIPTORS[descriptor]


@functools.lru_cache(maxsize=32)
def jitted_descriptor(name: str, static_items: tuple) -> Any:
  """The jitted function of descriptor `name` (a key of `DESCRIPTORS`) with the static options
  `static_items` (sorted (name, value) pairs), built once per option set (32 kept;
  `caches.clear_caches` empties it): called as fn(patches, frames, valid, extra) ->
  (descriptors (N, D) float32, valid (N,) bool)."""
  spec = DESCRIPTORS[name]
  return jit(lambda p, f, v, e: spec.fn(p, f, v, e, **dict(static_items)))


def descriptors_from_patches(patches: Patches, frames: Any, valid: Any, descriptor: str, *,
                             extra: Any = None, **options: Any) -> tuple[jax.Array, jax.Array]:
  """Run a registered descriptor's jitted function on prepared patches.

  Args:
    patches: `Patches` (every neighbor within r for the original descriptors).
    frames: (N, 3, 3) frames, rows x, y, z.
    valid: (N,) bool.
    descriptor: a key of `DESCRIPTORS`.
    extra: what the descriptor's `prepare` hook returned (SHOT: the neighbors' normals).
    **options: static options (e.g. `grid=` for snapshots and TOLDI).

  Returns:
    (descriptors (N, D) float32, valid (N,) bool).
  """
  spec = _spec(descriptor)
  if spec.prepare is not None and extra is None:
    raise ValueError(f"descriptor {descriptor!r} needs `extra` from its prepare hook "
                     f"(DESCRIPTORS[{descriptor!r}].prepare), e.g. the neighbors' normals")
  fn = jitted_descriptor(descriptor, tuple(sorted(options.items())))
  return fn(jax.tree.map(jnp.asarray, patches), jnp.asarray(frames, jnp.float32),
            jnp.asarray(valid, bool), extra)


def describe_patches(patches: Patches, frames: Any, valid: Any, descriptor: str, *,
                     points: np.ndarray, keypoints: np.ndarray, radius: float,
                     faces: np.ndarray | None = None, normals: np.ndarray | None = None,
                     chunk_size: int = 256, **options: Any) -> tuple[jax.Array, jax.Array]:
  """Descriptors from already searched patches, in chunks of bucketed shape (bounded memory).

  Args:
    patches: `Patches` of `keypoints` of `points` at radius `radius` (N keypoints).
    frames: (N, 3, 3) frames, rows x, y, z.
    valid: (N,) bool.
    descriptor: a key of `DESCRIPTORS`.
    points: (n, 3) the cloud (for the `prepare` hook).
    keypoints: (N,) indices (for the `prepare` hook).
    radius: r.
    faces: optional triangles (orient estimated normals).
    normals: optional (n, 3) normals for SHOT.
    chunk_size: at most this many keypoints per jitted call (fewer for large balls: at most
      `MAX_SLOTS` keypoint x neighbor slots per call).
    **options: static descriptor options.

  Returns:
    (descriptors (N, D) float32, valid (N,) bool).
  """
  spec = _spec(descriptor)
  n = int(np.shape(patches.mask)[0])
  frames = np.asarray(frames, np.float32)
  valid = np.asarray(valid, bool)
  if n == 0:
    return jnp.zeros((0, spec.dim), jnp.float32), jnp.zeros((0,), bool)
  # Bound keypoints x slots per call (dense balls, e.g. UWAOR's full-resolution scene at the
  # decimated model's mr, hold 30k+ points): about MAX_SLOTS x 0.5 kB for RoPS.
  k_max = bucket_k(max(1, int(np.asarray(patches.mask).sum(axis=1).max())))
  chunk = max(1, min(int(chunk_size), n, MAX_SLOTS // k_max))

  def run(idx: np.ndarray, n_real: int) -> tuple[jax.Array, jax.Array]:
    part = Patches(*(np.asarray(a)[idx] for a in patches))
    k_eff = max(1, int(np.asarray(part.mask).sum(axis=1).max()))
    order = np.argsort(~np.asarray(part.mask), axis=1, kind="stable")[:, :k_eff]
    part = part._replace(offsets=np.take_along_axis(np.asarray(part.offsets), order[..., None], 1),
                         mask=np.take_along_axis(np.asarray(part.mask), order, 1),
                         indices=np.take_along_axis(np.asarray(part.indices), order, 1))
    part = pad_patches(part, bucket_k(k_eff))
    fr, va = frames[idx], valid[idx].copy()
    va[n_real:] = False  # the padding: invalid copies of the chunk's first keypoint
    kp = np.asarray(keypoints)[idx]
    extra = None
    if spec.prepare is not None:
      extra = spec.prepare(points, kp, part, faces=faces, normals=normals, radius=radius)
    return descriptors_from_patches(part, fr, va, descriptor, extra=extra, **options)

  return map_chunks(run, n, chunk)


def compute_descriptors(
    points: Any,
    keypoints: np.ndarray,
    radius: float,
    frames: Any,
    valid: Any = None,
    descriptor: str = "toldi",
    *,
    faces: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    k: int | None = None,
    seed: int = 0,
    chunk_size: int = 256,
    index: SearchIndex | None = None,
    kernel: str = "auto",
    **options: Any,
) -> tuple[jax.Array, jax.Array]:
  """Descriptors of `keypoints` of a cloud on given frames (from any LRF method).

  The radius search runs on the host, chunk by chunk; each chunk's patch size K is bucketed
  (`common.bucket_k`), so a handful of compiled shapes serve every cloud.

  Args:
    points: (n, 3) cloud, or a `CheckedCloud` (its points are not checked again; faces and
      normals are given separately).
    keypoints: (m,) integer indices.
    radius: support radius r (cloud units; the paper: 15 mr, as the LRF).
    frames: (m, 3, 3) frames of the keypoints, rows x, y, z.
    valid: (m,) bool validity of the frames (None: every finite frame).
    descriptor: a key of `DESCRIPTORS`.
    faces: optional (f, 3) triangles (orient SHOT's estimated normals by the winding).
    normals: optional (n, 3) normals for SHOT (default: `lrf_jax.geometry.normals.estimate_normals`).
    k: neighbors per patch; None = every neighbor within r (the original descriptors).
    seed: seed of the subsample when `k` is set.
    chunk_size: keypoints per search and jitted call (memory: about chunk_size x K x 60 bytes
      for SHOT, x 250 bytes for RoPS).
    index: optional prebuilt `SearchIndex(points, seed)`.
    kernel: "jit" (patches, then the jitted descriptor), "host" (the descriptor's host fast path,
      `DESCRIPTORS[descriptor].host_descriptors`: every neighbor, float64, no padded patches;
      needs k=None), or "auto" (host where it applies and the backend is the CPU, else jit).
    **options: static descriptor options (`grid=`, `empty=`, `align_normals=`).

  Returns:
    (descriptors (m, D) float32, zeros where invalid; valid (m,) bool).

  Raises:
    ValueError: a bad cloud, keypoints, radius, frames or descriptor name.
  """
  _spec(descriptor)  # a ValueError for an unknown descriptor, before the other arguments
  from lrf_jax.geometry.cloud import CheckedCloud
  points = points.points if isinstance(points, CheckedCloud) else validate_cloud(points)
  keypoints = validate_keypoints(keypoints, points.shape[0])
  radius = validate_radius(radius)
  frames, valid = validate_frames(frames, valid, keypoints.shape[0])
  if int(chunk_size) < 1:
    raise ValueError(f"chunk_size: expected a positive integer, got {chunk_size!r}")
  validate_choice("kernel", kernel, ("auto", "host", "jit"))  # also with no keypoints
  if index is not None:
    validate_index(index, points)
  return descriptors_checked(descriptor, points, keypoints, radius, frames, valid, faces=faces,
                              normals=normals, k=k, seed=seed, chunk_size=chunk_size,
                              index=index, kernel=kernel, options=options)


def descriptors_checked(descriptor: str, points: np.ndarray, keypoints: np.ndarray,
                         radius: float, frames: np.ndarray, valid: np.ndarray, *,
                         faces: np.ndarray | None = None, normals: np.ndarray | None = None,
                         k: int | None = None, seed: int = 0, chunk_size: int = 256,
                         index: SearchIndex | None = None, kernel: str = "auto",
                         options: dict | None = None) -> tuple[jax.Array, jax.Array]:
  """`compute_descriptors` after its argument checks: the same arguments (and defaults), already
  checked by `compute_descriptors` (or by `register`, for the clouds it read, the keypoints it
  drew and the frames `compute_frames` gave), `kernel` and `index` included.

  Args:
    descriptor: a key of `DESCRIPTORS`.
    points: (n, 3) finite float64 cloud (`validate_cloud`).
    keypoints: (m,) int64 indices into it (`validate_keypoints`).
    radius: support radius r (cloud units; `validate_radius`'s range).
    frames: (m, 3, 3) float32 frames, rows x, y, z; valid: (m,) bool (`validate_frames`).
    faces: optional (f, 3) triangles, as `compute_descriptors` takes them.
    normals: optional (n, 3) normals, as `compute_descriptors` takes them.
    k: neighbors per patch (None: every neighbor within r).
    seed: seed of the subsample when `k` is set.
    chunk_size: a positive integer.
    index: optional prebuilt `SearchIndex(points, seed)`.
    kernel: "jit", "host" or "auto" (`compute_descriptors`).
    options: static descriptor options.

  Returns:
    As `compute_descriptors`.
  """
  spec = DESCRIPTORS[descriptor]
  options = {} if options is None else options
  m = keypoints.shape[0]
  if m == 0:
    return jnp.zeros((0, spec.dim), jnp.float32), jnp.zeros((0,), bool)
  if index is None or index.seed != seed or index.points.shape != points.shape:
    index = SearchIndex(points, seed)
  applies = spec.host_descriptors is not None and k is None
  if kernel == "host" and not applies:
    raise ValueError(f"kernel='host': descriptor {descriptor!r} has no host fast path for these "
                     "arguments (it needs DESCRIPTORS[descriptor].host_descriptors and k=None)")
  if kernel == "host" or (kernel == "auto" and applies and backend_is_cpu()):
    assert spec.host_descriptors is not None  # applies (kernel="host" raised above otherwise)
    host = spec.host_descriptors
    run_host = lambda idx, n_real: host(points, keypoints[idx], radius, frames[idx], valid[idx],
                                        index, **options)
    return map_chunks(run_host, m, min(int(chunk_size) * 16, m), pad=False)

  def run(idx: np.ndarray, n_real: int) -> tuple[jax.Array, jax.Array]:
    kp = keypoints[idx]
    if k is None:  # the whole ball: one plain radius search
      patches = ball_patches(index, points, kp, radius)
    else:
      patches = build_patches(points, kp, radius, k, seed=seed, index=index, validate=False)
    return describe_patches(patches, frames[idx], valid[idx], descriptor, points=points,
                            keypoints=kp, radius=radius, faces=faces, normals=normals,
                            chunk_size=len(idx), **options)

  return map_chunks(run, m, min(int(chunk_size), m), pad=False)


__all__ = [
    "select_correspondences",
    "DESCRIPTORS", "DescriptorSpec", "Matches", "compute_descriptors", "describe_patches",
    "descriptors_from_patches",
    "local_coordinates", "match_descriptors", "pad_patches", "rops_descriptors",
    "shot_descriptors", "snapshot_descriptors", "toldi_descriptors", "top_correspondences",
]
