"""Properties every registered LRF method must have, parameterised over `lrf_jax.METHODS`.

On a synthetic mesh (an irregular height field plus two degenerate far-away parts): orthonormal
rows and det +1; interior keypoints valid, a one-neighbor and a collinear support invalid with
an identity frame; frames that depend on the input; invariance to the order of the patch slots
(and triangle slots) and to extra padding holding garbage; NaN input flagged invalid without
touching the other keypoints; and every method honouring the declared `extra` layout. Every
method with a host kernel (`host_frames` or `host_patch_frames`) must give its jitted function's
frames on procedural clouds: smooth, noisy, planar, cut off, with degenerate keypoints
(`lrf_testing.host_check_cloud`). A new method registered in `lrf_jax/frames/__init__.py` is
tested here without edits; the guide's (docs/frames.md) "adding an LRF method" example, host kernel included,
is run as written and put through the same checks.
"""

from __future__ import annotations

import re
from pathlib import Path

import jax
import numpy as np
import pytest

import lrf_jax
from lrf_jax.geometry import normals as nm
from lrf_jax.frames.patch_frames import frames_from_patches
from lrf_jax.frames import KEYPOINT, SLOT, TRIANGLE, TRIANGLE_MASK
from lrf_jax.search.neighborhoods import build_patches
from lrf_jax.frames.normals_rule import prepare_extra
from tests.lrf_testing import (HOST_CHECK_KINDS, N_GOOD, assert_frames_orthonormal,
                               host_check_cloud, synthetic_mesh)

SYN = synthetic_mesh()
GUIDE = Path(__file__).resolve().parents[1] / "docs" / "frames.md"


def _inputs(method, k="default"):
  """Patches and `extra` of the synthetic keypoints through the library's own prepare rule."""
  spec = lrf_jax.METHODS[method]
  points, faces, keypoints, radius = SYN
  k = spec.default_k if k == "default" else k
  patches = build_patches(points, keypoints, radius, k, z_ratio=spec.z_ratio)
  extra = prepare_extra(spec, points, keypoints, patches, radius=radius, faces=faces)
  return patches, extra


def _run(method, patches, extra):
  f, v = frames_from_patches(patches, method, extra=extra)
  return np.asarray(f), np.asarray(v)


def _case(method):
  patches, extra = _inputs(method)
  frames, valid = _run(method, patches, extra)
  return patches, extra, frames, valid


def _take(a, perm):
  return np.take_along_axis(np.asarray(a), perm.reshape(perm.shape + (1,) * (a.ndim - 2)), 1)


def _permute(patches, extra, seed):
  """Shuffle each keypoint's patch slots, and its triangle slots, as `extra.AXES` declares."""
  rng = np.random.default_rng(seed)
  n, k = patches.mask.shape
  perm = np.stack([rng.permutation(k) for _ in range(n)])
  patches = patches._replace(offsets=_take(patches.offsets, perm),
                             mask=_take(patches.mask, perm), indices=_take(patches.indices, perm))
  if extra is None:
    return patches, None
  fields, tperm = {}, None
  for name, kind in type(extra).AXES.items():
    a = getattr(extra, name)
    if a is None or kind == KEYPOINT:
      continue
    if kind == SLOT:
      fields[name] = _take(a, perm)
    else:
      if tperm is None:
        tperm = np.stack([rng.permutation(a.shape[1]) for _ in range(n)])
      fields[name] = _take(a, tperm)
  return patches, extra._replace(**fields)


def _pad(patches, extra, more=32, seed=0):
  """Append `more` masked slots (and triangle slots) holding finite garbage."""
  rng = np.random.default_rng(seed)
  n = patches.mask.shape[0]
  junk = lambda *shape: rng.normal(scale=50.0, size=shape).astype(np.float32)
  patches = patches._replace(
      offsets=np.concatenate([patches.offsets, junk(n, more, 3)], 1),
      mask=np.concatenate([patches.mask, np.zeros((n, more), bool)], 1),
      indices=np.concatenate([patches.indices, np.full((n, more), -1, np.int32)], 1))
  if extra is None:
    return patches, None
  fields = {}
  for name, kind in type(extra).AXES.items():
    a = getattr(extra, name)
    if a is None or kind == KEYPOINT:
      continue
    a = np.asarray(a)
    tail = (np.zeros((n, more), bool) if kind == TRIANGLE_MASK
            else junk(n, more, *a.shape[2:]).astype(a.dtype))
    fields[name] = np.concatenate([a, tail], 1)
  return patches, extra._replace(**fields)


