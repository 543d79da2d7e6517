"""`.e57` files (`lrf_jax.io.read_e57`, the `formats` extra): files pye57 itself writes, with one
scan and with two scans with poses, read back through `read_cloud` (every scan, its pose
applied, concatenated), by scan, and through lrf-frames; the errors of a damaged file and of an
install without pye57."""

from __future__ import annotations

import sys

import numpy as np
import pytest

pye57 = pytest.importorskip(
    "pye57", reason="pye57 is not installed: the `formats` extra (pip install 'lrf_jax[formats]') "
    "reads .e57")

from scipy.spatial.transform import Rotation  # noqa: E402

from lrf_jax import io  # noqa: E402
from tests.lrf_testing import cli_error  # noqa: E402

# pye57 writes coordinates as float32 ("single precision" E57 float nodes): the file's precision.
F32 = float(np.finfo(np.float32).eps)


def _pose(angles_deg, translation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """(E57 quaternion w, x, y, z; rotation matrix; translation) of a scan's pose."""
  r = Rotation.from_euler("zyx", angles_deg, degrees=True)
  x, y, z, w = r.as_quat()
  return np.array([w, x, y, z]), r.as_matrix(), np.asarray(translation, np.float64)


def write_e57(path, scans) -> list[np.ndarray]:
  """Write `scans` [(points (n, 3), pose or None, invalid (n,) bool or None)] with pye57; the
  scans' coordinates as stored (float32), in their scanner frames."""
  stored = []
  with pye57.E57(str(path), mode="w") as f:
    for points, pose, invalid in scans:
      data = {"cartesianX": points[:, 0], "cartesianY": points[:, 1],
              "cartesianZ": points[:, 2], "intensity": np.linspace(0.0, 1.0, len(points))}
      if invalid is not None:
        data["cartesianInvalidState"] = np.where(invalid, 2, 0).astype(np.int8)
      kw = {} if pose is None else dict(rotation=pose[0], translation=pose[2])
      f.write_scan_raw(data, **kw)
      stored.append(points.astype(np.float32).astype(np.float64))
  return stored


def _points(n: int, seed: int) -> np.ndarray:
  return np.random.default_rng(seed).uniform(-5.0, 5.0, (n, 3))


def _close(a: np.ndarray, b: np.ndarray, scale: float = 20.0) -> None:
  """Equal within float32's precision at coordinates up to `scale`."""
  assert a.shape == b.shape
  assert np.abs(a - b).max() <= 4 * F32 * scale, np.abs(a - b).max()


def test_one_scan_reads_back_within_float32(tmp_path):
  pts = _points(800, 0)
  (stored,) = write_e57(tmp_path / "one.e57", [(pts, None, None)])
  cloud = io.read_cloud(tmp_path / "one.e57")
  assert cloud.points.dtype == np.float64 and cloud.faces is None and cloud.normals is None
  np.testing.assert_array_equal(cloud.points, stored)  # identity pose: exactly what is stored
  _close(cloud.points, pts)


def test_two_scans_with_poses_are_concatenated_in_the_file_frame(tmp_path):
  a, b = _points(500, 1), _points(300, 2)
  pose_a = _pose([0, 0, 0], [0, 0, 0])
  pose_b = _pose([40, -10, 5], [10.0, -2.0, 0.5])
  stored = write_e57(tmp_path / "two.e57", [(a, pose_a, None), (b, pose_b, None)])
  want_b = stored[1] @ pose_b[1].T + pose_b[2]
  cloud = io.read_cloud(tmp_path / "two.e57")
  assert len(cloud) == 800
  _close(cloud.points[:500], stored[0])
  _close(cloud.points[500:], want_b)
  _close(cloud.points[500:], b @ pose_b[1].T + pose_b[2])  # the written coordinates
  # scan by scan: posed, or in the scanner's own frame
  _close(io.read_e57(tmp_path / "two.e57", scan=1).points, want_b)
  np.testing.assert_array_equal(
      io.read_e57(tmp_path / "two.e57", scan=1, apply_pose=False).points, stored[1])
  np.testing.assert_array_equal(io.read_e57(tmp_path / "two.e57", scan=0).points[:5],
                                cloud.points[:5])


def test_invalid_points_are_left_out(tmp_path):
  pts = _points(100, 3)
  invalid = np.zeros(100, bool)
  invalid[::7] = True
  (stored,) = write_e57(tmp_path / "s.e57", [(pts, None, invalid)])
  np.testing.assert_array_equal(io.read_cloud(tmp_path / "s.e57").points, stored[~invalid])


@pytest.mark.parametrize("kw,fragment", [
    (dict(scan=2), r"scan: expected an index in \[0, 2\) \(2 scans in data3D\), found 2"),
    (dict(scan=-1), r"scan: expected an index in \[0, 2\)"),
    (dict(scan=True), r"found True"),
    (dict(apply_pose=False), r"apply_pose=False: expected a scan index"),
])
def test_bad_scan_arguments_name_the_file(tmp_path, kw, fragment):
  write_e57(tmp_path / "two.e57", [(_points(20, 4), None, None), (_points(20, 5), None, None)])
  with pytest.raises(ValueError, match=fragment) as e:
    io.read_e57(tmp_path / "two.e57", **kw)
  assert str(e.value).startswith(f"{tmp_path / 'two.e57'}: ")


@pytest.mark.parametrize("content", [b"", b"not an e57 file" * 100])
def test_a_bad_file_is_one_error_line_and_is_kept(tmp_path, content):
  path = tmp_path / "bad.e57"
  path.write_bytes(content)
  with pytest.raises(ValueError) as e:
    io.read_cloud(path)
  message = str(e.value)
  assert message.startswith(f"{path}: file: expected an E57 point cloud, found an unreadable file")
  assert "\n" not in message  # libE57Format's debug lines are left out
  assert path.read_bytes() == content  # pye57 removes a file it fails to open for writing only


def test_a_truncated_file_names_it(tmp_path):
  path = tmp_path / "t.e57"
  write_e57(path, [(_points(2000, 6), None, None)])
  data = path.read_bytes()
  path.write_bytes(data[: len(data) // 2])
  with pytest.raises(ValueError, match="expected an E57 point cloud") as e:
    io.read_cloud(path)
  assert str(e.value).startswith(f"{path}: ")


def test_without_pye57_the_error_names_the_extra(tmp_path, monkeypatch):
  write_e57(tmp_path / "s.e57", [(_points(10, 7), None, None)])
  monkeypatch.setitem(sys.modules, "pye57", None)
  with pytest.raises(io.MissingReaderError) as e:
    io.read_cloud(tmp_path / "s.e57")
  assert str(e.value).startswith(f"{tmp_path / 's.e57'}: reading .e57 needs pye57, ")
  assert "pip install 'lrf_jax[formats]'" in str(e.value)


def test_lrf_frames_on_an_e57_writes_frames(tmp_path):
  from lrf_jax import datasets
  from lrf_jax.cli.frames import main
  pts = np.asarray(datasets.make_demo_pair(1).model_points)[::8]
  pose = _pose([10, 20, 30], [1.0, 2.0, 3.0])
  (stored,) = write_e57(tmp_path / "object.e57", [(pts, pose, None)])
  out = tmp_path / "f.npz"
  assert main([str(tmp_path / "object.e57"), "--out", str(out), "--keypoints", "40"]) == 0
  with np.load(out) as f:
    assert f["frames"].shape == (40, 3, 3) and f["valid"].sum() >= 30
    _close(f["positions"], (stored @ pose[1].T + pose[2])[f["keypoints"]])


def test_lrf_frames_without_pye57_is_one_error_line(tmp_path, monkeypatch, capsys):
  from lrf_jax.cli.frames import main
  write_e57(tmp_path / "s.e57", [(_points(10, 8), None, None)])
  monkeypatch.setitem(sys.modules, "pye57", None)
  assert main([str(tmp_path / "s.e57"), "--out", str(tmp_path / "f.npz")]) == 2
  err = cli_error(capsys)
  assert "needs pye57" in err and "lrf_jax[formats]" in err and len(err.splitlines()) == 1
  assert not (tmp_path / "f.npz").exists()


def test_a_symbolic_link_loop_is_named(tmp_path):
  loop = tmp_path / "loop.e57"
  loop.symlink_to(loop)
  with pytest.raises(io.SymlinkLoopError, match="symbolic link loop"):
    io.read_cloud(loop)
