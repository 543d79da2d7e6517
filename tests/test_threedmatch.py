"""The 3DMatch fragment-pair reader and the benchmark cases built on the real data's truth."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lrf_jax import datasets
from lrf_jax.datasets import root as root_mod
from lrf_jax.datasets import threedmatch
from lrf_jax.datasets.pair import transform_points
from lrf_jax.io import check_rigid, write_ply, write_xf
from tests.lrf_testing import random_rotation

HEADER = "pair\tscene\tbenchmark\tsource\ttarget\tgt_source_to_target\n"


def _overlap(source, target, transform, radius):
  dist, _ = cKDTree(target).query(transform_points(transform, source), distance_upper_bound=radius)
  return float(np.isfinite(dist).mean())


@pytest.fixture(scope="module")
def scene_pairs(data_root):
  if not (Path(data_root) / threedmatch.FOLDER).is_dir():
    pytest.skip(f"{threedmatch.FOLDER}/ not under the data root")
  return datasets.load_threedmatch_scenes(data_root)


def test_loads_both_pairs(scene_pairs):
  assert [p.name for p in scene_pairs] == ["hotel3_8_15", "home_at_38_41"]
  assert [p.meta["benchmark"] for p in scene_pairs] == ["3DMatch", "3DLoMatch"]
  for p in scene_pairs:
    assert p.dataset == "3DMatch" and p.correspondence == "nearest"
    assert 15_000 < len(p.model_points) < 30_000 and 15_000 < len(p.scene_points) < 30_000
    assert 0.005 < p.mr < 0.025  # metres: 2.5 cm voxels, mean NN distance about 1.2 cm
    check_rigid(p.transform, p.name)


def test_overlap_under_gt_far_above_identity_and_inverse(scene_pairs):
  for p in scene_pairs:
    radius = 3 * p.mr
    under_gt = _overlap(p.model_points, p.scene_points, p.transform, radius)
    assert under_gt > 0.15, p.name
    for other in (np.eye(4), np.linalg.inv(p.transform)):
      assert under_gt > 2.5 * _overlap(p.model_points, p.scene_points, other, radius), p.name


def _write_set(folder: Path, gt: np.ndarray | str, rows: str | None = None) -> Path:
  folder.mkdir(parents=True, exist_ok=True)
  pts = np.random.default_rng(0).uniform(size=(50, 3))
  write_ply(folder / "a.ply", pts)
  write_ply(folder / "b.ply", pts + 0.1)
  if isinstance(gt, str):
    (folder / "gt.txt").write_text(gt)
  else:
    write_xf(folder / "gt.txt", gt)
  (folder / "pairs.tsv").write_text(
      HEADER + (rows if rows is not None else "p\tscene\t3DMatch\ta.ply\tb.ply\tgt.txt\n"))
  return folder


def test_small_set_round_trip(tmp_path):
  gt = np.eye(4)
  gt[:3, :3] = random_rotation(3)
  gt[:3, 3] = [0.1, 0.2, 0.3]
  folder = _write_set(tmp_path / threedmatch.FOLDER, gt)
  for root in (tmp_path, folder):  # the data root or the set's own folder
    (pair,) = datasets.load_threedmatch_scenes(root)
    np.testing.assert_allclose(pair.transform, gt)
    assert pair.name == "p" and pair.meta["files"] == ("a.ply", "b.ply", "gt.txt")


def test_missing_folder_lists_places(tmp_path, monkeypatch):
  monkeypatch.setattr(root_mod, "REPO_DATA", tmp_path / "repo_data")
  monkeypatch.delenv("LRF_DATA", raising=False)
  with pytest.raises(datasets.DataNotFoundError, match=r"threedmatch_scenes not found(.|\n)*"
                     r"repo_data \(does not exist\)(.|\n)*LRF_DATA: not set"):
    datasets.load_threedmatch_scenes()
  with pytest.raises(datasets.DataNotFoundError, match="threedmatch_scenes not found"):
    datasets.load_threedmatch_scenes(tmp_path)


def test_missing_files_are_named(tmp_path):
  folder = _write_set(tmp_path / threedmatch.FOLDER, np.eye(4))
  (folder / "b.ply").unlink()
  with pytest.raises(datasets.DataNotFoundError,
                     match=r"target fragment of p not found at .*b\.ply"):
    datasets.load_threedmatch_scenes(tmp_path)
  (folder / "pairs.tsv").unlink()
  with pytest.raises(datasets.DataNotFoundError, match=r"pairs\.tsv not found"):
    datasets.load_threedmatch_scenes(tmp_path)


@pytest.mark.parametrize("rows, match", [
    ("p\tscene\t3DMatch\ta.ply\tb.ply\n", r"pairs\.tsv: line 2: expected 6 tab-separated fields"),
    ("p\tscene\t3DMatch\ta.ply\t\tgt.txt\n", r"pairs\.tsv: line 2: field target: expected a "
     "value"),
    ("p\tscene\tKITTI\ta.ply\tb.ply\tgt.txt\n", r"pairs\.tsv: line 2: field benchmark: expected "
     r"one of \('3DMatch', '3DLoMatch'\), found 'KITTI'"),
    ("p\ts\t3DMatch\ta.ply\tb.ply\tgt.txt\np\ts\t3DMatch\ta.ply\tb.ply\tgt.txt\n",
     r"pairs\.tsv: line 3: field pair: expected each pair once"),
    ("", r"pairs\.tsv: rows: expected at least one pair"),
])
def test_bad_pairs_row(tmp_path, rows, match):
  _write_set(tmp_path / threedmatch.FOLDER, np.eye(4), rows)
  with pytest.raises(ValueError, match=match):
    datasets.load_threedmatch_scenes(tmp_path)


def test_bad_pairs_header(tmp_path):
  folder = _write_set(tmp_path / threedmatch.FOLDER, np.eye(4))
  (folder / "pairs.tsv").write_text("pair\tsource\ttarget\np\ta.ply\tb.ply\n")
  with pytest.raises(ValueError, match=r"pairs\.tsv: header \(line 1\): expected the "
                     r"tab-separated columns .*missing \['scene', 'benchmark', "
                     r"'gt_source_to_target'\]"):
    datasets.load_threedmatch_scenes(tmp_path)


@pytest.mark.parametrize("text, match", [
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", r"gt\.txt: matrix: expected a 4x4 matrix, found a 3x4"),
    ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"gt\.txt: matrix: expected an orthonormal"),
    ("-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"gt\.txt: matrix: expected det R = \+1.*"
     "reflection"),
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", r"gt\.txt: matrix: expected last row 0 0 0 1"),
])
def test_gt_not_rigid(tmp_path, text, match):
  _write_set(tmp_path / threedmatch.FOLDER, text)
  with pytest.raises(ValueError, match=match):
    datasets.load_threedmatch_scenes(tmp_path)


def test_scene_cases_fold_the_motion_into_gt_and_measure_overlap():
  """The benchmark's cases: the random motion is folded into gt, and a one-fragment pair's
  overlap is in the bin it was drawn for, the source's sensor position moves with it (on a
  synthetic room-like cloud, no data needed)."""
  sc = pytest.importorskip("benchmarks.scene_cases")
  rng = np.random.default_rng(0)
  xy = rng.uniform(0, 3, size=(12_000, 2))
  floor = np.c_[xy, 0.02 * np.sin(3 * xy[:, 0])]
  wall = np.c_[xy[:4000, 0], np.zeros(4000), xy[:4000, 1]]
  points = np.concatenate([floor, wall])
  spacing = sc.spacing_of(points)
  for bin_name in sc.BINS:
    src, dst, _ = sc._fragment_pair(points, spacing, bin_name, np.random.default_rng(1))
    assert sc.overlap_bin(sc.overlap_fraction(src, dst, np.eye(4))) == bin_name
    assert not (cKDTree(dst).query(src)[0] == 0).any()  # noise: no point shared exactly
    sensor = np.array([0.5, 0.5, 1.5])
    case = sc._finish("x", "hotel3", "room", src, dst, np.eye(4), "fragment", {},
                      np.random.default_rng(2), (sensor, sensor))
    check_rigid(case.gt, "case gt")
    # the source's sensor moves with it; the target's stays
    np.testing.assert_allclose(
        transform_points(case.gt, np.array([case.meta["source_viewpoint"]])), [sensor],
        atol=1e-9)
    assert case.meta["target_viewpoint"] == sensor.tolist()
    assert case.split == "tune" and case.unit == 1.0
    np.testing.assert_allclose(transform_points(case.gt, case.source), src, atol=1e-9)
    assert np.linalg.norm(case.source.mean(0) - src.mean(0)) > 1.0  # it did move
    assert case.overlap_bin == bin_name