def check_conventions(method):
  _, _, frames, valid = _case(method)
  assert_frames_orthonormal(frames, valid)
  assert valid[:N_GOOD].all(), f"{method}: interior keypoints invalid: {valid[:N_GOOD]}"
  assert not valid[N_GOOD], f"{method}: a 2-point neighborhood must be invalid"
  assert not valid[N_GOOD + 1], f"{method}: a collinear support must be invalid"
  np.testing.assert_array_equal(frames[~valid], np.broadcast_to(np.eye(3), frames[~valid].shape))
  cos = np.einsum("ni,mi->nm", frames[:N_GOOD, 0], frames[:N_GOOD, 0])
  assert (cos < 0.999).sum() > 0, f"{method}: the same x for every keypoint"


def check_slot_order_and_padding(method):
  patches, extra, frames, valid = _case(method)
  for p2, e2 in (_permute(patches, extra, seed=1), _pad(patches, extra)):
    f2, v2 = _run(method, p2, e2)
    np.testing.assert_array_equal(v2, valid)
    np.testing.assert_allclose(f2, frames, atol=2e-5)


def check_nan_input(method):
  patches, extra, frames, valid = _case(method)
  bad = 3
  axes = {} if extra is None else type(extra).AXES
  tri = next((name for name, kind in axes.items() if kind == TRIANGLE), None)
  if tri is not None:  # triangle methods read triangles, not offsets
    mask = next(name for name, kind in axes.items() if kind == TRIANGLE_MASK)
    t = np.array(getattr(extra, tri))
    t[bad, int(np.argmax(getattr(extra, mask)[bad])), 1, 2] = np.nan
    extra = extra._replace(**{tri: t})
  else:
    offsets = np.array(patches.offsets)
    offsets[bad, int(np.argmax(patches.mask[bad])), 0] = np.nan
    patches = patches._replace(offsets=offsets)
  f2, v2 = _run(method, patches, extra)
  assert not v2[bad]
  np.testing.assert_array_equal(f2[bad], np.eye(3))
  keep = np.arange(len(v2)) != bad
  np.testing.assert_array_equal(v2[keep], valid[keep])
  np.testing.assert_allclose(f2[keep], frames[keep], atol=1e-6)


def check_extra_layout(method):
  spec = lrf_jax.METHODS[method]
  patches, extra = _inputs(method)
  if spec.prepare is None:
    assert extra is None
    return
  assert isinstance(extra, spec.extra)
  n, k = patches.mask.shape
  for name, kind in spec.extra.AXES.items():
    a = getattr(extra, name)
    if a is None:
      continue
    assert a.shape[0] == n, (method, name, a.shape)
    if kind == SLOT:
      assert a.shape[1] == k, (method, name, a.shape)


CHECKS = (check_conventions, check_slot_order_and_padding, check_nan_input, check_extra_layout)


@pytest.mark.parametrize("check", CHECKS, ids=lambda c: c.__name__[6:])
@pytest.mark.parametrize("method", list(lrf_jax.METHODS))
def test_method_property(method, check):
  check(method)


def _readme_example() -> str:
  """The guide's "adding an LRF method" example (docs/frames.md, linked from the README)."""
  text = GUIDE.read_text()
  section = text[text.index("## The registry: adding an LRF method"):]
  return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_adding_a_method_as_the_readme_says():
  """The guide's toy method, registered inside this test only, passes every property check,
  runs through `compute_frames`, is equivariant on the synthetic mesh, and its host kernel
  passes the host check (`test_host_fast_path_equals_the_jitted_function`) on every cloud."""
  assert "centroid" not in lrf_jax.METHODS
  try:
    exec(compile(_readme_example(), str(GUIDE), "exec"), {})
    assert "centroid" in lrf_jax.METHODS
    for check in CHECKS:
      check("centroid")
    points, _, keypoints, radius = SYN
    rot = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))
    f0, v0 = map(np.asarray, lrf_jax.compute_frames(points, keypoints, radius, "centroid"))
    f1, v1 = map(np.asarray, lrf_jax.compute_frames(points @ rot.T + 3.0, keypoints, radius,
                                                    "centroid"))
    np.testing.assert_array_equal(v0, v1)
    np.testing.assert_allclose(f1[v0], f0[v0] @ rot.T, atol=1e-4)
    assert has_host_kernel(lrf_jax.METHODS["centroid"])  # its host kernel equals its definition
    for kind in HOST_CHECK_KINDS:
      check_host_equals_jit("centroid", kind)
  finally:
    lrf_jax.METHODS.pop("centroid", None)
  assert "centroid" not in lrf_jax.METHODS


