"""The methods' host fast paths on every neighbor: what a method declares (`BallKernel`) and how
any of them runs over many keypoints (`host_frames`).

A `BallKernel` is the `MethodSpec.host_frames` of a built-in method: its numba kernel and the
names of the inputs the kernel reads, built here for every method alike from the engine's ball
lists (`host_geometry.ball_lists`), so that a method module holds only its own kernel. The
kernel computes, in float64 and one keypoint per thread, the frames its method's jitted
function computes from padded patches (to float32 rounding). `host_frames` runs a method's
`MethodSpec.host_frames` (a `BallKernel` or any callable of that signature) over keypoints in
groups whose ball lists fit `HOST_NEIGHBOR_BUDGET`.
"""

from __future__ import annotations

import dataclasses
from typing import Any
from collections.abc import Callable

import numpy as np

from lrf_jax.frames import host_geometry as hg
from lrf_jax.frames.normal_based import usable_normals
from lrf_jax.frames.spec import MethodSpec, method_spec
from lrf_jax.search import engine
from lrf_jax.search.neighborhoods import SearchIndex, validate_index

# The inputs a `BallKernel` may name, each built per call from the call's arguments:
# "keypoints": (N,) int64, the keypoints' rows of the cloud;
# "counts": (N,) int64, the points within r of each keypoint (all of them, whatever `shells`);
# "normals": (n, 3) float64 per-point normals, NaN where they carry no direction
#   (`normal_based.usable_normals`);
# "keypoint_normals": (N, 3) float64, the same normals of the keypoints alone;
# "radius": the support radius r (float);
# "rz2": (z_ratio · r)², the squared radius of the z support (float);
# "mesh": the arrays `BallKernel.mesh` returns, one argument each.
BALL_INPUTS = ("keypoints", "counts", "normals", "keypoint_normals", "radius", "rz2", "mesh")


@dataclasses.dataclass(frozen=True)
class BallKernel:
  """A method's host fast path as data: its kernel and how the kernel's arguments are built.

  Called as `MethodSpec.host_frames` is, `self(points (n, 3) float64, keypoints (N,) int, radius,
  index, *, faces=, normals=) -> (frames (N, 3, 3) float32, valid (N,) bool)`, it lists every
  point within `radius` of each keypoint (the cloud's `SearchIndex`, `engine.ball_lists`), then
  runs

      kernel(points, centers, ptr, ball, *inputs, *constants, frames, valid)

  on the float64 cloud (n, 3), the keypoints' coordinates `centers` (N, 3), the ball lists
  (ball i is `ball[ptr[i]:ptr[i + 1]]`), the named inputs in order and the constants, into
  fresh (N, 3, 3) float64 `frames` and (N,) bool `valid` (`host_geometry.run_kernel`).

  Attributes:
    kernel: the numba kernel (`nb.njit(parallel=True, cache=True)`), which sets every frame i
      (the identity with `valid[i] = False` where the frame is invalid).
    inputs: names from `BALL_INPUTS`, in the kernel's order.
    constants: values passed after the inputs (tolerances, fixed options).
    z_ratio: the z support as a fraction of r, for the input "rz2" (the method's
      `MethodSpec.z_ratio`).
    shells: (a, b): list only the points within a · r or beyond b · r (the method's
      `MethodSpec.shells`); None: the whole ball.
    mesh: for the input "mesh": `mesh(points (n, 3) float64, faces) -> tuple of arrays` the
      kernel reads of the triangle mesh (computed once per mesh where the method caches them).
  """

  kernel: Callable[..., Any]
  inputs: tuple[str, ...] = ()
  constants: tuple[Any, ...] = ()
  z_ratio: float | None = None
  shells: tuple[float, float] | None = None
  mesh: Callable[[np.ndarray, Any], tuple[np.ndarray, ...]] | None = None

  def __post_init__(self):
    unknown = sorted(set(self.inputs) - set(BALL_INPUTS))
    if unknown:
      raise ValueError(f"BallKernel: unknown inputs {unknown}; expected names from {BALL_INPUTS}")
    if "rz2" in self.inputs and self.z_ratio is None:
      raise ValueError("BallKernel: the input 'rz2' needs z_ratio")
    if ("mesh" in self.inputs) != (self.mesh is not None):
      raise ValueError("BallKernel: the input 'mesh' and the mesh hook go together")

  def __call__(self, points: np.ndarray, keypoints: np.ndarray, radius: float, index: Any, *,
               faces: Any = None, normals: Any = None) -> tuple[np.ndarray, np.ndarray]:
    lists = hg.ball_lists(points, keypoints, radius, index, self.shells,
                          "counts" in self.inputs)
    pts, centers, ptr, ball = lists[:4]
    args: list[Any] = []
    for name in self.inputs:
      if name == "keypoints":
        args.append(np.asarray(keypoints, np.int64))
      elif name == "counts":
        args.append(lists[4])
      elif name == "normals":
        args.append(usable_normals(normals))
      elif name == "keypoint_normals":
        args.append(usable_normals(np.asarray(normals)[np.asarray(keypoints)]))
      elif name == "radius":
        args.append(float(radius))
      elif name == "rz2":
        assert self.z_ratio is not None  # checked in __post_init__
        rz = float(self.z_ratio * radius)
        args.append(rz * rz)
      else:  # "mesh"
        assert self.mesh is not None  # checked in __post_init__
        args.extend(self.mesh(pts, faces))
    return hg.run_kernel(self.kernel, len(centers), pts, centers, ptr, ball, *args,
                         *self.constants)


