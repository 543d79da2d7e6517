"""Training batches of LRF-Net (paper section 3.2): keypoints, patches, augmentation, sharding.

A fixed, seeded set of training keypoints over corresponding clouds (noise-free BR: each model
and the same model under a scene's ground truth). An epoch is one pass in a seeded shuffled
order; every batch is rebuilt from (seed, epoch, batch index) alone, with 256 points sampled
independently on each side, so a resumed run sees exactly the batches it would have. In a
multi-process run every process builds the same global batch from the seed and places only the
rows of its own devices (`global_batch`). With `config.z_view="voted"` each side of a batch also
carries the view direction that orients z at inference from the points alone
(`lrf_net_plus.points_only_view`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, NamedTuple, cast

import jax
import numpy as np
from jax.sharding import NamedSharding

from lrf_jax.frames.lrf_net_plus import points_only_normals, points_only_view
from lrf_jax.learning.config import TrainConfig
from lrf_jax.search.neighborhoods import Patches, build_patches

if TYPE_CHECKING:
  from lrf_jax.search.neighborhoods import AnyArray


@dataclasses.dataclass(frozen=True)
class TrainingClouds:
  """Corresponding clouds and the fixed training keypoints over them.

  Attributes:
    models: list of (n_c, 3) model clouds.
    scenes: list of (n_c, 3) scene clouds; scene point i corresponds to model point i.
    radii: (C,) support radius of each cloud in its units (radius_mr x the model's mr).
    mr: (C,) mesh resolution of each model.
    keypoints: (P, 2) int64 rows (cloud id, point index): the training set of one epoch.
    names: cloud names, for logs.
  """

  models: list[np.ndarray]
  scenes: list[np.ndarray]
  radii: np.ndarray
  mr: np.ndarray
  keypoints: np.ndarray
  names: list[str]


def _mix(*ints: int) -> int:
  """A deterministic 63-bit seed from integers (so batch seeds depend only on their position)."""
  return int(np.random.SeedSequence(list(ints)).generate_state(1, np.uint64)[0] >> np.uint64(1))


def sample_training_keypoints(sizes: list[int], count: int, seed: int,
                              exclude: list[np.ndarray] | None = None) -> np.ndarray:
  """A seeded set of (cloud id, point index) drawn uniformly over all points of all clouds.

  Args:
    sizes: points per cloud.
    count: keypoints wanted.
    seed: seed.
    exclude: per cloud, point indices that may not be drawn (the evaluation keypoints).

  Returns:
    (count, 2) int64.
  """
  pool = []
  for c, n in enumerate(sizes):
    ok = np.ones(n, bool)
    if exclude is not None and len(exclude[c]):
      ok[exclude[c]] = False
    idx = np.flatnonzero(ok)
    pool.append(np.stack([np.full(idx.size, c), idx], axis=1))
  pool = np.concatenate(pool)
  rng = np.random.default_rng(_mix(seed, 1))
  return pool[np.sort(rng.choice(len(pool), size=min(count, len(pool)), replace=False))]


class Batch(NamedTuple):
  """Corresponding patches: `model[i]` and `scene[i]` are one training pair.

  `model_view` / `scene_view`: with `TrainConfig.z_view="voted"`, (N, 3) float32 per side, the
  direction z must not point away from (`lrf_net_plus.points_only_view` on that side's cloud,
  in cloud units; 0: the `z_sign` rule decides); None otherwise (no leaves: the batch is the
  two `Patches` alone).
  """

  model: Patches
  scene: Patches
  model_view: AnyArray | None = None  # numpy on the host, jax.Array after `global_batch`
  scene_view: AnyArray | None = None


def crop_patches(patches: Patches, p: float, min_dist: float,
                 rng: np.random.Generator) -> Patches:
  """Partiality augmentation: cut a random fraction `p` of the patches by a plane.

  For a cut patch, a direction u uniform on the sphere and a distance c uniform in
  [min_dist, 1) · r are drawn; the neighbors with offset · u > c are dropped (mask False, offset
  0, index -1), as if a scan's boundary ran there. The keypoint side of the plane is kept, and
  the normal statistics (r/3) are left as they are: the cut teaches the x-axis weights to live
  with a support that ends early on one side.

  Args:
    patches: host `Patches` (N rows).
    p: probability of cutting each row.
    min_dist: smallest plane distance, as a fraction of r.
    rng: numpy generator (the caller seeds it per epoch, side and cloud).

  Returns:
    `Patches` with the same shapes.
  """
  n = patches.offsets.shape[0]
  cut = rng.random(n) < p
  u = rng.normal(size=(n, 3))
  u /= np.linalg.norm(u, axis=1, keepdims=True)
  c = rng.uniform(min_dist, 1.0, n) * np.asarray(patches.radius, np.float64)
  drop = cut[:, None] & (np.einsum("nkc,nc->nk", patches.offsets, u) > c[:, None])
  drop &= patches.mask
  return patches._replace(offsets=np.where(drop[..., None], 0.0, patches.offsets).astype(np.float32),
                          mask=patches.mask & ~drop,
                          indices=np.where(drop, -1, patches.indices).astype(np.int32))


class BatchMaker:
  """Builds the batch of any (epoch, step) from the seed alone.

  The patches of a whole epoch are built at once, cloud by cloud and side by side (one radius
  search per cloud and side instead of one per batch), and batches gather rows from them.
  Subsample seeds depend on (seed, epoch, side), so both sides of a pair sample their 256 points
  independently and every epoch sees new subsamples. With `config.noise_mr`, each cloud's scene
  side gets, per epoch, Gaussian noise of a level drawn from the list (seeded by (seed, epoch,
  cloud)). With `config.crop_p`, patches are cut by random planes (`crop_patches`), seeded by
  (seed, epoch, side, cloud). With `config.z_view="voted"`, the view of every patch
  (`epoch_views`) is computed with the patches, on the cloud they were searched in (the scene
  side after its noise), as inference computes it from the points alone; the cloud's oriented
  normals are kept for its unperturbed clouds (every model side, the scenes drawn without noise),
  so later epochs only sum them over the new patches.
  """

  def __init__(self, clouds: TrainingClouds, config: TrainConfig):
    self.clouds = clouds
    self.config = config
    self._epoch: int | None = None
    self._patches: tuple[Patches, Patches] | None = None
    self._views: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
    # Per (side, cloud): `points_only_normals` of that unperturbed cloud (z_view="voted").
    self._voted: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    # Per (side, cloud): the seed-independent fields (count, r/3 statistics) of the last patches
    # built on that cloud's unperturbed points, reused by the next epoch's search.
    self._stats: dict[tuple[int, int], Patches] = {}

  def epoch_order(self, epoch: int) -> np.ndarray:
    """(P,) the order in which `epoch` visits the rows of `clouds.keypoints`."""
    rng = np.random.default_rng(_mix(self.config.seed, 2, epoch))
    return rng.permutation(len(self.clouds.keypoints))

  def noise_level(self, epoch: int, cloud: int) -> float:
    """The noise (in mr) added to `cloud`'s scene side during `epoch` (0 without augmentation)."""
    if not self.config.noise_mr:
      return 0.0
    rng = np.random.default_rng(_mix(self.config.seed, 4, epoch, cloud))
    return float(rng.choice(np.asarray(self.config.noise_mr)))

  def side_points(self, epoch: int, side: int, cloud: int) -> tuple[np.ndarray, float]:
    """The (n, 3) points `epoch` searches on `cloud`'s side `side` (0: model, 1: scene; the
    scene with its noise of the epoch) and that noise level in mr (0 for the model side)."""
    pts = self.clouds.models[cloud] if side == 0 else self.clouds.scenes[cloud]
    level = self.noise_level(epoch, cloud) if side == 1 else 0.0
    if level > 0:
      rng = np.random.default_rng(_mix(self.config.seed, 5, epoch, cloud))
      pts = pts + rng.normal(scale=level * self.clouds.mr[cloud], size=pts.shape)
    return pts, level

  def epoch_patches(self, epoch: int) -> tuple[Patches, Patches]:
    """(model, scene) patches of every training keypoint for `epoch`, rows as `keypoints` (and,
    with `config.z_view="voted"`, their views: `epoch_views`)."""
    if self._epoch == epoch:
      assert self._patches is not None  # set with _epoch
      return self._patches
    cfg, kp = self.config, self.clouds.keypoints
    n, k = len(kp), cfg.patch_k
    sides, view_sides = [], []
    for side in (0, 1):
      seed = _mix(cfg.seed, 3, epoch, side)
      # The large fields are written in place by the search where a cloud's rows are one run
      # (the usual layout) and nothing rewrites them; the others are scattered below.
      # Uninitialised: build_patches (or the copy below) writes every row whole.
      big = (np.empty((n, k, 3), np.float32), np.empty((n, k), bool), np.empty((n, k), np.int32))
      parts, rows, views = [], [], []
      for c in np.unique(kp[:, 0]):
        sel = np.flatnonzero(kp[:, 0] == c)
        if sel[-1] - sel[0] + 1 == len(sel):
          sel = slice(sel[0], sel[-1] + 1)
        pts, level = self.side_points(epoch, side, int(c))
        in_place = isinstance(sel, slice) and cfg.crop_p <= 0
        stats = self._stats.get((side, int(c))) if level == 0 else None
        part = build_patches(pts, kp[sel, 1], float(self.clouds.radii[c]), k, seed=seed,
                             into=cast("tuple[np.ndarray, np.ndarray, np.ndarray]",  # big's 3
                                       tuple(a[sel] for a in big)) if in_place else None,
                             stats_from=stats, validate=False)
        if level == 0:
          # Only what `stats_from` reads is kept: the seed-dependent fields are dropped (None).
          self._stats[side, int(c)] = part._replace(
              offsets=None, mask=None, indices=None)  # type: ignore[arg-type]
        if cfg.crop_p > 0:
          crop_rng = np.random.default_rng(_mix(cfg.seed, 6, epoch, side, int(c)))
          part = crop_patches(part, cfg.crop_p, cfg.crop_min, crop_rng)
        if cfg.z_view == "voted":
          views.append(self._view(side, int(c), pts, part, level))
        parts.append((part, in_place))
        rows.append(sel)
      fields = list(big) + [np.empty((n,) + a.shape[1:], a.dtype) for a in parts[0][0][3:]]
      for (part, in_place), sel in zip(parts, rows):
        for i, (out, a) in enumerate(zip(fields, part)):
          if not (in_place and i < 3):
            out[sel] = a
      sides.append(Patches(*fields))
      view_sides.append(_scatter_rows(views, rows, n) if views else None)
    self._epoch, self._patches = epoch, (sides[0], sides[1])
    self._views = (view_sides[0], view_sides[1])
    return self._patches

  def epoch_views(self, epoch: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(model, scene) views of every training keypoint for `epoch`, rows as `keypoints`: (P, 3)
    float32 each with `config.z_view="voted"` (see `Batch`), else (None, None)."""
    self.epoch_patches(epoch)
    return self._views

  def _view(self, side: int, cloud: int, points: np.ndarray, patches: Patches,
            level: float) -> np.ndarray:
    """(N, 3) float32 view of `patches` on `points` (`cloud`'s side `side`, with noise `level`
    in mr): `lrf_net_plus.points_only_view`, the cloud's normals kept when `level` is 0."""
    radius = float(self.clouds.radii[cloud])
    voted = self._voted.get((side, cloud)) if level == 0 else None
    if voted is None:
      voted = points_only_normals(points, radius)
      if level == 0:
        self._voted[side, cloud] = voted
    return points_only_view(points, patches, radius, voted=voted)[0]

  def batch(self, epoch: int, step_in_epoch: int) -> Batch:
    """The host `Batch` (batch_size rows per side) of step `step_in_epoch` of `epoch`."""
    bs = self.config.batch_size
    rows = self.epoch_order(epoch)[step_in_epoch * bs:(step_in_epoch + 1) * bs]
    model, scene = self.epoch_patches(epoch)
    return Batch(*(jax.tree.map(lambda a: a[rows], p) for p in (model, scene, *self._views)))


def _scatter_rows(parts: list[np.ndarray], rows: list[slice | np.ndarray], n: int) -> np.ndarray:
  """(n, ...) array holding `parts[i]` at rows `rows[i]` (every row is covered)."""
  out = np.empty((n,) + parts[0].shape[1:], parts[0].dtype)
  for part, sel in zip(parts, rows):
    out[sel] = part
  return out


def global_batch(batch: Batch, sharding: NamedSharding) -> Batch:
  """`batch` (the same host arrays in every process) as global arrays laid out by `sharding`.

  Each process copies only the rows of its addressable devices, so no host data is exchanged
  between processes; in a single process this places exactly what `jax.device_put` would.
  Absent views (None) stay None.
  """
  return jax.tree.map(
      lambda a: jax.make_array_from_callback(a.shape, sharding, lambda index: a[index]), batch)
