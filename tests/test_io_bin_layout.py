"""`.bin` sweeps of either layout (`lrf_jax.io.sweeps`): 16-byte x, y, z, reflectance points (KITTI's,
the default) and 12-byte x, y, z ones (`bin_layout="xyz"`, `--bin-layout xyz`); a size that fits
only the other layout, and one that fits both with values that do not fit the default, are one
error naming both layouts and the option; `--bin-layout` reaches every command line's reader."""

from __future__ import annotations

import numpy as np
import pytest

from lrf_jax import io
from lrf_jax.io.reader import cloud_source
from lrf_jax.io.sweeps import MAX_SWEEP_RANGE
from tests.lrf_testing import FakeRegistration, cli_error


def sweep(n: int, seed: int = 0) -> np.ndarray:
  """A sensor-frame sweep's points (n, 3) float32: a ring of ground and walls around the
  sensor, as a car-mounted LiDAR sees them (both signs of x and y, z mostly below 0)."""
  rng = np.random.default_rng(seed)
  az = rng.uniform(0, 2 * np.pi, n)
  r = rng.uniform(3.0, 40.0, n)
  z = np.where(rng.random(n) < 0.6, -1.7, rng.uniform(-1.7, 3.0, n))
  return np.stack([r * np.cos(az), r * np.sin(az), z], axis=1).astype(np.float32)


def write_bin(path, points: np.ndarray, reflectance: np.ndarray | None = None) -> None:
  """16-byte records with `reflectance`, 12-byte ones without."""
  pts = np.asarray(points, "<f4")
  if reflectance is not None:
    pts = np.column_stack([pts, np.asarray(reflectance, "<f4")])
  pts.tofile(path)


# n points: 16 n bytes fits 12-byte points too when n % 3 == 0; 12 n fits 16 when n % 4 == 0.
@pytest.mark.parametrize("n", [1000, 999])
def test_the_16_byte_layout_is_the_default(tmp_path, n):
  pts = sweep(n)
  write_bin(tmp_path / "s.bin", pts, np.random.default_rng(1).uniform(0, 0.99, n))
  for kw in ({}, dict(bin_layout="xyzi")):
    cloud = io.read_cloud(tmp_path / "s.bin", **kw)
    assert cloud.points.dtype == np.float64
    np.testing.assert_array_equal(cloud.points, pts.astype(np.float64))
  np.testing.assert_array_equal(io.read_kitti_bin(tmp_path / "s.bin").points, pts)


@pytest.mark.parametrize("n", [1000, 999])
def test_the_12_byte_layout_is_read_with_the_option(tmp_path, n):
  pts = sweep(n)
  write_bin(tmp_path / "s.bin", pts)
  cloud = io.read_cloud(tmp_path / "s.bin", bin_layout="xyz")
  np.testing.assert_array_equal(cloud.points, pts.astype(np.float64))


@pytest.mark.parametrize("reflectance", [
    lambda n, rng: rng.uniform(0.0, 0.99, n),                     # KITTI's [0, 1]
    lambda n, rng: rng.integers(0, 256, n).astype(float),         # an 8-bit count
    lambda n, rng: rng.integers(0, 65536, n).astype(float),       # a 16-bit count
])
def test_a_size_fitting_both_with_a_reflectance_is_read_as_the_default(tmp_path, reflectance):
  n = 999  # 16 * 999 = 48 * 333
  pts = sweep(n)
  write_bin(tmp_path / "s.bin", pts, reflectance(n, np.random.default_rng(2)))
  np.testing.assert_array_equal(io.read_cloud(tmp_path / "s.bin").points, pts)


def test_a_12_byte_file_of_a_size_fitting_both_is_refused_naming_the_option(tmp_path):
  path = tmp_path / "s.bin"
  write_bin(path, sweep(1000))  # 12 * 1000 = 48 * 250
  with pytest.raises(ValueError) as e:
    io.read_cloud(path)
  message = str(e.value)
  assert message.startswith(f"{path}: reflectance (4th float of each 16-byte point): expected ")
  assert "negative values" in message and "fits both" in message
  assert "bin_layout='xyz' (--bin-layout xyz" in message and "--bin-layout xyzi" in message
  assert "\n" not in message
  assert len(io.read_cloud(path, bin_layout="xyz")) == 1000  # as the message says
  assert len(io.read_cloud(path, bin_layout="xyzi")) == 750  # asked for: read unchecked


def test_coordinates_beyond_any_sensor_are_refused_when_the_size_fits_both(tmp_path):
  pts = sweep(999)
  pts[10] = (2 * MAX_SWEEP_RANGE, 0.0, 0.0)
  write_bin(tmp_path / "s.bin", pts, np.full(999, 0.5))
  with pytest.raises(ValueError, match=r"x/y/z: expected a sensor-frame sweep's coordinates, "
                     r"within 10000 m of the sensor, found 1 points beyond it.*--bin-layout xyz"):
    io.read_cloud(tmp_path / "s.bin")
  assert len(io.read_cloud(tmp_path / "s.bin", bin_layout="xyzi")) == 999


