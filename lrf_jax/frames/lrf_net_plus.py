"""lrf_net_plus: LRF-Net's construction with a viewpoint-aware z sign, softmax x weights and
density-corrected weights (beyond the paper).

The jitted math is `lrf_net.lrf_net_frames` (with `z_sign="ball"`, `x_mode="softmax"`, `view=`
and `area=`); this module holds the host side (numpy, outside jit) that gathers its inputs:

* `prepare_view`: per keypoint, the direction z must not point away from (towards the sensor
  of a scan, along the mesh's oriented normals, or none);
* `patch_areas`: the surface area each neighbour stands for (barycentric vertex areas on a mesh,
  the inverse sampling density on a cloud), so that x does not depend on the sampling;

and its registry entry (`SPEC`, shipped weights `lrf_net_plus`, trained with
`configs/plus_soft.py`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lrf_jax.search import engine
from lrf_jax.frames.lrf_net import (MIN_Z_NEIGHBOURS, X_EPS, lrf_net_frames,
                                   table_host_supports)
from lrf_jax.frames.spec import KEYPOINT, SLOT, HostPatchKernel, MethodSpec
from lrf_jax.search.neighborhoods import Patches


class ViewExtra(NamedTuple):
  """`extra` of lrf_net_plus."""

  view: np.ndarray         # (N, 3) float32 direction z should not point away from (0: none)
  area: np.ndarray | None  # (N, K) float32 area per patch slot, mean 1 over a patch; 0 in padding
  AXES = {"view": KEYPOINT, "area": SLOT}


# ------------------------------------------------------------------------------ host hooks


def prepare_view(points, keypoints, patches, *, faces=None, normals=None, radius=None,
                 viewpoint=None) -> ViewExtra:
  """`MethodSpec.prepare` hook of lrf_net_plus: its `ViewExtra`. `view` is a direction z should
  not point away from, per keypoint (all of them move with the cloud, so z stays equivariant):

  * `viewpoint` given (a single-view scan): sensor position - keypoint;
  * else `normals` given (oriented by the caller): the sum of the normals of the patch
    neighbours within r/3 (the z support);
  * else `faces` given (a mesh): the same with `normals.estimate_normals` (PCA over 0.2 r, outside
    by the triangles' winding: the normals the normal-based LRFs use). Summed over the z support
    as FLARE does (PCL's `flipNormalTowardsNormalsMean`): a single oriented normal disagrees
    between the two sides of a BR pair on 1-7 % of keypoints at 0.5 mr noise, which flips z
    there; the whole patch is too wide for thin parts;
  * else zeros (the z sign then comes from `ball_sign`).
  """
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals
  pts = np.asarray(points, np.float64)
  kp = np.asarray(keypoints)
  if viewpoint is not None:
    view = np.asarray(viewpoint, np.float64)[None] - pts[kp]
  elif normals is not None or (faces is not None and radius is not None):
    nrm = (np.asarray(normals, np.float64) if normals is not None else
           estimate_normals(pts, NORMAL_RADIUS_RATIO * float(radius), faces))
    idx = np.asarray(patches.indices)
    off = np.asarray(patches.offsets, np.float64)
    near = (idx >= 0) & (np.einsum("nkc,nkc->nk", off, off) <= (float(radius) / 3.0) ** 2)
    view = np.where(near[..., None], np.nan_to_num(nrm[np.maximum(idx, 0)]), 0.0).sum(1)
  else:
    view = np.zeros((kp.shape[0], 3))
  return ViewExtra(np.nan_to_num(view).astype(np.float32),
                   patch_areas(pts, patches, faces) if patches is not None else None)


AREA_NEIGHBOURS = 8


def vertex_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """(n,) barycentric vertex areas of a triangle mesh: a third of the area of every incident
  triangle (0 for a vertex on no triangle). They sum to the mesh's area."""
  tri = np.asarray(points, np.float64)[np.asarray(faces)]
  area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
  out = np.zeros(len(points))
  for j in range(3):
    np.add.at(out, np.asarray(faces)[:, j], area / 3.0)
  return out


def patch_areas(points: np.ndarray, patches: Patches,
                faces: np.ndarray | None = None) -> np.ndarray:
  """(N, K) float32 surface area each patch neighbour stands for, relative to the patch mean.

  With `faces` (a mesh), a vertex's area is its barycentric share of its triangles
  (`vertex_areas`), exact for a mesh; vertices on no triangle, and every point of a cloud, get
  π d² / k with d the distance to its k-th nearest neighbour (k = `AREA_NEIGHBOURS`): the inverse
  of the local sampling density. Normalised to mean 1 over each patch's neighbours (0 in
  padding). Rotation and translation invariant.
  """
  from lrf_jax.geometry.normals import cache_last

  pts = np.asarray(points, np.float64)

  def estimate(which: np.ndarray) -> np.ndarray:
    kk = min(AREA_NEIGHBOURS + 1, len(pts))
    d, _ = engine.knn(engine.knn_grid(pts, kk), pts[which], kk)
    return np.pi * d[:, -1] ** 2 / AREA_NEIGHBOURS

  def compute():
    if faces is None or len(faces) == 0:
      return estimate(np.arange(len(pts)))
    area = vertex_areas(pts, faces)
    lone = np.flatnonzero(area <= 0)  # vertices on no triangle: the cloud estimate
    if lone.size:
      area[lone] = estimate(lone)
    return area

  key = (pts,) if faces is None else (pts, np.asarray(faces))
  per_point = cache_last("point_area", key, compute)
  idx = np.asarray(patches.indices)
  a = np.where(idx >= 0, per_point[np.maximum(idx, 0)], 0.0)
  mean = a.sum(1, keepdims=True) / np.maximum((idx >= 0).sum(1, keepdims=True), 1)
  return (a / np.where(mean > 0, mean, 1.0)).astype(np.float32)


# ------------------------------------------------------------------------------ registry entry


def _lrf_net_plus(patches: Patches, extra: ViewExtra | None, *, params, x_mode: str = "softmax",
                  lut: int = 0, density: bool = True, oriented_sign: bool = True):
  return lrf_net_frames(params, patches, x_mode=x_mode, z_sign="ball", lut=lut,
                        view=None if extra is None or not oriented_sign else extra.view,
                        area=None if extra is None or not density else extra.area)


def _lrf_net_plus_host(patches: Patches, extra: ViewExtra | None, table, options: dict):
  from lrf_jax.frames.lrf_net_host import lrf_net_frames_host
  return lrf_net_frames_host(
      patches, table.values, x_mode=options.get("x_mode", "softmax"), z_sign="ball",
      view=None if extra is None or not options.get("oriented_sign", True) else extra.view,
      area=None if extra is None or not options.get("density", True) else extra.area,
      x_eps=X_EPS, min_count=MIN_Z_NEIGHBOURS)


SPEC = MethodSpec(
    "lrf_net_plus", _lrf_net_plus, default_k=512, needs_params=True, weights="lrf_net_plus",
    host_patch_frames=HostPatchKernel(_lrf_net_plus_host, table_host_supports),
    prepare=prepare_view, extra=ViewExtra, uses_viewpoint=True, default_options=(("lut", 257),),
    description="Beyond the paper: LRF-Net with the z sign towards the sensor of a scan "
                "(viewpoint=), else from the mesh's oriented normals, else over the whole "
                "support (ball_sign); the network's outputs read as log-weights "
                "(x_mode='softmax': x can follow a few rim points, as FLARE's does), trained "
                "with noise augmentation (configs/plus_soft.py); weights times the area each "
                "point stands for (density=True: sampling-invariant x); K = 512 (less "
                "subsampling noise); the network read from a 257 x 257 table (lut=257, "
                "lut=0: exact)")
