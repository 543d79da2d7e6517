"""LRF-Net frames (Zhu et al., section 3.1): TOLDI z-axis, learned weights, weighted x-axis.

For one keypoint p with radius neighbors q_i (offsets pq_i = q_i - p):

* z: `geometry.toldi_normal` over all neighbors within r/3 (its sign makes Σ (p - q_i)·z >= 0);
* attributes (eq. `eq_attrib`): a_dist = |pq_i| / r, a_angle = cos(z, pq_i) (0 for the keypoint
  itself, whose direction is undefined);
* weights w_i = WeightNet(a_i) (weights.py);
* x (eqs. `eq_vector_x`, `eq_axis_x`): normalised Σ w_i v_i with v_i = pq_i - (pq_i·z) z;
* y = z × x (eq. `eq_lrf`), rows (x, y, z).

Minimum neighbors: 3 within r/3 (a plane needs 3 points) with a non-degenerate covariance, and a
weighted x-sum that does not vanish (|Σ w_i v_i| > 1e-5 Σ |w_i| |v_i|); otherwise the frame is
returned as the identity with `valid = False`.

The gradient of the loss flows through the weights only: z comes from an eigen-decomposition of
statistics that do not depend on the parameters.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple
from collections.abc import Callable

from lrf_jax._jax import is_jax_numpy, jax, jnp
import numpy as np

from lrf_jax.geometry import ops as geometry
from lrf_jax.frames.spec import HostPatchKernel, MethodSpec
from lrf_jax.frames.weights import Params, apply_weights, apply_weights_numpy
from lrf_jax.search.neighborhoods import Patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray

# |Σ w v| must exceed this fraction of Σ |w| |v| for x to be defined (symmetric patches fail).
X_EPS = 1e-5
MIN_Z_NEIGHBORS = 3


def attributes(offsets: AnyArray, z: jax.Array, radius: AnyArray) -> jax.Array:
  """The two invariant attributes of eq. `eq_attrib` for every neighbor.

  Args:
    offsets: (K, 3) pq_i (cloud units; padding may hold anything finite).
    z: (3,) unit z-axis.
    radius: () support radius r.

  Returns:
    (K, 2) [|pq_i| / r, cos(z, pq_i)]; the cosine is 0 where pq_i = 0.
  """
  dist = geometry.safe_norm(offsets)
  ok = dist > 0
  cos = jnp.where(ok, (offsets @ z) / jnp.where(ok, dist, 1.0), 0.0)
  return jnp.stack([dist / radius, cos], axis=-1)


def x_axis_from_weights(offsets: AnyArray, mask: AnyArray, z: jax.Array,
                        weights: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Weighted vector sum of tangent projections (eqs. `eq_vector_x`, `eq_axis_x`), unnormalised.

  Args:
    offsets: (K, 3) pq_i.
    mask: (K,) bool, False for padding.
    z: (3,) unit z-axis.
    weights: (K,) per-neighbor weights (any sign).

  Returns:
    (s, ok): s (3,) = Σ_i w_i v_i over real neighbors; ok False when it vanishes relative to
    Σ |w_i| |v_i| (e.g. a symmetric planar patch with uniform weights, or all weights zero).

  TOLDI's x axis is this sum with its weights (`toldi.toldi_weights`); the host kernels of both
  compute it with `host_geometry.x_axis_sum_of`.
  """
  w = jnp.where(mask, weights, 0.0)
  v = geometry.tangent_projection(offsets, z)
  s = jnp.sum(w[:, None] * v, axis=0)
  scale = jnp.sum(jnp.abs(w) * geometry.safe_norm(v))
  return s, geometry.safe_norm(s) > X_EPS * scale


def frame_from_weights(offsets: AnyArray, mask: AnyArray, z: jax.Array, z_ok: jax.Array,
                       weights: jax.Array) -> tuple[jax.Array, jax.Array]:
  """A frame (rows x, y, z) from a z-axis and per-neighbor x weights; identity when invalid."""
  s, x_ok = x_axis_from_weights(offsets, mask, z, weights)
  frame, n_ok = geometry.frame_from_zx(z, s)
  valid = z_ok & x_ok & n_ok
  return geometry.identity_where_invalid(frame, valid), valid