# Ball-list entries (8 bytes each) a host fast path holds at a time.
HOST_NEIGHBOR_BUDGET = 1 << 24


def host_frames_in_budget(spec: MethodSpec, points: np.ndarray, kp: np.ndarray, radius: float,
                          index: SearchIndex, faces: Any, normals: Any,
                          counts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
  """`spec.host_frames` over `kp` in groups whose balls hold at most `HOST_NEIGHBOR_BUDGET`
  points together (one keypoint at least), so memory does not grow with the ball size.

  Args:
    spec: a method whose `host_frames` is set.
    points: (n, 3) float64 cloud.
    kp: (N,) int64 keypoints.
    radius: support radius r.
    index: the cloud's `SearchIndex`.
    faces: (f, 3) triangles or None.
    normals: (n, 3) normals as `normals_rule.method_normals` gives them, or None.
    counts: (N,) points within `radius` of each keypoint, if already counted.

  Returns:
    (frames (N, 3, 3) float32, valid (N,) bool), numpy, in the order of `kp`.
  """
  if counts is None:
    counts = engine.ball_counts(index.grid(radius), points[kp], radius)
  group = np.cumsum(counts) // HOST_NEIGHBOR_BUDGET
  cuts = np.flatnonzero(np.diff(group)) + 1
  assert spec.host_frames is not None  # both callers check it
  parts = [spec.host_frames(points, part, radius, index, faces=faces, normals=normals)
           for part in np.split(kp, cuts)]
  return np.concatenate([f for f, _ in parts]), np.concatenate([v for _, v in parts])


def _in_callers_order(order: np.ndarray, frames: Any, valid: Any) -> tuple[np.ndarray, np.ndarray]:
  """Frames and validity computed for kp[order], as numpy arrays in the order of kp."""
  back = np.empty_like(order)
  back[order] = np.arange(len(order))
  return np.asarray(frames)[back], np.asarray(valid)[back]


def host_frames(points: np.ndarray, keypoints: np.ndarray, radius: float, method: str, *,
                index: SearchIndex, faces: np.ndarray | None = None,
                normals: np.ndarray | None = None, ball_counts: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
  """A method's host fast path over every neighbor (`compute_frames(kernel="host")` without the
  argument checks, normal estimation or chunking): for callers that already hold the index.
  Keypoints are visited in grid-cell order; the results come back in the order given.

  Args:
    points: (n, 3) float64 cloud, validated.
    keypoints: (m,) int64 indices into `points`.
    radius: support radius r (> 0).
    method: a key of `METHODS` whose `host_frames` is set.
    index: `SearchIndex(points, seed)` (the host paths read every neighbor; the seed only
      orders the grid).
    faces: (f, 3) triangles for mesh methods.
    normals: (n, 3) normals as `normals_rule.method_normals` gives them (None for methods
      without).
    ball_counts: (m,) points within `radius` of each keypoint, if already counted.

  Returns:
    (frames (m, 3, 3) float32 rows x, y, z, valid (m,) bool), as numpy arrays.

  Raises:
    ValueError: a method without a host fast path, or an `index` not built from `points`.
  """
  spec = method_spec(method)
  if spec.host_frames is None:
    raise ValueError(f"method {method!r} has no host fast path (METHODS[method].host_frames)")
  validate_index(index, points)
  kp = np.asarray(keypoints, np.int64)
  order = engine.query_order(index.grid(radius), points[kp])  # cache-friendly, as compute_frames
  counts = None if ball_counts is None else np.asarray(ball_counts)[order]
  frames, valid = host_frames_in_budget(spec, points, kp[order], float(radius), index, faces,
                                        normals, counts)
  return _in_callers_order(order, frames, valid)
