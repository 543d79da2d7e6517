"""`compute_frames`' numerics (`lrf_jax.frames.compute`): scale, zero normals, out-of-range
magnitudes.

* Scale: every method is invariant to a common scale of cloud and radius, so a sweep of the
  factor s over 1e-30 .. 1e30 must give the unscaled frames (max abs difference of the entries
  <= `AGREE`) with the same validity, on the host default path and on `kernel="jit"`.
* Zero normals (the placeholder of PLY files without normals) carry no direction: every method
  that reads normals (`needs_normals`) returns all its frames invalid, on both paths.
* A radius or cloud outside the supported scale raises a ValueError naming the scale, never a
  numba SystemError.

The cloud is `lrf_testing.synthetic_mesh` in units of its support radius (1681 surface points,
its 40 interior keypoints valid for every method, plus its two degenerate keypoints, invalid).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import lrf_jax
from lrf_jax.datasets.synthetic import vertex_normals
from tests.lrf_testing import synthetic_mesh

SCALES = (1e-30, 1e-12, 1e-3, 1e3, 1e12, 1e30)
AGREE = 1e-5  # max abs difference of frame entries between a scaled and the unscaled cloud
PATHS = ("auto", "jit")
N_INTERIOR = 40


def _mesh():
  points, faces, keypoints, radius = synthetic_mesh()
  n = 41
  interior = np.arange(n * n).reshape(n, n)[7:34:4, 7:34:4].reshape(-1)[:N_INTERIOR]
  points = points / radius  # radius 1: the sweep's radii span exactly 1e-30 .. 1e30
  kp = np.concatenate([interior, keypoints[-2:]])  # + one lone pair point, one collinear point
  return points, faces, kp, vertex_normals(points, faces)


POINTS, FACES, KEYPOINTS, NORMALS = _mesh()
NORMAL_METHODS = [m for m, spec in lrf_jax.METHODS.items() if spec.needs_normals]


def _frames(method: str, kernel: str, scale: float = 1.0, normals: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
  spec = lrf_jax.METHODS[method]
  kw = {}
  if spec.needs_mesh:
    kw["faces"] = FACES
  if spec.needs_normals or spec.uses_viewpoint:
    kw["normals"] = NORMALS if normals is None else normals
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # the degenerate keypoints' tiny balls
    f, v = lrf_jax.compute_frames(POINTS * scale, KEYPOINTS, scale, method, kernel=kernel, **kw)
  return np.asarray(f), np.asarray(v)


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("method", list(lrf_jax.METHODS))
def test_frames_do_not_depend_on_the_scale(method, kernel):
  base, valid = _frames(method, kernel)
  assert valid[:N_INTERIOR].all(), f"{method}: interior keypoints invalid at scale 1"
  assert not valid[N_INTERIOR:].any(), f"{method}: a degenerate keypoint came back valid"
  for s in SCALES:
    f, v = _frames(method, kernel, s)
    np.testing.assert_array_equal(v, valid, err_msg=f"{method} {kernel}: validity at scale {s:g}")
    diff = float(np.abs(f - base).max())
    assert diff <= AGREE, f"{method} {kernel}: frames at scale {s:g} differ by {diff:.2e}"


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("method", NORMAL_METHODS)
def test_zero_normals_make_every_frame_invalid(method, kernel):
  zero = np.zeros_like(NORMALS)
  f, v = _frames(method, kernel, normals=zero)
  assert not v.any(), f"{method} {kernel}: {int(v.sum())} frames valid from all-zero normals"
  np.testing.assert_array_equal(f, np.broadcast_to(np.eye(3, dtype=np.float32), f.shape))
  # Zero rows are missing normals, as NaN rows are: the same frames either way.
  some = NORMALS.copy()
  some[::3] = 0.0
  nan = NORMALS.copy()
  nan[::3] = np.nan
  f0, v0 = _frames(method, kernel, normals=some)
  f1, v1 = _frames(method, kernel, normals=nan)
  np.testing.assert_array_equal(v0, v1)
  np.testing.assert_array_equal(f0, f1)


@pytest.mark.parametrize("kernel", PATHS)
@pytest.mark.parametrize("scale", (1e-40, 1e40))
def test_out_of_range_scale_raises(scale, kernel):
  with pytest.raises(ValueError, match="scale"):
    _frames("toldi", kernel, scale)


@pytest.mark.parametrize("method", ("toldi", "shot", "rops"))
def test_far_coordinates_raise_value_error_not_system_error(method):
  """A cloud 1e160 radii from the origin (float64 offsets there are meaningless and the grid's
  integer cell indices overflow) is refused before any compiled code runs."""
  spec = lrf_jax.METHODS[method]
  kw = {"faces": FACES} if spec.needs_mesh else {}
  with pytest.raises(ValueError, match="scale"):
    lrf_jax.compute_frames(POINTS + 1e160, KEYPOINTS, 1.0, method, **kw)