def test_method_spec_rejects_an_undeclared_extra():
  from typing import NamedTuple

  from lrf_jax.frames import MethodSpec

  class NoAxes(NamedTuple):
    a: np.ndarray

  hook = lambda *args, **kw: None
  with pytest.raises(ValueError, match="AXES"):
    MethodSpec("bad", lambda p, e: None, prepare=hook, extra=NoAxes)
  with pytest.raises(ValueError, match="go together"):
    MethodSpec("bad", lambda p, e: None, prepare=hook)


def test_normal_methods_get_the_same_normals_on_every_path():
  """compute_frames and the evaluation's thunk of estimated normals feed one rule."""
  from lrf_jax.frames.normals_rule import method_normals
  points, faces, _, radius = SYN
  est = nm.estimate_normals(points, nm.NORMAL_RADIUS_RATIO * radius, faces)
  for name in ("board", "gframes", "lrf_net_plus"):
    spec = lrf_jax.METHODS[name]
    a = method_normals(spec, points, radius, faces=faces)
    b = method_normals(spec, points, radius, faces=faces, normals=lambda: est)
    np.testing.assert_array_equal(a, b)
  plus = lrf_jax.METHODS["lrf_net_plus"]
  assert method_normals(plus, points, radius) is None  # a cloud: prepare_view orients it
  assert method_normals(plus, points, radius, faces=faces, viewpoint=np.zeros(3)) is None
  assert method_normals(lrf_jax.METHODS["rops"], points, radius, faces=faces) is None


def has_host_kernel(spec) -> bool:
  """Whether a method has a host path (`host_frames` or `host_patch_frames`)."""
  return spec.host_frames is not None or spec.host_patch_frames is not None


HOST_METHODS = [m for m, s in lrf_jax.METHODS.items() if has_host_kernel(s)]
# Methods whose frame on an exact tilted plane is set by float rounding (`host_check_cloud`): a
# sign vote over heights Σ (q_i - p)·z of about 0, or an x from the highest point or from
# heights h_i of about 0; their host and jitted frames differ there (both valid).
ROUNDING_ON_A_TILTED_PLANE = {"toldi", "shot", "rops", "board", "flare", "ps", "lrf_net",
                              "uniform", "centroid"}


def _both_kernels(method, points, keypoints, radius, faces):
  out = []
  for kernel in ("host", "jit"):
    f, v = lrf_jax.compute_frames(points, keypoints, radius, method, faces=faces, kernel=kernel)
    out.append((np.asarray(f), np.asarray(v)))
  return out


def _agreement(method, host, jit):
  (fh, _), (fj, _) = host, jit
  cx = np.sum(fh[:, 0] * fj[:, 0], -1)
  if method == "mian":  # x is sign-ambiguous by construction
    cx = np.abs(cx)
  return 0.5 * (cx + np.sum(fh[:, 2] * fj[:, 2], -1))


def check_host_equals_jit(method, kind):
  """`kernel="host"` (compiled float64 code: `host_frames` on every neighbor, or
  `host_patch_frames` on the same patches) gives the jitted function's validity, and its frames
  to float32 rounding (mean cosine of x and z > 1 - 1e-5), on `host_check_cloud(kind)`: the two
  degenerate keypoints invalid, the smooth field's keypoints valid. On an exact tilted plane a
  method of `ROUNDING_ON_A_TILTED_PLANE` takes its z sign and its x from float rounding: there
  the two paths agree on validity and on the z axis (the plane's normal) up to its sign."""
  points, faces, keypoints, radius = host_check_cloud(kind)
  host, jit = _both_kernels(method, points, keypoints, radius, faces)
  assert_frames_orthonormal(*host)
  np.testing.assert_array_equal(host[1], jit[1], err_msg=f"{method} on {kind}: validity")
  assert not host[1][-2:].any(), f"{method} on {kind}: a degenerate keypoint is valid"
  assert kind != "smooth" or host[1][:-2].all(), f"{method}: smooth keypoints invalid"
  if kind == "tilted_plane" and method in ROUNDING_ON_A_TILTED_PLANE:
    cz = np.abs(np.sum(host[0][:, 2] * jit[0][:, 2], -1))[host[1]]
    assert cz.size == 0 or cz.min() > 1 - 1e-5, (method, kind, cz.min())
    return
  mc = _agreement(method, host, jit)[host[1]]
  assert mc.size == 0 or mc.min() > 1 - 1e-5, (method, kind, mc.min())


