"""`lrf_jax.checks`: coordinates too large to compute with are refused by the one cloud check,
with the magnitude found and the limit, and without overflowing while checking."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from lrf_jax import checks, datasets, io


@pytest.fixture(scope="module")
def points():
  return datasets.make_demo_pair(0).model_points[::8]


@pytest.mark.parametrize("scale", [1e44, 1e150, 1e200, 1e300])
def test_huge_coordinates_are_refused_naming_magnitude_and_limit(points, scale):
  big = points * (scale / np.abs(points).max())
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # no overflow while checking
    with pytest.raises(ValueError) as e:
      checks.validate_cloud(big, "source")
  message = str(e.value)
  assert message.startswith("source: expected coordinates of magnitude at most 1e+42, got "
                            f"{len(big)} point(s) beyond it (largest magnitude {scale:.3e}")
  assert "overflow float64" in message and "rescale the cloud" in message
  assert "fold" not in message and "inf" not in message.replace("to inf", "")


def test_the_largest_supported_coordinates_pass(points):
  ok = points * (checks.MAX_COORDINATE / np.abs(points).max())
  np.testing.assert_array_equal(checks.validate_cloud(ok), ok)
  assert checks.MAX_COORDINATE == checks.MAX_SCALE * checks.MAX_RADII_FROM_ORIGIN
  assert checks.MAX_COORDINATE ** 2 * 1e12 < np.finfo(np.float64).max  # sums of squares: finite


def test_non_finite_points_keep_their_message(points):
  bad = points.copy()
  bad[3, 1] = 1e300
  bad[5, 0] = np.nan
  with pytest.raises(ValueError, match=r"^points: expected finite coordinates, got 1 non-finite "
                                       r"point\(s\) \(NaN or inf; first at row 5"):
    checks.validate_cloud(bad)


def test_a_reader_names_the_file_and_field(points, tmp_path):
  path = tmp_path / "scan.npy"
  np.save(path, points * 1e200)
  with pytest.raises(ValueError, match=r"scan\.npy: x/y/z columns: expected coordinates of "
                                       r"magnitude at most 1e\+42"):
    io.read_cloud(path)


def test_huge_viewpoints_and_translations_are_refused(tmp_path):
  with pytest.raises(ValueError, match=r"^viewpoint: expected a sensor position with coordinates "
                                       r"of magnitude at most 1e\+42"):
    checks.validate_viewpoint([1e300, 0.0, 0.0])
  assert checks.validate_viewpoint([1e42, 0.0, 0.0]) is not None
  t = np.eye(4)
  t[:3, 3] = [0.0, 1e200, 0.0]
  with pytest.raises(ValueError, match=r"^T\.txt: pose: expected a translation of magnitude at "
                                       r"most 1e\+42 .*found translation \[0\.0, 1e\+200, 0\.0\] "
                                       r"\(magnitude 1\.000e\+200\)"):
    io.check_rigid(t, "T.txt", "pose")


def test_uint64_keypoint_out_of_range_is_reported_exactly():
  from lrf_jax.checks import validate_keypoints
  with pytest.raises(ValueError, match="9223372036854775813"):
    validate_keypoints(np.array([2**63 + 5], np.uint64), 100)


@pytest.mark.parametrize("seed, ok", [(0, True), (2**32 - 1, True), (np.uint32(7), True),
                                      (-1, False), (2**32, False), (2**64, False),
                                      (True, False), (1.0, False)])
def test_one_seed_rule_for_the_library_and_every_command_line(seed, ok):
  """Seeds are integers in [0, 2**32): JAX's keys take 32 bits, a larger seed would repeat a
  smaller one (key(2**32 + 5) == key(5)) or overflow."""
  from lrf_jax.checks import validate_seed
  if ok:
    assert validate_seed(seed) == int(seed)
  else:
    with pytest.raises(ValueError, match=r"--seed: expected an integer in \[0, 2\*\*32\)"):
      validate_seed(seed, "--seed")


def test_derived_seeds_stay_in_range():
  from lrf_jax.checks import MAX_SEED, derived_seed, validate_seed
  assert derived_seed(5, 1) == 6 and derived_seed(MAX_SEED - 1, 1) == 0
  assert validate_seed(derived_seed(MAX_SEED - 1, 3)) == 2
