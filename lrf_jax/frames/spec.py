"""What an LRF method declares (`MethodSpec`), the registry `METHODS`, and `add_method`.

A method is a pure, jittable `fn(patches, extra, **options) -> (frames (N, 3, 3), valid (N,))`
plus what it needs: a patch size, the radius of its normal support, learned parameters, a mesh,
and optionally a host-side `prepare` hook (numpy, outside jit) that gathers per-keypoint arrays
`extra` for it. `extra` is a NamedTuple whose class attribute `AXES` says, for each field, how
its axes are indexed, so that generic code and tests can permute, pad or slice it:

* `KEYPOINT`: (N, ...) one row per keypoint;
* `SLOT`: (N, K, ...) indexed like the patch slots (`Patches.indices`);
* `TRIANGLE`: (N, T, ...) indexed by triangle slot; `TRIANGLE_MASK`: the (N, T) bool mask of
  those slots (False in padding).
"""

from __future__ import annotations

import dataclasses
from typing import Any
from collections.abc import Callable

from lrf_jax.defaults import DEFAULT_METHOD, RADIUS_MR  # noqa: F401 -- also the frames' names

KEYPOINT = "keypoint"
SLOT = "slot"
TRIANGLE = "triangle"
TRIANGLE_MASK = "triangle_mask"
AXIS_KINDS = (KEYPOINT, SLOT, TRIANGLE, TRIANGLE_MASK)


@dataclasses.dataclass(frozen=True)
class HostPatchKernel:
  """A method's frames from prepared patches on the host (numba, float64), for the option sets
  it supports: `MethodSpec.host_patch_frames`, the hook of methods on subsampled patches or with
  options (a method on every neighbor without options uses `MethodSpec.host_frames`).

  Attributes:
    fn: `fn(patches, extra, params, options) -> (frames (N, 3, 3) float32, valid (N,) bool)`;
      `params` is the weight table (`lrf_net.WeightTable`) where the options read one, and
      `options` holds every option (the method's defaults filled in).
    supports: `supports(options) -> bool`: whether `fn` computes what `MethodSpec.fn` would
      for these options.
  """

  fn: Callable[..., Any]
  supports: Callable[[dict], bool]

  def __call__(self, patches: Any, extra: Any, params: Any, options: dict) -> Any:
    return self.fn(patches, extra, params, options)


@dataclasses.dataclass(frozen=True)
class MethodSpec:
  """How to compute one LRF method.

  Attributes:
    name: registry key.
    fn: `fn(patches, extra, **options) -> (frames, valid)`, pure and jittable; `extra` is what
      `prepare` returned (None when there is no `prepare`). For learned methods `options` holds
      `params`. Its keyword-only arguments are the method's options.
    default_k: patch size K used when the caller gives none; None = every neighbor in the ball.
    z_ratio: radius of the z support as a fraction of r (stored in `Patches.z_*`).
    needs_params: the method takes learned parameters.
    needs_mesh: the method needs triangle faces (`faces=` in `compute_frames`).
    needs_normals: `prepare` reads per-point normals (the caller's, else estimated; see
      `lrf_jax.frames.normals_rule.method_normals`).
    prepare: optional host-side hook `prepare(points, keypoints, patches, faces=..., normals=...,
      radius=...)` returning an instance of `extra` (per-keypoint arrays) fed to `fn`.
    extra: the NamedTuple type `prepare` returns, with its `AXES` layout (None: no extra).
    uses_viewpoint: `prepare` also takes `viewpoint=` (the sensor position of a single-view scan,
      or None) and handles it itself (methods without it get viewpoint-oriented normals instead).
    description: one line for `lrf_jax.METHODS` listings.
    weights: name of the shipped parameter file used when no params are given
      (`lrf_jax/weights/<weights>.msgpack`).
    default_options: options applied unless the caller gives them (e.g. lut=257).
    host_frames: optional host fast path for a method on every neighbor (`default_k=None`):
      `host_frames(points (n, 3) float64, keypoints (N,) int, radius, index, *, faces=,
      normals=) -> (frames (N, 3, 3) float32, valid (N,) bool)`, numpy and compiled engine code
      (`frames.host_geometry`) computing the same frames as `fn` from the cloud's ball lists
      (`index` is its `SearchIndex`), without padded patches; `faces` the mesh or None, `normals`
      (n, 3) as `normals_rule.method_normals` gives them (None for a method without). The
      built-in methods' are `host_path.BallKernel`s: a numba kernel and the names of the inputs
      it reads, which `BallKernel` builds alike for every method. `compute_frames` runs it by
      default on a CPU backend (`kernel="auto"`) for calls with k=None and no options.
    host_patch_frames: optional `HostPatchKernel` for a method on subsampled patches (an
      integer `default_k`) or with options: computes the same frames as `fn` from the same
      (padded, subsampled) patches and `extra` on the host; `compute_frames` runs it by default
      on a CPU backend where `supports` accepts the options (`kernel="auto"`). The two hooks
      take different inputs on purpose: `host_frames` never builds patches (its speed), and
      `host_patch_frames` must see the very patches `fn` sees (the same seeded subsample); where
      both are set and apply, `host_frames` runs. Either must equal `fn`: the same validity,
      the same axes to float32 rounding, checked for every registered method by
      tests/test_method_properties.py::test_host_fast_path_equals_the_jitted_function.
    confidence: optional `confidence(patches, extra, frames, valid, options) -> (N,)` in
      [0, 1]: how sure each frame's z sign is (`compute_frames(..., return_confidence=True)`);
      `options` holds every option (the method's defaults filled in).
    shells: (a, b) fractions of r when the method reads only the neighbors within a * r or
      beyond b * r: with every neighbor (k=None), `compute_frames` then gathers only those
      (`build_patches(shells=)`), which gives the same frames from smaller patches. None: the
      method reads the whole ball.
  """

  name: str
  fn: Callable[..., Any]
  default_k: int | None = 256
  z_ratio: float = 1.0 / 3.0
  needs_params: bool = False
  needs_mesh: bool = False
  needs_normals: bool = False
  prepare: Callable[..., Any] | None = None
  extra: type | None = None
  uses_viewpoint: bool = False
  description: str = ""
  weights: str = "lrf_net"
  default_options: tuple[tuple[str, Any], ...] = ()
  shells: tuple[float, float] | None = None
  host_frames: Callable[..., Any] | None = None
  host_patch_frames: HostPatchKernel | None = None
  confidence: Callable[..., Any] | None = None

  def __post_init__(self):
    if self.needs_normals and (self.prepare is None or self.uses_viewpoint):
      raise ValueError(f"MethodSpec {self.name!r}: needs_normals is for a prepare hook that is "
                       "not viewpoint-aware")
    if (self.prepare is None) != (self.extra is None):
      raise ValueError(f"MethodSpec {self.name!r}: prepare and extra go together (the hook "
                       "returns an instance of the extra NamedTuple)")
    if self.extra is not None:
      axes = getattr(self.extra, "AXES", None)
      fields = getattr(self.extra, "_fields", None)
      if fields is None or not isinstance(axes, dict) or set(axes) != set(fields) or any(
          kind not in AXIS_KINDS for kind in axes.values()):
        raise ValueError(f"MethodSpec {self.name!r}: extra must be a NamedTuple with an AXES "
                         f"dict giving each field one of {AXIS_KINDS}")


