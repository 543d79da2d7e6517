"""lrf_net_plus: LRF-Net's construction with a viewpoint-aware z sign, softmax x weights and
density-corrected weights (beyond the paper).

The jitted math is `lrf_net.lrf_net_frames` (with `z_sign="ball"`, `x_mode="softmax"`, `view=`
and `area=`); this module holds the host side (numpy, outside jit) that gathers its inputs:

* `prepare_view`: per keypoint, the direction z must not point away from (towards the sensor
  of a scan, along the mesh's or the caller's oriented normals, else along normals oriented from
  the points alone, `normals.orient_by_vote`) and how far that direction's sign is trusted;
  its points-alone case is `points_only_view`, which training also calls
  (`TrainConfig.z_view="voted"`, `configs/plus_points.py`) so that both orient z the same way;
* `patch_areas`: the surface area each neighbor stands for (barycentric vertex areas on a mesh,
  the inverse sampling density on a cloud), so that x does not depend on the sampling;

and `sign_confidence`, the per-keypoint confidence of the z sign (`compute_frames(...,
return_confidence=True)`), and its registry entry (`SPEC`, shipped weights `lrf_net_plus`,
trained with `configs/plus_soft.py`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

from lrf_jax._jax import jax, jnp
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.search import engine
from lrf_jax.frames.lrf_net import (MIN_Z_NEIGHBORS, X_EPS, lrf_net_frames,
                                   table_host_supports)
from lrf_jax.frames.spec import KEYPOINT, SLOT, HostPatchKernel, MethodSpec
from lrf_jax.frames.lrf_net_plus_sums import relative_areas, support_sums
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray


# Below this vote margin (`normals.orient_by_vote`) a component's sign is not used and z falls
# back to `ball_sign`: scans of objects vote decisively, indoor rooms (convex furniture and
# concave corners cancel) do not, and there the component's sign would be a coin toss per
# fragment (every keypoint of a pair flipped or none); benchmarks/README.md has the margins.
MIN_VOTE_TRUST = 0.25
# Heights below this fraction of the neighbors' distances count as flat (`sign_confidence`).
FLAT_EPS = 1e-3


class ViewExtra(NamedTuple):
  """`extra` of lrf_net_plus."""

  view: AnyArray         # (N, 3) float32 direction z should not point away from (0: none)
  area: AnyArray | None  # (N, K) float32 area per patch slot, mean 1 over a patch; 0 in padding
  # (N,) float32 in [0, 1]: how far the sign of `view` is trusted (1: a sensor position, the
  # caller's or the mesh's oriented normals; the vote margin of `orient_by_vote` for normals
  # oriented from the points alone; 0 where view = 0). None: 1 wherever view is non-zero.
  trust: AnyArray | None = None
  # A class attribute, not a field: mypy takes it for a field (hence the ignores here and on
  # the constructor calls).
  AXES = {"view": KEYPOINT, "area": SLOT, "trust": KEYPOINT}  # type: ignore[misc]


# ------------------------------------------------------------------------------ host hooks


def prepare_view(points, keypoints, patches, *, faces=None, normals=None, radius=None,
                 viewpoint=None, oriented: bool = True) -> ViewExtra:
  """`MethodSpec.prepare` hook of lrf_net_plus: its `ViewExtra`. `view` is a direction z should
  not point away from, per keypoint (all of them move with the cloud, so z stays equivariant):

  * `viewpoint` given (a single-view scan): sensor position - keypoint;
  * else `normals` given (oriented by the caller): the sum of the normals of the patch
    neighbors within r/3 (the z support);
  * else `faces` given (a mesh): the same with `normals.estimate_normals` (PCA over 0.2 r, outside
    by the triangles' winding: the normals the normal-based LRFs use). Summed over the z support
    as FLARE does (PCL's `flipNormalTowardsNormalsMean`): a single oriented normal disagrees
    between the two sides of a BR pair on 1-7 % of keypoints at 0.5 mr noise, which flips z
    there; the whole patch is too wide for thin parts;
  * else (the points alone, with a radius and patches) the same sum with normals oriented from
    the points (`normals.voted_normals`: PCA over 0.2 r, Hoppe propagation over the cloud, each
    connected component's sign by the majority of convexity votes over r), trusted as far as
    that vote's margin (its `trust` averaged over the z support); where that margin is below
    `MIN_VOTE_TRUST` the view is zero;
  * else zeros (the z sign then comes from `ball_sign`); also for the points alone when
    `oriented` is False (the frames will not read the view: `oriented_sign=False`).

  `trust` (see `ViewExtra`) is 1 for the first three and the vote margin for the fourth; 0 where
  `view` is 0.
  """
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, estimate_normals
  pts = np.asarray(points, np.float64)
  kp = np.asarray(keypoints)
  trust = None
  if viewpoint is not None:
    view = np.asarray(viewpoint, np.float64)[None] - pts[kp]
  elif patches is not None and radius is not None and (normals is not None or faces is not None):
    nrm = (np.asarray(normals, np.float64) if normals is not None else
           estimate_normals(pts, NORMAL_RADIUS_RATIO * float(radius), faces))
    view, trust = support_view(nrm, None, patches, radius)
  elif patches is not None and radius is not None and oriented:
    view, trust = points_only_view(pts, patches, radius)
    return ViewExtra(view, patch_areas(pts, patches, faces), trust)  # type: ignore[call-arg]
  elif normals is not None:
    raise ValueError("prepare_view: normals need the patches and the radius")
  else:
    view = np.zeros((kp.shape[0], 3))
  view, trust = _finish_view(view, trust)
  return ViewExtra(view,  # type: ignore[call-arg]  # AXES is no field
                   patch_areas(pts, patches, faces) if patches is not None else None, trust)


def points_only_normals(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
  """The normals `prepare_view` orients from the points alone: `normals.voted_normals` (PCA over
  `NORMAL_RADIUS_RATIO` r, propagation, each component's sign by convexity votes over r).

  Args:
    points: (n, 3) cloud (cloud units).
    radius: support radius r (cloud units).

  Returns:
    (normals (n, 3) float64, trust (n,) float64 in [0, 1], the vote margin of each point's
    component). They depend on the cloud and r only, so a caller may keep them for another set
    of patches of the same cloud (`points_only_view(..., voted=)`).
  """
  from lrf_jax.geometry.normals import NORMAL_RADIUS_RATIO, voted_normals
  return voted_normals(np.asarray(points, np.float64), NORMAL_RADIUS_RATIO * float(radius),
                       float(radius))


def points_only_view(points: np.ndarray, patches: Patches, radius: float, *,
                     voted: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
  """`prepare_view`'s view and trust for the points alone (no viewpoint, faces or normals):
  `support_view` of `points_only_normals`. Training uses it (`TrainConfig.z_view="voted"`) so
  that its z sign is the one inference gives.

  Args:
    points: (n, 3) cloud (cloud units).
    patches: `Patches` of N keypoints of `points` (their `indices` and `offsets` are read).
    radius: support radius r (cloud units).
    voted: `points_only_normals(points, radius)` if already computed (None: computed here).

  Returns:
    (view (N, 3) float32, trust (N,) float32), as `ViewExtra.view` and `ViewExtra.trust`.
  """
  nrm, per_point = voted if voted is not None else points_only_normals(points, radius)
  return _finish_view(*support_view(nrm, per_point, patches, radius))


def support_view(normals: np.ndarray, per_point: np.ndarray | None, patches: Patches,
                 radius: float) -> tuple[np.ndarray, np.ndarray | None]:
  """The sum of the oriented normals of each patch's neighbors within r/3 (the z support).

  One compiled pass over the patches (`lrf_net_plus_sums.support_sums`); its sums are numpy's
  of the arrays `tests/test_lrf_net_plus_points_only.py` writes out (`support_view_reference` there), bit
  for bit.

  Args:
    normals: (n, 3) oriented normals of the cloud (NaN rows are skipped).
    per_point: (n,) trust of each normal's sign (`points_only_normals`), or None (trusted).
    patches: `Patches` of N keypoints of that cloud.
    radius: support radius r (cloud units).

  Returns:
    (view (N, 3) float64, trust (N,) float64 or None): with `per_point`, trust is its mean over
    the z support and the view is zeroed where it is below `MIN_VOTE_TRUST` (`ball_sign` then).
  """
  idx = np.asarray(patches.indices)
  off = np.asarray(patches.offsets)
  idx = idx if idx.dtype == np.int32 else idx.astype(np.int64)
  off = off if off.dtype == np.float32 else off.astype(np.float64)
  view = np.zeros((idx.shape[0], 3))
  trust = np.zeros(idx.shape[0])
  weigh = per_point is not None
  support_sums(np.ascontiguousarray(normals, np.float64),
               np.ascontiguousarray(per_point if weigh else np.zeros(0), np.float64),
               np.ascontiguousarray(idx), np.ascontiguousarray(off), (float(radius) / 3.0) ** 2,
               weigh, MIN_VOTE_TRUST, view, trust)
  return view, trust if weigh else None


def _finish_view(view: np.ndarray, trust: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
  """(view (N, 3), trust (N,) or None) -> float32 `ViewExtra` fields: NaN views zeroed, trust 0
  where the view is 0 and 1 where it is given without a trust."""
  view = np.nan_to_num(view)
  given = np.any(view != 0, axis=1)
  trust = np.where(given, 1.0 if trust is None else trust, 0.0)
  return view.astype(np.float32), trust.astype(np.float32)


AREA_NEIGHBORS = 8


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
  """(N, K) float32 surface area each patch neighbor stands for, relative to the patch mean.

  With `faces` (a mesh), a vertex's area is its barycentric share of its triangles
  (`vertex_areas`), exact for a mesh; vertices on no triangle, and every point of a cloud, get
  π d² / k with d the distance to its k-th nearest neighbor (k = `AREA_NEIGHBORS`): the inverse
  of the local sampling density. Normalised to mean 1 over each patch's neighbors (0 in
  padding). Rotation and translation invariant.
  """
  from lrf_jax.geometry.cloud_cache import cache_last, cloud_knn

  pts = np.asarray(points, np.float64)

  def estimate(which: np.ndarray) -> np.ndarray:
    kk = min(AREA_NEIGHBORS + 1, len(pts))
    d, _ = engine.knn(engine.knn_grid(pts, kk), pts[which], kk)
    return np.pi * d[:, -1] ** 2 / AREA_NEIGHBORS

  def compute():
    if faces is None or len(faces) == 0:  # every point: the cloud's k-NN, which the
      d = cloud_knn(pts, min(AREA_NEIGHBORS + 1, len(pts)))[0]  # orientation reads too
      return np.pi * d ** 2 / AREA_NEIGHBORS
    area = vertex_areas(pts, faces)
    lone = np.flatnonzero(area <= 0)  # vertices on no triangle: the cloud estimate
    if lone.size:
      area[lone] = estimate(lone)
    return area

  key = (pts,) if faces is None else (pts, np.asarray(faces))
  per_point = cache_last("point_area", key, compute)
  idx = np.asarray(patches.indices)
  idx = np.ascontiguousarray(idx if idx.dtype == np.int32 else idx.astype(np.int64))
  out = np.empty(idx.shape, np.float32)
  relative_areas(np.ascontiguousarray(per_point, np.float64), idx,
                 np.ascontiguousarray(patches.mask, np.bool_), out)
  return out


# ------------------------------------------------------------------------------ sign confidence


def sign_confidence(frames: jax.Array, valid: jax.Array, patches: Patches,
                    extra: ViewExtra | None, oriented_sign: bool = True) -> jax.Array:
  """How sure each keypoint's z sign is, in [0, 1] (pure jnp; beyond the paper).

  * z oriented by a view direction (`view_sign`; `extra.view` non-zero and `oriented_sign`):
    trust · |cos(z, view)|: the trust of the direction's own sign (`ViewExtra.trust`: 1 for a
    sensor position or the caller's / the mesh's oriented normals, the vote margin of
    `normals.orient_by_vote` for normals oriented from the points alone) times how far z is
    from the plane where the two signs tie (a grazing view or normals across an edge);
  * z by `ball_sign` (no view direction): the patch height's share of its absolute heights,
    |Σ_i h_i| / (Σ_i |h_i| + FLAT_EPS Σ_i |pq_i|), h_i = pq_i · z, over the real neighbors (0
    for a flat or symmetric patch, about 1 when the whole patch lies on one side of the tangent
    plane);
  * 0 for an invalid frame.

  Rotation and translation invariant (every term is a dot product of vectors that move with
  the cloud). A matcher can weight correspondences by it or skip frames below a threshold.

  Args:
    frames: (N, 3, 3) frames (rows x, y, z) of these patches.
    valid: (N,) bool.
    patches: their `Patches`.
    extra: their `ViewExtra` (None: the ball sign everywhere).
    oriented_sign: the method's option of that name (False: the ball sign everywhere).

  Returns:
    (N,) float32 confidence (dimensionless).
  """
  def ratio(a, b):
    return jnp.where(b > 0, a / jnp.where(b > 0, b, 1.0), 0.0)

  z = jnp.asarray(frames, jnp.float32)[:, 2]
  offsets = jnp.nan_to_num(jnp.asarray(patches.offsets, jnp.float32))
  mask = jnp.asarray(patches.mask)
  h = jnp.where(mask, jnp.einsum("nkc,nc->nk", offsets, z), 0.0)
  dist = jnp.where(mask, geometry.safe_norm(offsets), 0.0)
  ball = ratio(jnp.abs(jnp.sum(h, -1)), jnp.sum(jnp.abs(h), -1) + FLAT_EPS * jnp.sum(dist, -1))
  if extra is None or not oriented_sign:
    conf = ball
  else:
    view = jnp.asarray(extra.view, jnp.float32)
    norm = geometry.safe_norm(view)
    trust = (jnp.where(norm > 0, 1.0, 0.0) if extra.trust is None
             else jnp.asarray(extra.trust, jnp.float32))
    cos = ratio(jnp.abs(jnp.einsum("nc,nc->n", view, z)), norm)
    conf = jnp.where(norm > 0, trust * cos, ball)
  return jnp.where(jnp.asarray(valid), jnp.clip(conf, 0.0, 1.0), 0.0).astype(jnp.float32)


def _confidence(patches: Patches, extra: ViewExtra | None, frames, valid, options: dict):
  return sign_confidence(frames, valid, patches, extra, bool(options.get("oriented_sign", True)))


# ------------------------------------------------------------------------------ registry entry


def _lrf_net_plus(patches: Patches, extra: ViewExtra | None, *, params, x_mode: str = "softmax",
                  lut: int = 0, density: bool = True, oriented_sign: bool = True,
                  vote: bool = True):
  del vote  # read by the prepare hook (`orients`): without it `extra.view` is zero
  return lrf_net_frames(params, patches, x_mode=x_mode, z_sign="ball", lut=lut,
                        view=None if extra is None or not oriented_sign else extra.view,
                        area=None if extra is None or not density else extra.area)


def _lrf_net_plus_host(patches: Patches, extra: ViewExtra | None, table, options: dict):
  from lrf_jax.frames.lrf_net_host import lrf_net_frames_host
  return lrf_net_frames_host(
      patches, table.values, x_mode=options.get("x_mode", "softmax"), z_sign="ball",
      view=None if extra is None or not options.get("oriented_sign", True) else extra.view,
      area=None if extra is None or not options.get("density", True) else extra.area,
      x_eps=X_EPS, min_count=MIN_Z_NEIGHBORS)


SPEC = MethodSpec(
    "lrf_net_plus", _lrf_net_plus, default_k=512, needs_params=True, weights="lrf_net_plus",
    host_patch_frames=HostPatchKernel(_lrf_net_plus_host, table_host_supports),
    prepare=prepare_view, extra=ViewExtra, uses_viewpoint=True, default_options=(("lut", 257),),
    confidence=_confidence,
    description="Beyond the paper: LRF-Net with the z sign towards the sensor of a scan "
                "(viewpoint=), else from the mesh's or the caller's oriented normals, else from "
                "normals oriented from the points alone (propagation, each component's sign by a "
                "majority of convexity votes), with a per-keypoint sign confidence; the network's "
                "outputs read as log-weights (x_mode='softmax': x can follow a few rim points, as "
                "FLARE's does), trained with noise augmentation (configs/plus_soft.py); weights "
                "times the area each point stands for (density=True: sampling-invariant x); K = 512"
                " (less subsampling noise); the network read from a 257 x 257 table (lut=257, "
                "lut=0: exact)")