def _host_check_params():
  for method in HOST_METHODS:
    for kind in HOST_CHECK_KINDS:
      yield pytest.param(method, kind, id=f"{method}-{kind}")


@pytest.mark.parametrize("method,kind", list(_host_check_params()))
def test_host_fast_path_equals_the_jitted_function(method, kind):
  """Every method with a host kernel, on smooth, noisy, planar, cut-off and degenerate input."""
  check_host_equals_jit(method, kind)


@pytest.mark.parametrize("method", HOST_METHODS)
def test_host_fast_path_equals_the_jitted_function_on_the_bunny(method, br_bunny):
  points, faces, mr, _ = br_bunny
  keypoints = np.random.default_rng(4).choice(len(points), 400, replace=False)
  host, jit = _both_kernels(method, points, keypoints, 15.0 * mr, faces)
  assert (host[1] == jit[1]).mean() >= 0.995
  both = host[1] & jit[1]
  mc = _agreement(method, host, jit)[both]
  assert (mc > 0.9999).mean() >= 0.99 and both.mean() > 0.9, (method, np.sort(mc)[:5])


def test_kernel_argument_is_checked():
  points, _, keypoints, radius = SYN
  with pytest.raises(ValueError, match="kernel"):
    lrf_jax.compute_frames(points, keypoints, radius, "shot", kernel="gpu")
  with pytest.raises(ValueError, match="no host fast path"):
    lrf_jax.compute_frames(points, keypoints, radius, "lrf_net_variant", kernel="host")
  with pytest.raises(ValueError, match="no host fast path"):
    lrf_jax.compute_frames(points, keypoints, radius, "shot", k=64, kernel="host")


def test_host_fast_path_splits_by_a_neighbor_budget(monkeypatch):
  """Keypoints are grouped so that their balls' lists stay within a budget: the same frames."""
  from lrf_jax.frames import host_path
  points, faces, keypoints, radius = SYN
  full = lrf_jax.compute_frames(points, keypoints, radius, "shot", kernel="host")
  monkeypatch.setattr(host_path, "HOST_NEIGHBOR_BUDGET", 50)  # a few keypoints per group
  split = lrf_jax.compute_frames(points, keypoints, radius, "shot", kernel="host")
  np.testing.assert_array_equal(np.asarray(full[0]), np.asarray(split[0]))
  np.testing.assert_array_equal(np.asarray(full[1]), np.asarray(split[1]))


@pytest.mark.parametrize("method", ["shot", "gframes", "lrf_net_plus"])
def test_host_paths_return_frames_in_the_callers_order(method):
  """The host paths visit keypoints in grid-cell order and pad no chunk: shuffled keypoints in
  chunks that do not divide them give the same frames, row for row, as one call in order."""
  points, faces, keypoints, radius = SYN
  kp = np.concatenate([keypoints, keypoints[::-1]])  # repeats, and more than one chunk below
  perm = np.random.default_rng(5).permutation(len(kp))
  kw = dict(faces=faces) if lrf_jax.METHODS[method].needs_mesh else {}
  kw["kernel"] = "host"  # the default on a CPU; on an accelerator the default is jitted
  f0, v0 = lrf_jax.compute_frames(points, kp, radius, method, **kw)
  f1, v1 = lrf_jax.compute_frames(points, kp[perm], radius, method, chunk_size=7, **kw)
  assert f1.shape == (len(kp), 3, 3) and v1.shape == (len(kp),)
  assert all(isinstance(a, jax.Array) for a in (f0, v0, f1, v1))  # one chunk or several
  np.testing.assert_array_equal(np.asarray(f1), np.asarray(f0)[perm])
  np.testing.assert_array_equal(np.asarray(v1), np.asarray(v0)[perm])
