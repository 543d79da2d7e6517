"""The one rule that feeds a method's `prepare` hook: which normals, oriented how, which viewpoint.

`compute_frames`, the evaluation protocols, the descriptors' frames and `register` all go through
`method_normals` and `prepare_extra`, so a method sees the same inputs on every path.
"""

from __future__ import annotations

from typing import Any
from collections.abc import Callable

import numpy as np

from lrf_jax.frames.spec import MethodSpec
from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals

# The caller's (n, 3) normals; or None (estimate them when the method needs them) or a thunk that
# returns that estimate (so that a caller holding a cache estimates them only when needed).
NormalsArg = np.ndarray | None | Callable[[], np.ndarray]


def method_normals(spec: MethodSpec, points: np.ndarray, radius: float, *,
                   faces: np.ndarray | None = None, normals: NormalsArg = None,
                   viewpoint: np.ndarray | None = None) -> np.ndarray | None:
  """The per-point normals `spec.prepare` is given (None: it gets none).

  The rule:
  * a method whose hook reads no normals (`needs_normals` False, not viewpoint-aware): None;
  * a viewpoint-aware method (`uses_viewpoint`, lrf_net_plus) orients its z by the viewpoint
    when there is one; without one it reads the caller's normals, else, on a mesh, normals
    estimated and oriented by the faces' winding; a cloud without either gets None (its hook
    then orients normals from the points itself, `normals.voted_normals`: propagation alone has
    no reliable outside on a cloud, the per-component vote gives it one);
  * a hook with `needs_normals` (the normal-based methods, GFrames) gets the caller's normals, else
    `estimate_normals` (PCA over `NORMAL_RADIUS_RATIO` · r, oriented by the faces, else towards
    the viewpoint, else by propagation).

  Args:
    spec: the method.
    points: (n, 3) cloud.
    radius: support radius r (normals are estimated over 0.2 r).
    faces: optional (f, 3) triangles.
    normals: the caller's (n, 3) normals; or None or a thunk: estimate them (the thunk returns
      the estimate `estimate_normals` would, e.g. from the caller's cache).
    viewpoint: optional (3,) sensor position, validated by the caller.

  Returns:
    (n, 3) normals or None.
  """
  if spec.prepare is None or not (spec.needs_normals or spec.uses_viewpoint):
    return None
  given = normals is not None and not callable(normals)
  if spec.uses_viewpoint:
    if viewpoint is not None or (not given and faces is None):
      return None
    if given:
      assert normals is not None and not callable(normals)  # what `given` says
      return normals
    return normals() if callable(normals) else estimate_normals(
        points, NORMAL_RADIUS_RATIO * radius, faces)
  if given:
    assert normals is not None and not callable(normals)
    return normals
  return normals() if callable(normals) else estimate_normals(
      points, NORMAL_RADIUS_RATIO * radius, faces, viewpoint)


def orients(options: dict) -> bool:
  """Whether a viewpoint-aware method's frames read an orientation from the points alone, for
  these options (the method's defaults filled in or not): lrf_net_plus's `oriented_sign` and
  `vote` (False: the convexity vote of `normals.voted_normals` is skipped and a cloud without
  a viewpoint, normals or mesh takes the ball sign). `prepare_extra`'s `oriented`."""
  return bool(options.get("oriented_sign", True)) and bool(options.get("vote", True))


def prepare_extra(spec: MethodSpec, points: np.ndarray, keypoints: np.ndarray, patches: Any, *,
                  radius: float, faces: np.ndarray | None = None, normals: NormalsArg = None,
                  viewpoint: np.ndarray | None = None, oriented: bool = True) -> Any:
  """What `spec.prepare` returns for these keypoints' patches (None without a hook).

  Args:
    spec: the method.
    points: (n, 3) cloud.
    keypoints: (N,) indices of the patches' keypoints.
    patches: their `Patches`.
    radius: support radius r.
    faces: optional (f, 3) triangles.
    normals: the caller's normals, a thunk returning them, or None (see `method_normals`).
    viewpoint: optional (3,) sensor position (viewpoint-aware methods read it themselves).
    oriented: for viewpoint-aware methods, whether their frames read an orientation from the
      points alone (`orients` of the method's options); False spares orienting the normals of a
      bare cloud.

  Returns:
    An instance of `spec.extra`, or None.
  """
  if spec.prepare is None:
    return None
  nrm = method_normals(spec, points, radius, faces=faces, normals=normals, viewpoint=viewpoint)
  vp = {"viewpoint": viewpoint, "oriented": bool(oriented)} if spec.uses_viewpoint else {}
  return spec.prepare(points, keypoints, patches, faces=faces, normals=nrm, radius=radius, **vp)
