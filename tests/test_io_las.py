"""`.las`/`.laz` files (`lrf_jax.io.read_las`, the `formats` extra): files laspy itself writes, with
a scale and an offset, read back through `read_cloud` and the command lines; the errors of a
damaged file and of an install without laspy or its LAZ backend."""

from __future__ import annotations

import sys

import numpy as np
import pytest

laspy = pytest.importorskip(
    "laspy", reason="laspy is not installed: the `formats` extra (pip install 'lrf_jax[formats]') "
    "reads .las/.laz")

from lrf_jax import io  # noqa: E402
from lrf_jax.io.las import read_las  # noqa: E402
from tests.lrf_testing import cli_error  # noqa: E402

# A georeferenced file: UTM-like offsets, millimetre counts.
SCALES = np.array([0.001, 0.001, 0.0005])
OFFSETS = np.array([500_000.0, 4_100_000.0, 120.0])


def _has_laz() -> bool:
  return bool(laspy.LazBackend.detect_available())


def write_las(path, points: np.ndarray, *, scales=SCALES, offsets=OFFSETS, point_format: int = 3,
              version: str = "1.2") -> np.ndarray:
  """Write `points` (n, 3) with laspy (compressed for a .laz path); the coordinates the file
  holds (rounded to its scale), as laspy reads them back."""
  header = laspy.LasHeader(point_format=point_format, version=version)
  header.scales, header.offsets = np.asarray(scales), np.asarray(offsets)
  las = laspy.LasData(header)
  las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
  las.intensity = np.arange(len(points), dtype=np.uint16)
  las.write(str(path))
  return np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)


def _points(n: int = 2000, seed: int = 0) -> np.ndarray:
  rng = np.random.default_rng(seed)
  return OFFSETS + rng.uniform(0.0, 50.0, (n, 3))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("point_format,version", [(0, "1.2"), (3, "1.2"), (6, "1.4")])
def test_read_back_within_the_scale(tmp_path, suffix, point_format, version):
  if suffix == ".laz" and not _has_laz():
    pytest.skip("no LAZ backend (lazrs) installed")
  pts = _points()
  path = tmp_path / f"cloud{suffix}"
  stored = write_las(path, pts, point_format=point_format, version=version)
  cloud = io.read_cloud(path)
  assert cloud.points.dtype == np.float64 and cloud.points.shape == pts.shape
  assert cloud.faces is None and cloud.normals is None and cloud.path == path
  np.testing.assert_array_equal(cloud.points, stored)  # X * scale + offset, in float64
  assert np.all(np.abs(cloud.points - pts) <= SCALES / 2 + 1e-9)  # within half a count
  np.testing.assert_array_equal(read_las(path).points, cloud.points)


def test_compression_is_read_from_the_header_not_the_suffix(tmp_path):
  if not _has_laz():
    pytest.skip("no LAZ backend (lazrs) installed")
  stored = write_las(tmp_path / "c.laz", _points(300))
  (tmp_path / "c.laz").rename(tmp_path / "named.las")
  np.testing.assert_array_equal(io.read_cloud(tmp_path / "named.las").points, stored)


