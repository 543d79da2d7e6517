"""LRF methods behind one registry: `METHODS[name]` describes how to compute and what is needed.

Every method is a pure function of a `Patches` batch (plus, for some, extra per-keypoint arrays
gathered on the host by the method's `prepare` hook: neighbour normals, mesh triangles, ...) that
returns `(frames (N, 3, 3), valid (N,))` with rows x, y, z, det +1, identity where invalid.
`lrf_jax.compute_frames` is the one public entry that does the search, the preparation and the
jitted, chunked evaluation for any of them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from lrf_jax.frames.lrf_net import lrf_net_frames, prepare_view, uniform_frames
from lrf_jax.frames.toldi import toldi_frames


@dataclasses.dataclass(frozen=True)
class MethodSpec:
  """How to compute one LRF method.

  Attributes:
    name: registry key.
    fn: `fn(patches, extra, **options) -> (frames, valid)`, pure and jittable; `extra` is what
      `prepare` returned (None when there is no `prepare`). For learned methods `options` holds
      `params`.
    default_k: patch size K used when the caller gives none; None = every neighbour in the ball.
    z_ratio: radius of the normal support as a fraction of r (stored in `Patches.z_*`).
    needs_params: the method takes learned parameters.
    needs_mesh: the method needs triangle faces (`faces=` in `compute_frames`).
    prepare: optional host-side hook `prepare(points, keypoints, patches, faces=..., normals=...,
      radius=...)` returning a pytree of per-keypoint arrays (leading axis N) fed to `fn` as
      `extra`.
    uses_viewpoint: `prepare` also takes `viewpoint=` (the sensor position of a single-view scan,
      or None) and handles it itself (methods without it get viewpoint-oriented normals instead).
    description: one line for `lrf_jax.METHODS` listings.
    weights: name of the shipped parameter file used when no params are given
      (`lrf_jax/weights/<weights>.msgpack`).
    default_options: options applied unless the caller gives them (lrf_net_plus: lut=257).
    shells: (a, b) fractions of r when the method reads only the neighbours within a * r or
      beyond b * r (FLARE: its r/3 plane support and its 0.85 r margin): with every neighbour
      (k=None), `compute_frames` then gathers only those (`build_patches(shells=)`), which gives
      the same frames from smaller patches. None: the method reads the whole ball.
  """

  name: str
  fn: Callable[..., Any]
  default_k: int | None = 256
  z_ratio: float = 1.0 / 3.0
  needs_params: bool = False
  needs_mesh: bool = False
  prepare: Callable[..., Any] | None = None
  uses_viewpoint: bool = False
  description: str = ""
  weights: str = "lrf_net"
  default_options: tuple[tuple[str, Any], ...] = ()
  shells: tuple[float, float] | None = None


def _lrf_net(patches, extra, *, params, x_mode: str = "sum", lut: int = 0):
  del extra
  return lrf_net_frames(params, patches, x_mode=x_mode, lut=lut)


def _uniform(patches, extra, *, z_sign: str = "toldi"):
  del extra
  return uniform_frames(patches, z_sign=z_sign)


def _lrf_net_plus(patches, extra, *, params, x_mode: str = "softmax", lut: int = 0,
                  density: bool = True, oriented_sign: bool = True):
  return lrf_net_frames(params, patches, x_mode=x_mode, z_sign="ball", lut=lut,
                        view=None if extra is None or not oriented_sign else extra["view"],
                        area=None if extra is None or not density else extra["area"])


def _toldi(patches, extra, *, signed: bool = True):
  del extra
  return toldi_frames(patches, signed=signed)


class MethodRegistry(dict):
  """`METHODS`: a dict name -> `MethodSpec` that prints as a table, one method per line."""

  def table(self) -> str:
    """name, kind, needs, default K and weights of every method, aligned columns."""
    rows = [("name", "kind", "needs", "default K", "weights")]
    for name, spec in self.items():
      needs = [w for w, on in (("mesh", spec.needs_mesh), ("params", spec.needs_params),
                               ("normals", spec.prepare is not None and not spec.needs_mesh
                                and not spec.needs_params)) if on]
      rows.append((name, "learned" if spec.needs_params else "hand-crafted",
                   ", ".join(needs) or "-", "all" if spec.default_k is None else
                   str(spec.default_k), spec.weights if spec.needs_params else "-"))
    width = [max(len(r[i]) for r in rows) for i in range(5)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, width)).rstrip() for r in rows)

  def __repr__(self) -> str:
    return self.table()

  __str__ = __repr__


METHODS: MethodRegistry = MethodRegistry()


def register(spec: MethodSpec) -> MethodSpec:
  """Add a method to `METHODS` (also for users' own methods)."""
  METHODS[spec.name] = spec
  return spec


register(MethodSpec(
    "lrf_net", _lrf_net, default_k=256, needs_params=True, default_options=(("lut", 257),),
    description="LRF-Net (Zhu et al.): TOLDI z over r/3, learned per-point weights for x, read "
                "from a 257 x 257 table by default (lut=257; lut=0: the exact network)"))
def _variant(patches, extra, *, params, z_mode: str = "normal", x_mode: str = "sum1"):
  del extra
  from lrf_jax.frames.ablation import variant_frames
  if not any(k in params for k in ("weights", "x_reg", "z_reg")):
    params = {"weights": params}  # plain LRF-Net parameters
  return variant_frames(params, patches, z_mode=z_mode, x_mode=x_mode)


register(MethodSpec(
    "lrf_net_variant", _variant, default_k=256, needs_params=True,
    description="LRF-Net ablation variants (options z_mode: normal/dr, x_mode: sum1/sum2/dr/max)"))
register(MethodSpec(
    "lrf_net_plus", _lrf_net_plus, default_k=512, needs_params=True, weights="lrf_net_plus",
    prepare=prepare_view, uses_viewpoint=True, default_options=(("lut", 257),),
    description="Beyond the paper: LRF-Net with the z sign towards the sensor of a scan "
                "(viewpoint=), else from the mesh's oriented normals, else over the whole "
                "support (ball_sign); the network's outputs read as log-weights "
                "(x_mode='softmax': x can follow a few rim points, as FLARE's does), trained "
                "with noise augmentation (configs/plus_soft.py); weights times the area each "
                "point stands for (density=True: sampling-invariant x); K = 512 (less "
                "subsampling noise); the network read from a 257 x 257 table (lut=257, "
                "lut=0: exact). Every choice was made on the bunny validation scans"))
register(MethodSpec(
    "uniform", _uniform, default_k=256,
    description="LRF-Net's construction with uniform weights (w = 1): the learned weights' baseline"))
register(MethodSpec(
    "toldi", _toldi, default_k=None,
    description="TOLDI (Yang et al. 2017): z over r/3, x weights (r-d)^2 sign(h) h^2 (original C++)"))

__all__ = ["METHODS", "MethodRegistry", "MethodSpec", "register", "lrf_net_frames", "toldi_frames", "uniform_frames"]

# ------------------------------------------------------------------------------------------------
# Hand-crafted LRFs (PCL-equivalent where PCL has them). Imported here, after `register`, so that
# each method module stays a plain library of pure functions.
# ------------------------------------------------------------------------------------------------
from lrf_jax.frames import board as _board_mod  # noqa: E402
from lrf_jax.frames import flare as _flare_mod  # noqa: E402
from lrf_jax.frames.board import board_frames  # noqa: E402
from lrf_jax.frames.flare import flare_frames  # noqa: E402
from lrf_jax.frames.gframes import gframes_frames, prepare_gframes  # noqa: E402
from lrf_jax.frames.mian import mian_frames  # noqa: E402
from lrf_jax.frames.ps import ps_frames  # noqa: E402
from lrf_jax.frames.rops import prepare_triangles, rops_frames  # noqa: E402
from lrf_jax.frames.shot import shot_frames  # noqa: E402
from lrf_jax.normals import prepare_normals  # noqa: E402


def _mian(patches, extra, *, center: str = "centroid"):
  return mian_frames(patches, extra["kp_normal"], center=center)


def _shot(patches, extra):
  del extra
  return shot_frames(patches)


def _rops(patches, extra):
  return rops_frames(patches, extra["tri"], extra["tri_mask"])


def _board(patches, extra):
  return board_frames(patches, extra["normals"])


def _flare(patches, extra):
  return flare_frames(patches, extra["normals"], extra["kp_normal"])


def _ps(patches, extra):
  return ps_frames(patches, extra["kp_normal"])


def _gframes(patches, extra):
  return gframes_frames(patches, extra["tri"], extra["tri_mask"], extra["tri_f"],
                        extra["kp_normal"])


register(MethodSpec(
    "mian", _mian, default_k=None, prepare=prepare_normals,
    description="Mian et al. 2010: covariance eigenvectors, z signed by the normal (x/y sign "
                "ambiguous)"))
register(MethodSpec(
    "shot", _shot, default_k=None,
    description="SHOT (Tombari et al. 2010): (r-d)-weighted covariance about p, majority-vote "
                "signs (PCL)"))
register(MethodSpec(
    "rops", _rops, default_k=None, needs_mesh=True, prepare=prepare_triangles,
    description="RoPS (Guo et al. 2013): area- and distance-weighted triangle scatter (PCL); "
                "needs a mesh"))
register(MethodSpec(
    "board", _board, default_k=None, z_ratio=_board_mod.Z_RATIO, prepare=prepare_normals,
    description="BOARD (Petrelli & Di Stefano 2011): plane-fit z over r/3, x to the most "
                "inclined margin normal (PCL)"))
register(MethodSpec(
    "flare", _flare, default_k=None, z_ratio=_flare_mod.Z_RATIO, prepare=prepare_normals,
    shells=(_flare_mod.Z_RATIO, _flare_mod.MARGIN),
    description="FLARE / SD (Petrelli & Di Stefano 2012): plane-fit z over r/3, x to the "
                "highest margin point (PCL)"))
register(MethodSpec(
    "ps", _ps, default_k=None, prepare=prepare_normals,
    description="Point signature (Chua & Jarvis 1997): contour-plane z, x to the highest "
                "contour point"))
register(MethodSpec(
    "gframes", _gframes, default_k=None, needs_mesh=True, prepare=prepare_gframes,
    description="GFrames (Melzi et al. 2019): normal z, x = area-weighted mean-curvature "
                "gradient; needs a mesh"))

__all__ += ["board_frames", "flare_frames", "gframes_frames", "mian_frames", "ps_frames",
            "rops_frames", "shot_frames"]
