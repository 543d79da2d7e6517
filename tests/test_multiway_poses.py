"""Multiway's trajectory file poses.txt (KITTI's pose-file layout, issue 44) and `voxel_size`
passed through `register_all` and `--voxel-size` to every pairwise registration."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax import multiway
from lrf_jax.multiway import outputs as multiway_outputs
from lrf_jax.multiway import pipeline as multiway_pipeline


def _result(names, poses, in_model):
  return multiway.MultiwayResult(names=tuple(names), poses=poses, in_model=np.asarray(in_model),
                                 reference=0, edges=(), mr=1.0, seconds=0.0)


def _poses(n, seed=0):
  x = np.tile(np.eye(4), (n, 1, 1))
  x[1:, :3, :3] = Rotation.random(n - 1, random_state=seed).as_matrix()
  x[1:, :3, 3] = np.random.default_rng(seed).normal(size=(n - 1, 3)) * 10
  return x


def test_poses_txt_is_kittis_layout_with_nan_for_a_scan_left_out(tmp_path):
  """Line k: scan k's [R|t] row-major (12 numbers, p_ref = R p + t); a scan left out: 12 nan;
  written atomically and listed in the manifest."""
  x = _poses(4)
  x[2] = np.nan
  res = _result(["s0", "s1", "s2", "s3"], x, [True, True, False, True])
  clouds = [np.random.default_rng(k).normal(size=(30, 3)) for k in range(4)]
  multiway_outputs.write_outputs(res, clouds, tmp_path / "d", figures=False)
  text = (tmp_path / "d" / "poses.txt").read_text()
  lines = text.splitlines()
  assert len(lines) == 4 and all(len(line.split()) == 12 for line in lines)
  assert lines[2].split() == ["nan"] * 12
  back = np.loadtxt(tmp_path / "d" / "poses.txt").reshape(-1, 3, 4)
  for k in (0, 1, 3):
    np.testing.assert_allclose(back[k], x[k, :3, :4], rtol=1e-8, atol=1e-8)
  assert lines[0].split() == ["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"]
  manifest = json.loads((tmp_path / "d" / "manifest.json").read_text())
  assert "poses.txt" in manifest["files"]
  assert multiway_outputs.kitti_poses(x) == text


def test_a_scan_named_poses_does_not_overwrite_the_trajectory(tmp_path):
  names = multiway_outputs.scan_names(["d/poses.ply", "e/Poses.npy", "f/a.ply"])
  assert names == ["poses_2", "Poses_3", "a"]
  with pytest.raises(ValueError, match=r"names\[0\]: 'POSES' is reserved"):
    multiway_outputs.check_names(["POSES", "b"])


def _recorder(calls):
  def run(src, dst, **kw):
    calls.append(kw)
    return SimpleNamespace(transform=np.eye(4), success=True, reason="", n_inliers=50,
                           overlap=1.0, rmse=0.0)
  return run


def test_voxel_size_is_passed_to_every_pairwise_registration():
  clouds = [np.random.default_rng(k).normal(size=(200, 3)) for k in range(3)]
  for voxel_size in (0, 0.5):
    calls: list[dict] = []
    multiway.register_all(clouds, mr=0.1, pairwise=_recorder(calls), voxel_size=voxel_size,
                          refine=False)
    assert len(calls) == 3 and all(c["voxel_size"] == voxel_size for c in calls)
  calls = []
  multiway.register_all(clouds, mr=0.1, pairwise=_recorder(calls), refine=False)
  assert all("voxel_size" not in c for c in calls)  # None: `register`'s own choice
  with pytest.raises(ValueError, match="voxel_size"):
    multiway.register_all(clouds, mr=0.1, voxel_size=-1.0)


def test_median_mr_is_the_working_resolution_of_uneven_scans():
  """A scan dense near the sensor and sparse far away: the mr is its area-weighted spacing
  (`working_resolution`; `registration_resolution` caps nothing here), as `register` measures
  it, not its mean spacing."""
  from lrf_jax.geometry.resolution import working_resolution
  from lrf_jax.io.cloud import Cloud
  rng = np.random.default_rng(0)
  near = rng.uniform(-1, 1, size=(20000, 3)) * [1, 1, 0.01]
  far = rng.uniform(-30, 30, size=(2000, 3)) * [1, 1, 0.01]
  cloud = Cloud(np.concatenate([near, far]), None, None)
  mr = multiway_pipeline.median_mr([cloud], ["sweep"])
  assert mr == working_resolution(cloud.points).mr


def test_median_mr_of_full_density_scans_is_a_fraction_of_their_extent():
  """Scans sampled more finely than register works (`registration_resolution`): the job's mr
  is the median of their capped resolutions, as `register` measures each."""
  from lrf_jax.geometry import resolution
  from lrf_jax.io.cloud import Cloud
  rng = np.random.default_rng(0)
  scans = [Cloud(rng.uniform(-1, 1, size=(n, 3)) * [s, s, 0.001], None, None)
           for n, s in ((150_000, 1.0), (150_000, 1.5), (120_000, 2.0))]
  floors = [resolution.cloud_extent(c.points) / resolution.MAX_EXTENT_MR for c in scans]
  assert all(resolution.working_resolution(c.points).mr < f for c, f in zip(scans, floors))
  caps = [resolution.registration_resolution(c.points) for c in scans]
  assert all(r.capped and r.mr >= f for r, f in zip(caps, floors))
  caps = [r.mr for r in caps]
  assert multiway_pipeline.median_mr(scans, ["a", "b", "c"]) == pytest.approx(np.median(caps),
                                                                     rel=1e-12)


def test_cli_voxel_size_reaches_register_all(tmp_path, monkeypatch, capsys):
  from lrf_jax.cli.register import main
  paths = []
  for k in range(3):
    paths.append(str(tmp_path / f"s{k}.npy"))
    np.save(paths[-1], np.random.default_rng(k).normal(size=(30, 3)))
  seen = {}

  def run(clouds, *, names, **kw):
    seen.update(kw)
    return _result(names, np.tile(np.eye(4), (len(names), 1, 1)), [True] * len(names))
  monkeypatch.setattr(multiway_pipeline, "register_all", run)
  assert main([*paths, "--voxel-size", "0.25", "--quiet"]) == 0
  assert seen["voxel_size"] == 0.25
  monkeypatch.setattr(multiway_pipeline, "register_all", lambda *a, **k: pytest.fail("registered"))
  assert main([*paths, "--voxel-size", "-1", "--quiet"]) == 2
  assert "--voxel-size:" in capsys.readouterr().err


@pytest.mark.data
def test_kitti_dev_sweeps_trajectory(data_root, tmp_path):
  """The six raw dev sweeps, no resolution or voxel given, each sweep with the next (the 5
  consecutive pairs, to keep the test near 30 s; every pair as by default: 0.023 deg, 0.99 cm
  at worst) and the joint ICP: poses.txt within 5 cm and 0.2 deg of poses_DERIVED.txt (pseudo
  ground truth, about 1 cm / 0.1 deg; measured 0.060 deg, 2.05 cm at worst)."""
  folder = data_root / "lidar_kitti00"
  paths = [str(folder / f"{k:06d}.bin") for k in range(6)]
  res = multiway.register_all(paths, seed=0, all_pairs_max=0, loop_candidates=0)
  assert res.in_model.all()
  multiway_outputs.write_outputs(res, [np.zeros((3, 3))] * 6, tmp_path, figures=False)
  ours = np.loadtxt(tmp_path / "poses.txt").reshape(-1, 3, 4)
  truth = np.loadtxt(folder / "poses_DERIVED.txt").reshape(-1, 3, 4)
  for k in range(6):
    rot = ours[k, :, :3] @ truth[k, :, :3].T
    deg = np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1)))
    assert deg < 0.2 and np.linalg.norm(ours[k, :, 3] - truth[k, :, 3]) < 0.05, (k, deg)