# Longest description shown in a `METHODS` listing (the whole one: `METHODS[name].description`).
DESCRIPTION_WIDTH = 100


def _one_line(text: str, width: int = DESCRIPTION_WIDTH) -> str:
  """`text` on one line, cut at a word boundary to at most `width` characters ("..." added)."""
  text = " ".join(text.split())
  if len(text) <= width:
    return text
  return text[:width - 3].rsplit(" ", 1)[0].rstrip(",;:") + "..."


class MethodRegistry(dict):
  """`METHODS`: a dict name -> `MethodSpec` that prints as a table, one method per line: what
  it needs and what it is (its description, shortened), the default marked with `*`."""

  def table(self) -> str:
    """One line per method: name (`*` before the default), kind, needs, default K, weights
    and description (cut to `DESCRIPTION_WIDTH` characters), in aligned columns; a header
    line first and a footer line naming the default last."""
    rows = [("", "name", "kind", "needs", "default K", "weights", "description")]
    for name, spec in self.items():
      needs = [w for w, on in (("mesh", spec.needs_mesh), ("params", spec.needs_params),
                               ("normals", spec.prepare is not None and not spec.needs_mesh
                                and not spec.needs_params)) if on]
      rows.append(("*" if name == DEFAULT_METHOD else "", name,
                   "learned" if spec.needs_params else "hand-crafted",
                   ", ".join(needs) or "-", "all" if spec.default_k is None else
                   str(spec.default_k), spec.weights if spec.needs_params else "-",
                   _one_line(spec.description) or "-"))
    width = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, width)).rstrip() for r in rows]
    return "\n".join(lines + [f"* the default ({DEFAULT_METHOD}: compute_frames, register, "
                               "lrf-frames, lrf-register); full text: "
                               "METHODS[name].description"])

  def describe(self, name: str) -> str:
    """"NAME: DESCRIPTION" of method `name` (its whole description; "(the default)" after the
    default's name).

    Raises:
      KeyError: no such method (the message lists the registered ones).
    """
    if name not in self:
      raise KeyError(f"unknown method {name!r}; expected one of {sorted(self)}")
    return (f"{name}{' (the default)' if name == DEFAULT_METHOD else ''}: "
            f"{self[name].description}")

  def __repr__(self) -> str:
    return self.table()

  __str__ = __repr__


METHODS: MethodRegistry = MethodRegistry()


def method_spec(method: Any) -> MethodSpec:
  """The registered `MethodSpec` of `method` (the one check of a method name).

  Raises:
    ValueError: `method` is not a key of `METHODS` (the message lists them).
  """
  if not isinstance(method, str) or method not in METHODS:
    raise ValueError(f"method: unknown LRF method {method!r}; expected one of {sorted(METHODS)}")
  return METHODS[method]


def add_method(spec: MethodSpec) -> MethodSpec:
  """Add a method to `METHODS` under `spec.name` (replacing one of that name) and return it.

  `lrf_jax.compute_frames(..., method=spec.name)` then runs it: the search with `spec.default_k`
  and `spec.z_ratio`, the `prepare` hook, and `spec.fn` jitted per option set. (Named so that
  `lrf_jax.register` means one thing: aligning scans.)
  """
  if not isinstance(spec, MethodSpec):
    raise TypeError(f"add_method: expected a MethodSpec, got {type(spec).__name__}")
  METHODS[spec.name] = spec
  return spec