@pytest.mark.parametrize("n,layout,written,other", [
    (1001, None, "xyz", "xyz"),      # 12 * 1001: not a multiple of 16
    (1001, "xyzi", "xyz", "xyz"),
    (1001, "xyz", "xyzi", "xyzi"),   # 16 * 1001: not a multiple of 12
])
def test_a_size_fitting_only_the_other_layout_names_both_and_the_option(tmp_path, n, layout,
                                                                         written, other):
  path = tmp_path / "s.bin"
  write_bin(path, sweep(n), None if written == "xyz" else np.full(n, 0.5))
  with pytest.raises(ValueError) as e:
    io.read_cloud(path, bin_layout=layout)
  message = str(e.value)
  assert message.startswith(f"{path}: size: expected a whole number of ")
  assert "16-byte points" in message and "12-byte points" in message
  assert f"pass bin_layout={other!r} (--bin-layout {other} on the command line)" in message


def test_a_size_fitting_neither_layout_names_both(tmp_path):
  path = tmp_path / "s.bin"
  path.write_bytes(b"\0" * 50)
  with pytest.raises(ValueError, match=r"size: expected a whole number of 16-byte points .*"
                     r"found 50 bytes, a whole number of neither 16-byte .* nor 12-byte"):
    io.read_cloud(path)


def test_a_bad_layout_is_refused(tmp_path):
  write_bin(tmp_path / "s.bin", sweep(4))
  with pytest.raises(ValueError, match=r"bin_layout: expected one of 'xyzi', 'xyz'"):
    io.read_cloud(tmp_path / "s.bin", bin_layout="xyzrgb")


def test_cloud_source_reads_only_bin_files_with_a_layout(tmp_path):
  write_bin(tmp_path / "s.bin", sweep(1000))
  np.save(tmp_path / "s.npy", sweep(10))
  for path in (tmp_path / "s.bin", str(tmp_path / "s.npy")):
    assert cloud_source(path) is path  # read later, by read_cloud's defaults
  assert cloud_source(str(tmp_path / "s.npy"), "xyz") == str(tmp_path / "s.npy")
  cloud = cloud_source(tmp_path / "s.bin", "xyz")
  assert isinstance(cloud, io.Cloud) and len(cloud) == 1000
  with pytest.raises(ValueError, match="--bin-layout"):
    cloud_source(tmp_path / "s.bin", "xyzw")


def test_the_real_kitti_sweeps_read_as_the_default(data_root, tmp_path):
  """The six raw KITTI sweeps (five of six have a size that fits both layouts) read as 16-byte
  points, unchanged; their first three columns saved as 12-byte points are refused without the
  option (62% of the misread reflectance negative) and read with it."""
  sweeps = sorted((data_root / "lidar_kitti00").glob("*.bin"))
  assert len(sweeps) == 6
  for path in sweeps:
    raw = np.fromfile(path, "<f4").reshape(-1, 4)
    np.testing.assert_array_equal(io.read_cloud(path).points, raw[:, :3])
  raw = np.fromfile(sweeps[0], "<f4").reshape(-1, 4)
  assert len(raw) % 4 == 0  # its 12-byte form fits both layouts too
  raw[:, :3].tofile(tmp_path / "xyz.bin")
  with pytest.raises(ValueError, match="--bin-layout xyz"):
    io.read_cloud(tmp_path / "xyz.bin")
  np.testing.assert_array_equal(io.read_cloud(tmp_path / "xyz.bin", bin_layout="xyz").points,
                                raw[:, :3])


# ----------------------------------------------------------------------------- command lines




def _fake_register(seen: list):
  """A `register` that reads its inputs as the real one does (`as_cloud`) and records them."""
  def register(source, target, **kw):
    from lrf_jax.geometry.cloud import as_cloud
    seen.append((source, target, as_cloud(source, "source"), as_cloud(target, "target"), kw))
    return FakeRegistration()
  return register


@pytest.fixture()
def sweeps_12(tmp_path):
  """Two 12-byte sweeps of sizes that fit only 12-byte points (1001 points) and one that fits
  both (1000 points)."""
  paths = []
  for k, n in enumerate((1001, 1001, 1000)):
    paths.append(tmp_path / f"s{k}.bin")
    write_bin(paths[-1], sweep(n, seed=k))
  return paths


def test_lrf_frames_reads_a_12_byte_sweep_with_the_option(sweeps_12, tmp_path, capsys):
  from lrf_jax.cli.frames import main
  out = tmp_path / "f.npz"
  assert main([str(sweeps_12[0]), "--out", str(out), "--keypoints", "30"]) == 2
  err = cli_error(capsys)
  assert "--bin-layout xyz" in err and "12-byte points" in err and len(err.splitlines()) == 1
  assert not out.exists()
  assert main([str(sweeps_12[0]), "--out", str(out), "--keypoints", "30", "--bin-layout",
               "xyz"]) == 0
  with np.load(out) as f:
    assert f["frames"].shape == (30, 3, 3)
    np.testing.assert_array_equal(f["positions"], sweep(1001, 0)[f["keypoints"]])


