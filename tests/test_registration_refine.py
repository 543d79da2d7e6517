"""lrf_jax.registration.refine: an init is checked by the one rigid-transform rule, its rotation
block projected to the nearest rotation within INIT_PROJECT (a published ground truth printed
with few digits), refused beyond with the figure."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax.io.validation import ProjectedRotation, nearest_rotation, rigid_deviation
from lrf_jax.registration import refine


def _off(deviation: float, seed: int = 0) -> np.ndarray:
  rng = np.random.default_rng(seed)
  t = np.eye(4)
  t[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
  t[:3, 3] = rng.normal(size=3)
  noise = rng.normal(size=(3, 3))
  t[:3, :3] += noise / np.abs(noise).max() * deviation / 2
  return t


def test_nearest_rotation_is_the_polar_factor():
  rng = np.random.default_rng(1)
  for _ in range(20):
    m = rng.normal(size=(3, 3))
    r = nearest_rotation(m)
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12) and np.linalg.det(r) == pytest.approx(1)
    # no rotation is nearer (Frobenius): compare with random rotations near it
    for q in Rotation.random(50, random_state=2).as_matrix():
      assert np.linalg.norm(m - r) <= np.linalg.norm(m - q) + 1e-12


def test_an_init_off_orthonormal_within_the_bound_is_projected_with_a_warning():
  t = _off(5e-4)
  assert 1e-4 < rigid_deviation(t) < 1e-2
  with pytest.warns(ProjectedRotation, match=r"off orthonormal"):
    out = refine.check_init(t)
  assert rigid_deviation(out) < 1e-12 and np.array_equal(out[:3, 3], t[:3, 3])
  assert np.abs(out[:3, :3] - t[:3, :3]).max() < 1e-3


def test_an_init_beyond_the_bound_is_refused_naming_the_figure():
  t = _off(3e-2)
  with pytest.raises(ValueError, match=r"init: matrix: expected an orthonormal rotation block "
                                       r"\(\|RᵀR - I\| <= 0.01\), found \|RᵀR - I\| = 0.0"):
    refine.check_init(t)


def test_a_rigid_init_is_returned_as_it_is():
  import warnings
  t = _off(0.0)
  with warnings.catch_warnings():
    warnings.simplefilter("error", ProjectedRotation)
    assert np.array_equal(refine.check_init(t), t)


def test_the_cli_notes_a_projected_init_in_one_line(tmp_path, capsys):
  from lrf_jax.cli.register import read_init
  path = tmp_path / "init.txt"
  np.savetxt(path, _off(5e-4))
  out = read_init(str(path))
  assert rigid_deviation(out) < 1e-12
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("note: --init: ") and "projected" in err[0]
