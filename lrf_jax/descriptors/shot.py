"""SHOT352 (Tombari, Salti, Di Stefano 2010) on an external LRF, as PCL 1.13 `SHOTEstimation`.

Bin layout (352 = 32 spatial volumes x 11 cosine bins), histogram index = v * 11 + c:

* spatial volume v = 4 * sector + 2 * shell + upper, 0..31, with
  - sector 0..7: azimuth atan2(y, x) in the LRF, 45 deg sectors centred at -157.5 + 45 * sector
    deg (PCL's bit logic, reproduced exactly);
  - shell: 1 when |q - p| > r/2 (outer of two radial shells);
  - upper: 1 when z > 0 (two elevation halves);
* cosine bin c: b = (1 + n_q . z) * 10 / 2 in [0, 10] for the neighbor's normal n_q and the LRF's
  z; c = floor(b + 0.5) in 0..10 (10 shape bins plus PCL's 11th slot for cos >= 0.9).

Quadrilinear interpolation (PCL `interpolateSingleChannel`): each neighbor votes 1 - |b - c| to
its bin and |b - c| to the adjacent cosine bin ((c +- 1) mod 10: PCL's circular wrap, so b in
[8.5, 9.5) spills into c = 0, not 10), and in each of the radial, elevation and azimuth
directions a weight to its own volume and the complement to the neighboring volume (no spill
beyond the outer shell, the poles, and nothing across the azimuth for points on the z axis).
The histogram is L2-normalised (PCL; the ECCV paper normalised by the sum).

Normal signs (`align_normals`, default True; a deviation from PCL): SHOT's cosines need normals
whose signs agree between the two clouds being matched. Normals estimated on a scan without a
mesh are oriented by propagation, whose global sign can differ from scan to scan, which flips
every cosine. With `align_normals` the patch's normals are flipped together when their sum points
against the LRF's z (Σ n_q · z < 0), so the descriptor depends on the normals only up to one sign
per patch (equivariantly: z is disambiguated by the LRF). `align_normals=False` is PCL exactly
(the agreement test uses it).

Neighbors: every point within r except those at distance 0 (the keypoint itself) and those with
a non-finite normal. Invalid (zeros, `valid = False`): an invalid frame, fewer than 5 points in
the ball (keypoint included, PCL's rule), or an empty histogram.

References:
  Tombari, Salti, Di Stefano, "Unique signatures of histograms for local surface description",
  ECCV 2010. PCL 1.13 `features/impl/shot.hpp`.
"""

from __future__ import annotations

import math

from lrf_jax._jax import jax, jnp

from lrf_jax.descriptors.common import local_coordinates, sanitize_inputs
from lrf_jax.search.neighborhoods import Patches

N_COS = 10                 # PCL nr_shape_bins_
STRIDE = N_COS + 1         # slots per spatial volume
N_VOLUMES = 32
DIM = N_VOLUMES * STRIDE   # 352
MIN_POINTS = 5