def test_lrf_frames_refuses_a_bad_layout_before_any_work(sweeps_12, tmp_path, capsys):
  from lrf_jax.cli.frames import main
  with pytest.raises(SystemExit) as e:
    main([str(sweeps_12[0]), "--out", str(tmp_path / "f.npz"), "--bin-layout", "xyzw"])
  assert e.value.code == 2 and "--bin-layout" in capsys.readouterr().err


def test_lrf_register_hands_the_sweeps_read_with_the_option(sweeps_12, monkeypatch, capsys):
  from lrf_jax import registration
  from lrf_jax.cli.register import main
  seen: list = []
  monkeypatch.setattr(registration, "register", _fake_register(seen))
  kitti = sweeps_12[0].parent / "kitti.bin"  # 16-byte points
  write_bin(kitti, sweep(999, 5), np.full(999, 0.25))
  a, b = str(kitti), str(sweeps_12[0])
  assert main([a, a]) == 0
  assert seen[-1][:2] == (a, a)  # no option: the paths, read by `register` as before
  capsys.readouterr()
  assert main([a, b]) == 2
  assert "--bin-layout xyz" in cli_error(capsys)
  assert main([b, str(sweeps_12[2]), "--bin-layout", "xyz"]) == 0
  *_, source, target, kw = seen[-1]
  assert "bin_layout" not in kw
  np.testing.assert_array_equal(source.points, sweep(1001, 0))
  np.testing.assert_array_equal(target.points, sweep(1000, 2))


def test_lrf_register_reads_with_the_option_end_to_end(sweeps_12, capsys):
  """Without the option the 12-byte sweep is one error line naming it; with it a transform
  is printed (rc 0 or 3)."""
  from lrf_jax.cli.register import main
  a, b = str(sweeps_12[0]), str(sweeps_12[1])
  assert main([a, b, "--keypoints", "200"]) == 2
  assert "--bin-layout xyz" in cli_error(capsys)
  rc = main([a, b, "--keypoints", "200", "--bin-layout", "xyz"])
  out = capsys.readouterr()
  assert rc in (0, 3), out.err
  assert np.array([[float(v) for v in line.split()] for line in out.out.split("\n")[:4]]).shape \
      == (4, 4)


def test_the_multiway_form_reads_with_the_option(sweeps_12, tmp_path, monkeypatch, capsys):
  from lrf_jax import multiway
  from lrf_jax.cli.register import main
  from lrf_jax.multiway import pipeline
  seen = {}

  def run(clouds, *, names, **kw):
    seen["clouds"] = clouds
    n = len(names)
    return multiway.MultiwayResult(names=tuple(names), poses=np.tile(np.eye(4), (n, 1, 1)),
                                   in_model=np.ones(n, bool), reference=0, edges=(), mr=1.0,
                                   seconds=0.0)
  monkeypatch.setattr(pipeline, "register_all", run)
  scans = [str(p) for p in sweeps_12]
  assert main([*scans, "--quiet"]) == 2
  assert "--bin-layout xyz" in cli_error(capsys)
  assert main([*scans, "--quiet", "--bin-layout", "xyz"]) == 0
  assert [len(c.points) for c in seen["clouds"]] == [1001, 1001, 1000]
  np.testing.assert_array_equal(seen["clouds"][2].points, sweep(1000, 2))


def test_lrf_batch_frames_and_register_take_the_option(sweeps_12, tmp_path, monkeypatch, capsys):
  """lrf-batch frames runs lrf-frames' computation with the layout (an item per scan, done);
  lrf-batch register hands the layout to each pair's reading (the registration replaced: the
  reading is under test) and records it among the job's options."""
  from lrf_jax import registration
  from lrf_jax.cli.batch import main
  scans = [str(p) for p in sweeps_12[:2]]
  out = tmp_path / "frames"
  assert main(["frames", *scans, "--out", str(out), "--keypoints", "20", "--no-progress"]) == 3
  assert main(["frames", *scans, "--out", str(tmp_path / "frames2"), "--keypoints", "20",
               "--no-progress", "--bin-layout", "xyz"]) == 0
  with np.load(tmp_path / "frames2" / "s0.npz") as f:
    np.testing.assert_array_equal(f["positions"], sweep(1001, 0)[f["keypoints"]])
  capsys.readouterr()
  seen: list = []
  monkeypatch.setattr(registration, "register", _fake_register(seen))
  pairs = tmp_path / "pairs.tsv"
  pairs.write_text(f"source\ttarget\n{scans[0]}\t{scans[1]}\n")
  assert main(["register", str(pairs), "--out", str(tmp_path / "reg"), "--no-progress"]) == 3
  assert "--bin-layout xyz" in (tmp_path / "reg" / "results.tsv").read_text()
  assert main(["register", str(pairs), "--out", str(tmp_path / "reg2"), "--no-progress",
               "--bin-layout", "xyz"]) == 0
  *_, source, target, kw = seen[-1]
  assert "bin_layout" not in kw and len(source.points) == 1001 == len(target.points)
  records = list((tmp_path / "reg2" / ".lrf-batch").rglob("*.json"))
  assert any('"bin_layout": "xyz"' in r.read_text() for r in records)  # among its options