def z_axes(patches: Patches) -> tuple[jax.Array, jax.Array]:
  """TOLDI/LRF-Net z-axes of every keypoint: (N, 3) unit vectors and (N,) validity."""
  z, ok = jax.vmap(lambda c, m, n: geometry.toldi_normal(c, m, n, MIN_Z_NEIGHBORS))(
      patches.z_cov, patches.z_mean, patches.z_count)
  return jax.lax.stop_gradient(z), ok


WeightFn = Callable[["AnyArray", "jax.Array", "AnyArray"], "jax.Array"]  # (offsets, z, radius)


def ball_sign(z: jax.Array, offsets: AnyArray, mask: AnyArray) -> jax.Array:
  """Re-orient z so that Σ (p - q_i)·z >= 0 over the whole patch (all radius neighbors kept),
  not only the r/3 ball: TOLDI's sign rule at the full support scale (lrf_net_plus).

  The r/3 centroid height that TOLDI uses is a curvature sign that noise and flat regions flip
  on 8-22% of BR/bunny/UWA3M keypoints; over the 15 mr ball the same rule flips on 1-10%.

  Args:
    z: (N, 3) unit normals. offsets: (N, K, 3). mask: (N, K).

  Returns:
    (N, 3) z, flipped where the patch lies mostly above the tangent plane.
  """
  h = jnp.sum(jnp.where(mask, jnp.einsum("nkc,nc->nk", offsets, z), 0.0), axis=-1)
  return jnp.where((h > 0)[:, None], -z, z)


def view_sign(z: jax.Array, view: AnyArray) -> jax.Array:
  """Orient z towards the sensor where a viewpoint is known (|view| > 0), as PCL orients scan
  normals (`flipNormalTowardsViewpoint`); keypoints with view = 0 keep their z.

  Args:
    z: (N, 3) unit normals. view: (N, 3) sensor position minus keypoint (0: unknown).

  Returns:
    (N, 3) z with z · view >= 0 wherever view is non-zero.
  """
  h = jnp.einsum("nc,nc->n", z, view)
  return jnp.where((h < 0)[:, None], -z, z)


def softmax_weights(scores: jax.Array, mask: AnyArray) -> jax.Array:
  """Attention-style x weights (lrf_net_plus, beyond the paper): w_i = exp(s_i - max_j s_j) over
  the real neighbors of each patch, 0 in padding.

  The network's output is read as a log-weight, so it can concentrate x on a few neighbors (a
  soft version of FLARE's "highest point on the rim") or spread it (a large temperature), and the
  weights are positive. Normalisation is irrelevant (x is normalised), so no division.

  Args:
    scores: (N, K) network outputs. mask: (N, K) bool.

  Returns:
    (N, K) weights in [0, 1], 1 at each patch's best-scored neighbor.
  """
  s = jnp.where(mask, scores, -jnp.inf)
  top = jax.lax.stop_gradient(jnp.max(s, axis=-1, keepdims=True))
  return jnp.where(mask, jnp.exp(s - jnp.where(jnp.isfinite(top), top, 0.0)), 0.0)