def test_a_truncated_las_names_the_point_count(tmp_path):
  path = tmp_path / "c.las"
  write_las(path, _points(1000))
  data = path.read_bytes()
  for cut, name in ((len(data) // 2, "half.las"), (len(data) - 3 * 34, "three_short.las")):
    (tmp_path / name).write_bytes(data[:cut])  # the second at a record boundary: laspy reads
    with pytest.raises(ValueError, match=r"point count: expected 1000 points") as e:  # fewer
      io.read_cloud(tmp_path / name)
    assert str(tmp_path / name) in str(e.value) and "truncated" in str(e.value)


@pytest.mark.parametrize("content,fragment", [
    (b"not a las file at all" * 20, "Invalid file signature"),
    (b"", "empty"),
])
def test_a_bad_file_is_one_error_naming_it(tmp_path, content, fragment):
  path = tmp_path / "bad.las"
  path.write_bytes(content)
  with pytest.raises(ValueError) as e:
    io.read_cloud(path)
  message = str(e.value)
  assert message.startswith(f"{path}: ") and "LAS/LAZ" in message and "\n" not in message
  assert fragment.lower() in message.lower()


def test_a_damaged_laz_is_one_error_naming_it(tmp_path):
  if not _has_laz():
    pytest.skip("no LAZ backend (lazrs) installed")
  path = tmp_path / "c.laz"
  write_las(path, _points(5000))
  data = path.read_bytes()
  path.write_bytes(data[: len(data) * 2 // 3])
  with pytest.raises(ValueError, match=r"expected a LAS/LAZ point cloud") as e:
    io.read_cloud(path)
  assert str(e.value).startswith(f"{path}: ")


def test_without_laspy_the_error_names_the_extra(tmp_path, monkeypatch):
  write_las(tmp_path / "c.las", _points(10))
  monkeypatch.setitem(sys.modules, "laspy", None)  # `import laspy` fails as if not installed
  for name, package in (("c.las", "laspy"), ("c.laz", "laspy[lazrs]")):
    (tmp_path / name).write_bytes((tmp_path / "c.las").read_bytes())
    with pytest.raises(io.MissingReaderError) as e:
      io.read_cloud(tmp_path / name)
    message = str(e.value)
    assert message.startswith(f"{tmp_path / name}: reading ")
    assert f"needs {package}," in message and "pip install 'lrf_jax[formats]'" in message
    assert isinstance(e.value, ImportError) and isinstance(e.value, ValueError)


def test_without_the_laz_backend_the_error_names_the_extra(tmp_path, monkeypatch):
  if not _has_laz():
    pytest.skip("no LAZ backend (lazrs) installed")
  write_las(tmp_path / "c.laz", _points(10))
  write_las(tmp_path / "c.las", _points(10))
  monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
  with pytest.raises(io.MissingReaderError, match=r"needs laspy\[lazrs\].*lrf_jax\[formats\]"):
    io.read_cloud(tmp_path / "c.laz")
  assert len(io.read_cloud(tmp_path / "c.las")) == 10  # uncompressed: no backend needed


def test_lrf_frames_on_a_laz_writes_frames(tmp_path, capsys):
  if not _has_laz():
    pytest.skip("no LAZ backend (lazrs) installed")
  from lrf_jax import datasets
  from lrf_jax.cli.frames import main
  pts = np.asarray(datasets.make_demo_pair(0).model_points)[::8]
  path = tmp_path / "object.laz"
  stored = write_las(path, pts * 10 + OFFSETS, scales=(1e-4, 1e-4, 1e-4))
  out = tmp_path / "f.npz"
  assert main([str(path), "--out", str(out), "--keypoints", "40"]) == 0
  with np.load(out) as f:
    assert f["frames"].shape == (40, 3, 3) and f["valid"].sum() >= 30
    np.testing.assert_array_equal(f["positions"], stored[f["keypoints"]])


def test_lrf_register_on_two_las_files_prints_the_transform(tmp_path, capsys):
  """A synthetic object and the same object moved by a known rigid transform, both in
  georeferenced files (offsets of 500 and 4100 km, 10 um counts): rc 0 (the rotation within a
  fraction of a degree of the truth, each point mapped within ~1 mr of its image, in the files'
  coordinates: the translation alone would carry the rotation's error times 4e6 m) or 3 (not
  sure: printed anyway)."""
  from scipy.spatial.transform import Rotation

  from lrf_jax import datasets
  from lrf_jax.cli.register import main
  pts = np.asarray(datasets.make_demo_pair(0, partial=False).model_points)[::2]
  t = np.eye(4)
  t[:3, :3] = Rotation.from_euler("zyx", [30, 10, 5], degrees=True).as_matrix()
  t[:3, 3] = (0.2, -0.1, 0.05)
  moved = pts @ t[:3, :3].T + t[:3, 3]
  scales = (1e-5, 1e-5, 1e-5)
  a = write_las(tmp_path / "a.las", pts + OFFSETS, scales=scales)
  b = write_las(tmp_path / "b.las", moved + OFFSETS, scales=scales)
  rc = main([str(tmp_path / "a.las"), str(tmp_path / "b.las"), "--keypoints", "300"])
  captured = capsys.readouterr()
  assert rc in (0, 3), captured.err
  printed = np.array([[float(v) for v in line.split()] for line in captured.out.split("\n")[:4]])
  assert printed.shape == (4, 4)
  if rc == 0:  # in the files' frame: b = R (a - o) + t + o, each point within ~1 mr (0.018)
    angle = np.degrees(Rotation.from_matrix(printed[:3, :3] @ t[:3, :3].T).magnitude())
    residual = np.abs(a @ printed[:3, :3].T + printed[:3, 3] - b).max()
    assert angle < 0.5 and residual < 0.02, (angle, residual)  # 9 printed digits at 4e6 m


def test_lrf_register_without_laspy_is_one_error_line(tmp_path, monkeypatch, capsys):
  from lrf_jax.cli.register import main
  write_las(tmp_path / "a.las", _points(50))
  monkeypatch.setitem(sys.modules, "laspy", None)
  assert main([str(tmp_path / "a.las"), str(tmp_path / "a.las")]) == 2
  err = cli_error(capsys)
  assert "a.las: reading .las needs laspy" in err and "lrf_jax[formats]" in err
  assert len(err.strip().splitlines()) == 1


def test_a_symbolic_link_loop_is_named(tmp_path):
  loop = tmp_path / "loop.laz"
  loop.symlink_to(loop)
  with pytest.raises(io.SymlinkLoopError, match="symbolic link loop"):
    io.read_cloud(loop)