def _shot_one(local: jax.Array, dist: jax.Array, cos: jax.Array, use: jax.Array,
              radius: jax.Array) -> jax.Array:
  """Unnormalised SHOT histogram of one keypoint.

  Args:
    local: (K, 3) neighbor coordinates in the LRF.
    dist: (K,) |q - p|.
    cos: (K,) n_q . z, clipped to [-1, 1].
    use: (K,) bool, the neighbors that vote.
    radius: () r.

  Returns:
    (352,) histogram.
  """
  x, y, z = local[:, 0], local[:, 1], local[:, 2]
  bit4 = ((y > 0) | ((y == 0) & (x < 0))).astype(jnp.int32)
  bit3 = jnp.where((x > 0) | ((x == 0) & (y > 0)), 1 - bit4, bit4)
  desc = ((bit4 << 3) + (bit3 << 2)) << 1
  ax, ay = jnp.abs(x), jnp.abs(y)
  desc += jnp.where((x * y > 0) | (x == 0), jnp.where(ax >= ay, 0, 4), jnp.where(ax > ay, 4, 0))
  desc += (z > 0).astype(jnp.int32)
  outer = dist > radius / 2
  desc += 2 * outer.astype(jnp.int32)

  bd = (1.0 + cos) * N_COS / 2.0
  step = jnp.floor(bd + 0.5).astype(jnp.int32)
  frac = bd - step
  own = 1.0 - jnp.abs(frac)
  cos_idx = desc * STRIDE + jnp.where(frac > 0, (step + 1) % N_COS, (step - 1 + N_COS) % N_COS)
  cos_w = jnp.abs(frac)

  # Radial shells.
  rd_out = (dist - 0.75 * radius) / (radius / 2)
  rd_in = (dist - 0.25 * radius) / (radius / 2)
  far = outer & (dist > 0.75 * radius)
  near = ~outer & (dist < 0.25 * radius)
  own += jnp.where(outer, jnp.where(far, 1 - rd_out, 1 + rd_out),
                   jnp.where(near, 1 + rd_in, 1 - rd_in))
  rad_idx = jnp.where(outer, desc - 2, desc + 2) * STRIDE + step
  rad_w = jnp.where(outer, jnp.where(far, 0.0, -rd_out), jnp.where(near, 0.0, rd_in))

  # Elevation.
  safe_d = jnp.where(use, dist, 1.0)
  inc = jnp.arccos(jnp.clip(z / safe_d, -1.0, 1.0))
  lower = (inc > math.pi / 2) | ((jnp.abs(inc - math.pi / 2) < 1e-30) & (z <= 0))
  id_lo = (inc - 0.75 * math.pi) / (math.pi / 2)
  id_up = (inc - 0.25 * math.pi) / (math.pi / 2)
  pole_lo = inc > 0.75 * math.pi
  pole_up = inc < 0.25 * math.pi
  own += jnp.where(lower, jnp.where(pole_lo, 1 - id_lo, 1 + id_lo),
                   jnp.where(pole_up, 1 + id_up, 1 - id_up))
  inc_idx = jnp.where(lower, desc + 1, desc - 1) * STRIDE + step
  inc_w = jnp.where(lower, jnp.where(pole_lo, 0.0, -id_lo), jnp.where(pole_up, 0.0, id_up))

  # Azimuth (not for points on the z axis).
  has_az = (x != 0) | (y != 0)
  az = jnp.arctan2(y, x)
  sel = desc >> 2
  adist = (az - (-7.0 * math.pi / 8.0 + (math.pi / 4.0) * sel)) / (math.pi / 4.0)
  adist = jnp.clip(adist, -0.5, 0.5)
  own += jnp.where(has_az, 1 - jnp.abs(adist), 0.0)
  az_idx = jnp.where(adist > 0, (desc + 4) % N_VOLUMES, (desc - 4 + N_VOLUMES) % N_VOLUMES)
  az_idx = az_idx * STRIDE + step
  az_w = jnp.where(has_az, jnp.abs(adist), 0.0)

  own_idx = desc * STRIDE + step
  idx = jnp.concatenate([own_idx, cos_idx, rad_idx, inc_idx, az_idx])
  w = jnp.concatenate([own, cos_w, rad_w, inc_w, az_w]) * jnp.tile(use, 5)
  idx = jnp.where(jnp.tile(use, 5), idx, 0)
  return jnp.zeros(DIM, local.dtype).at[idx].add(w)


def shot_descriptors(patches: Patches, frames: jax.Array, valid: jax.Array,
                     normals: jax.Array, *,
                     align_normals: bool = True) -> tuple[jax.Array, jax.Array]:
  """SHOT352 descriptors of a batch (pure, jittable).

  Args:
    patches: `Patches` with every neighbor within r (build them with `k=None`).
    frames: (N, 3, 3) LRFs, rows x, y, z, from any method.
    valid: (N,) bool validity of the frames.
    normals: (N, K, 3) the neighbors' unit normals (NaN where undefined, anything in padding),
      e.g. from `lrf_jax.frames.normal_based.prepare_normals`.
    align_normals: flip a patch's normals together when Σ n_q · z < 0 (module docstring);
      False = PCL.

  Returns:
    (descriptors (N, 352) float32, L2 norm 1, zeros where invalid; valid (N,) bool).
  """
  offsets, mask, frames, ok = sanitize_inputs(patches, frames, valid)
  normals = jnp.asarray(normals, offsets.dtype)
  n_ok = jnp.all(jnp.isfinite(normals), axis=-1)
  normals = jnp.where(n_ok[..., None], normals, 0.0)
  local = local_coordinates(offsets, frames)
  dist = jnp.sqrt(jnp.sum(offsets * offsets, axis=-1))
  use = mask & n_ok & (dist > 0)
  cos = jnp.einsum("nkc,nc->nk", normals, frames[:, 2])
  if align_normals:
    flip = jnp.sum(jnp.where(use, cos, 0.0), axis=-1) < 0
    cos = jnp.where(flip[:, None], -cos, cos)
  cos = jnp.clip(cos, -1.0, 1.0)
  radius = jnp.asarray(patches.radius, offsets.dtype)
  hist = jax.vmap(_shot_one)(local, dist, cos, use, jnp.where(ok, radius, 1.0))
  norm = jnp.sqrt(jnp.sum(hist * hist, axis=-1))
  ok = ok & (jnp.asarray(patches.count) >= MIN_POINTS) & (norm > 0)
  desc = hist / jnp.where(ok, norm, 1.0)[:, None]
  return jnp.where(ok[:, None], desc, 0.0), ok