def frames_with_weight_fn(patches: Patches, weight_fn: WeightFn, x_mode: str = "sum",
                          z_sign: str = "toldi", view: AnyArray | None = None,
                          area: AnyArray | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Frames for all keypoints given a per-neighbor weight function.

  Args:
    patches: `Patches` with leading axis N.
    weight_fn: (offsets (N, K, 3), z (N, 3), radius (N,)) -> weights (N, K).
    x_mode: "sum" (eq. `eq_axis_x`), "softmax" (the same sum with `softmax_weights` of the
      outputs: lrf_net_plus, beyond the paper) or "max" (the tangent projection of the neighbor
      with the largest weight, the paper's ablation "Max"; no gradient through the argmax).
    z_sign: "toldi" (the paper: sign from the r/3 neighbors) or "ball" (`ball_sign`).
    view: optional (N, 3) sensor position minus keypoint; where non-zero it decides the z sign
      (`view_sign`), overriding `z_sign`.
    area: optional (N, K) surface area each neighbor stands for (`prepare_view`); the weights
      are multiplied by it, so that x does not depend on the sampling density (beyond the paper).

  Returns:
    (frames (N, 3, 3), valid (N,), weights (N, K)).
  """
  patches, finite = geometry.sanitize(patches)
  z, z_ok = z_axes(patches)
  if z_sign == "ball":
    z = ball_sign(z, patches.offsets, patches.mask)
  elif z_sign != "toldi":
    raise ValueError(f"z_sign: expected 'toldi' or 'ball', got {z_sign!r}")
  if view is not None:
    z = view_sign(z, view)
  w = weight_fn(patches.offsets, z, patches.radius)
  if x_mode == "softmax":
    w = softmax_weights(w, patches.mask)
  if area is not None:
    w = w * area
  if x_mode == "max":
    idx = jnp.argmax(jnp.where(patches.mask, w, -jnp.inf), axis=-1)
    w = jax.nn.one_hot(idx, w.shape[-1], dtype=w.dtype)
  elif x_mode not in ("sum", "softmax"):
    raise ValueError(f"x_mode: expected 'sum', 'softmax' or 'max', got {x_mode!r}")
  frames, valid = jax.vmap(frame_from_weights)(patches.offsets, patches.mask, z, z_ok & finite, w)
  return frames, valid, w


def lrf_net_weights(params: Params) -> WeightFn:
  """The learned weight function of LRF-Net for `params`."""

  def fn(offsets, z, radius):
    attrs = jax.vmap(attributes)(offsets, z, radius)
    return apply_weights(params, attrs)

  return fn


class WeightTable(NamedTuple):
  """The weight network tabulated on a size x size grid over (|pq|/r in [0, 1], cos in [-1, 1])
  (`weight_table`); pass it where parameters go, with `lut=size`, to skip rebuilding it."""

  values: AnyArray  # (size, size): jax.Array, numpy from `weight_table_numpy`


def weight_table(params: Params, size: int = 257, xp: Any = jnp) -> WeightTable:
  """Evaluate the network (`weights.apply_weights`) once on the lut grid: size² evaluations
  (about 25 ms for 257 on 2 CPU cores, worth caching when a call has only a few thousand
  keypoints).

  Args:
    params: WeightNet parameters.
    size: grid points per axis: |pq|/r at linspace(0, 1, size), cos at linspace(-1, 1, size).
    xp: jax.numpy (the jitted paths; traceable) or numpy (float32, for the host frame kernels:
      no JAX program to trace and load in a fresh process; equal up to float32 rounding).

  Returns:
    `WeightTable` with values (size, size) [i, j] = w(i / (size - 1), 2 j / (size - 1) - 1),
    an `xp` array (float32 for numpy).
  """
  host = not is_jax_numpy(xp)
  dtype = np.float32 if host else None  # jax.numpy: its default float
  grid = xp.linspace(0.0, 1.0, size, dtype=dtype)
  cgrid = xp.linspace(-1.0, 1.0, size, dtype=dtype)
  attrs = xp.stack(xp.meshgrid(grid, cgrid, indexing="ij"), -1)
  # numpy: one BLAS thread beside numba's (`weights.apply_weights_numpy`)
  return WeightTable(apply_weights_numpy(params, attrs) if host else apply_weights(params, attrs))


def weight_table_numpy(params: Params, size: int = 257) -> WeightTable:
  """`weight_table(params, size, xp=np)`: values (size, size) float32 numpy."""
  return weight_table(params, size, np)


def lut_weights(params: Params | WeightTable, size: int = 257) -> WeightFn:
  """The learned weight function tabulated on a size x size grid over the attribute domain
  (|pq|/r in [0, 1], cos in [-1, 1]) and read by bilinear interpolation.

  The network maps 2 numbers to 1, so one table of size² evaluations replaces K evaluations per
  keypoint (11k multiply-adds each): with K = 256 and 4096-keypoint chunks, 257² is 16x fewer
  network evaluations, and the per-neighbor cost drops to a few gathers. The network is
  piecewise linear (ReLU), so the interpolation error is small; `tests/test_lrf_net.py` bounds
  the frame deviation from the exact weights. `params` may be a prebuilt `WeightTable` of that
  size (`compute_frames` caches one per parameter set).
  """
  table = (params if isinstance(params, WeightTable) else weight_table(params, size)).values
  if table.shape != (size, size):
    raise ValueError(f"lut: a WeightTable of shape {table.shape} was given for lut={size}")

  def fn(offsets, z, radius):
    a = jax.vmap(attributes)(offsets, z, radius)
    u = jnp.clip(a[..., 0], 0.0, 1.0) * (size - 1)
    v = (jnp.clip(a[..., 1], -1.0, 1.0) + 1.0) * 0.5 * (size - 1)
    i0 = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, size - 2)
    j0 = jnp.clip(jnp.floor(v).astype(jnp.int32), 0, size - 2)
    fu, fv = u - i0, v - j0
    t00, t01 = table[i0, j0], table[i0, j0 + 1]
    t10, t11 = table[i0 + 1, j0], table[i0 + 1, j0 + 1]
    return ((1 - fu) * ((1 - fv) * t00 + fv * t01) + fu * ((1 - fv) * t10 + fv * t11))

  return fn


def uniform_weights(offsets, z, radius):
  """w_i = 1 for every neighbor: the "uniform weights, same z" baseline."""
  del z, radius
  return jnp.ones(offsets.shape[:-1], offsets.dtype)


def lrf_net_frames(params: Params, patches: Patches, *, x_mode: str = "sum",
                   z_sign: str = "toldi", lut: int = 0, view: AnyArray | None = None,
                   area: AnyArray | None = None) -> tuple[jax.Array, jax.Array]:
  """LRF-Net frames for a batch of patches (pure; jit it or call through `compute_frames`).

  Args:
    params: WeightNet parameters (`weights.default_params()` for the shipped ones).
    patches: `Patches` (N keypoints, K neighbors).
    x_mode: "sum" (the paper), "softmax" (`softmax_weights`, lrf_net_plus) or "max" (ablation).
    z_sign: "toldi" (the paper) or "ball" (lrf_net_plus, see `ball_sign`).
    lut: 0 evaluates the network per neighbor (exact); n > 1 reads the weights from an n x n
      table of the network (`lut_weights`), much faster at the same K.
    view: optional (N, 3) sensor position minus keypoint (single-view scans): z is oriented
      towards the sensor where it is non-zero (`view_sign`).
    area: optional (N, K) area per neighbor multiplying the weights (`prepare_view`).

  Returns:
    (frames (N, 3, 3) rows x, y, z; valid (N,) bool).
  """
  weight_fn = lut_weights(params, lut) if lut > 1 else lrf_net_weights(params)
  frames, valid, _ = frames_with_weight_fn(patches, weight_fn, x_mode, z_sign, view, area)
  return frames, valid


def uniform_frames(patches: Patches, z_sign: str = "toldi") -> tuple[jax.Array, jax.Array]:
  """LRF-Net's construction with w_i = 1 (the normalised sum of tangent projections)."""
  frames, valid, _ = frames_with_weight_fn(patches, uniform_weights, z_sign=z_sign)
  return frames, valid


# ------------------------------------------------------------------------------ registry entries


def _lrf_net(patches: Patches, extra: None, *, params, x_mode: str = "sum", lut: int = 0):
  del extra
  return lrf_net_frames(params, patches, x_mode=x_mode, lut=lut)


def _uniform(patches: Patches, extra: None, *, z_sign: str = "toldi"):
  del extra
  return uniform_frames(patches, z_sign=z_sign)


def table_host_supports(options: dict) -> bool:
  """Whether `lrf_net_host` computes these options' frames: table weights (lut > 1) with the x
  weights summed or softmaxed (not the ablation's "max")."""
  return int(options.get("lut", 0) or 0) > 1 and options.get("x_mode", "sum") in ("sum", "softmax")


def _lrf_net_host(patches: Patches, extra: None, table: WeightTable, options: dict):
  from lrf_jax.frames.lrf_net_host import lrf_net_frames_host
  del extra
  return lrf_net_frames_host(patches, table.values, x_mode=options.get("x_mode", "sum"),
                             x_eps=X_EPS, min_count=MIN_Z_NEIGHBORS)


def _uniform_host(patches: Patches, extra: None, params: None, options: dict):
  from lrf_jax.frames.lrf_net_host import lrf_net_frames_host
  del extra, params
  return lrf_net_frames_host(patches, None, z_sign=options.get("z_sign", "toldi"), x_eps=X_EPS,
                             min_count=MIN_Z_NEIGHBORS)


SPEC = MethodSpec(
    "lrf_net", _lrf_net, default_k=256, needs_params=True, default_options=(("lut", 257),),
    host_patch_frames=HostPatchKernel(_lrf_net_host, table_host_supports),
    description="LRF-Net (Zhu et al.): TOLDI z over r/3, learned per-point weights for x, read "
                "from a 257 x 257 table by default (lut=257; lut=0: the exact network)")
UNIFORM_SPEC = MethodSpec(
    "uniform", _uniform, default_k=256,
    host_patch_frames=HostPatchKernel(_uniform_host, lambda options: True),
    description="LRF-Net's construction with uniform weights (w = 1): the learned weights' baseline")
