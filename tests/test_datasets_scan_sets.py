"""Scan sets (`lrf_jax.datasets.scan_sets`): each pose layout parses to the same pairs, the
overlap rule keeps and drops what it says, every bad folder is one error naming its file and
line, and a pair's ground truth lays the source onto the target (checked by brute force).

The synthetic folders are one demo mesh cut into pieces by azimuth (each `width` degrees wide,
centred `step` degrees apart around the ring), each piece stored in its own frame: moved by the
inverse of a known seeded pose, which the pose file then gives back."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrf_jax import datasets
from lrf_jax.datasets import scan_sets
from lrf_jax.io.validation import ProjectedRotation


def synthetic_pieces(n: int = 5, width: float = 120.0, step: float = 72.0,
                     seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
  """(pieces in their own frames, (n, 4, 4) poses mapping each into the common frame)."""
  points = datasets.make_demo_mesh("blob", seed)[0][::2]
  azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
  rng = np.random.default_rng(seed)
  pieces, poses = [], []
  for k in range(n):
    gap = (azimuth - k * step + 180.0) % 360.0 - 180.0
    piece = points[np.abs(gap) < width / 2]
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    pose[:3, 3] = rng.uniform(-3, 3, 3)
    inv = np.linalg.inv(pose)
    pieces.append(piece @ inv[:3, :3].T + inv[:3, 3])
    poses.append(pose)
  return pieces, np.stack(poses)


def kitti_lines(poses: np.ndarray) -> str:
  return "".join(" ".join(f"{v:.17g}" for v in p[:3].ravel()) + "\n" for p in poses)


def write_scan_folder(folder: Path, layout: str = "kitti", **kw) -> np.ndarray:
  """A scan folder of `synthetic_pieces(**kw)` in `layout` ("kitti", "3dmatch" or "stanford");
  returns the poses. gt.log lists every pair (i < j)."""
  folder.mkdir(parents=True, exist_ok=True)
  pieces, poses = synthetic_pieces(**kw)
  n = len(pieces)
  if layout == "kitti":
    for k, piece in enumerate(pieces):
      np.save(folder / f"scan{k}.npy", piece)
    (folder / "poses.txt").write_text(kitti_lines(poses))
  elif layout == "3dmatch":
    records = []
    for k, piece in enumerate(pieces):
      np.save(folder / f"cloud_bin_{k}.npy", piece)
    for i in range(n):
      for j in range(i + 1, n):
        t = np.linalg.inv(poses[i]) @ poses[j]  # fragment j onto fragment i
        records.append(f"{i} {j} {n}\n" + "".join(" ".join(f"{v:.12g}" for v in row) + "\n"
                                                  for row in t))
    (folder / "gt.log").write_text("".join(records))
  else:
    lines = []
    for k, piece in enumerate(pieces):
      np.save(folder / f"part{k}.npy", piece)
      qx, qy, qz, qw = Rotation.from_matrix(poses[k][:3, :3].T).as_quat()  # world = R(q)ᵀ p + t
      t = poses[k][:3, 3]
      lines.append(f"bmesh part{k}.npy " + " ".join(f"{v:.17g}" for v in (*t, qx, qy, qz, qw))
                   + "\n")
    (folder / "scans.conf").write_text("camera 0 0 0 0 0 0 1\n" + "".join(lines))
  return poses


@pytest.fixture(scope="module")
def kitti_set(tmp_path_factory):
  folder = tmp_path_factory.mktemp("sets") / "ring"
  poses = write_scan_folder(folder)
  return datasets.read_scan_set(folder, use_cache=False), poses


def test_pose_layouts_give_the_same_pairs_and_ground_truth(tmp_path, kitti_set):
  ring, poses = kitti_set
  assert ring.format == "kitti" and ring.name == "ring"
  assert ring.scans == tuple(f"scan{k}.npy" for k in range(5))
  np.testing.assert_allclose(ring.poses, poses, atol=1e-12)
  expected = {p.meta["scan_index"]: p.transform for p in ring.pairs}
  for layout in ("3dmatch", "stanford"):
    write_scan_folder(tmp_path / layout, layout)
    other = datasets.read_scan_set(tmp_path / layout, use_cache=False)
    assert other.format == layout
    got = {p.meta["scan_index"]: p.transform for p in other.pairs}
    if layout == "3dmatch":  # record "i j" (i < j): fragment j (source) onto fragment i
      got = {(i, j): np.linalg.inv(t) for (j, i), t in got.items()}
    assert set(got) == set(expected), layout
    for ij, t in got.items():
      np.testing.assert_allclose(t, expected[ij], atol=1e-6, err_msg=f"{layout} {ij}")
  # each pair's transform is inv(P_target) @ P_source: source i onto target j
  for p in ring.pairs:
    i, j = p.meta["scan_index"]
    np.testing.assert_allclose(p.transform, np.linalg.inv(poses[j]) @ poses[i], atol=1e-9)


def test_pair_transform_lays_the_source_onto_the_target_brute_force(kitti_set):
  ring, _ = kitti_set
  pair = ring.pairs[0]
  moved = pair.model_points @ pair.transform[:3, :3].T + pair.transform[:3, 3]
  rng = np.random.default_rng(1)
  sample = moved[rng.choice(len(moved), 300, replace=False)]
  d = np.sqrt(((sample[:, None, :] - pair.scene_points[None]) ** 2).sum(-1)).min(axis=1)
  # the pieces share the mesh's vertices: where they overlap, a source point IS a target point
  assert np.mean(d < 1e-9) > 0.3
  # the inverse (the usual mistake) lays almost nothing onto the target
  inv = np.linalg.inv(pair.transform)
  wrong = pair.model_points[:300] @ inv[:3, :3].T + inv[:3, 3]
  d_wrong = np.sqrt(((wrong[:, None, :] - pair.scene_points[None]) ** 2).sum(-1)).min(axis=1)
  assert np.mean(d_wrong < 2 * pair.mr) < 0.05


def test_pairs_carry_the_protocol_fields(kitti_set):
  ring, _ = kitti_set
  pair = ring.pairs[0]
  assert pair.dataset == "ring" and pair.correspondence == "nearest"
  assert pair.name == "scan0->scan1" and pair.meta["scans"] == ("scan0.npy", "scan1.npy")
  np.testing.assert_array_equal(pair.model_viewpoint, np.zeros(3))  # KITTI layout: the origin
  assert pair.mr_definition == "mean_nn_distance"
  assert 0.015 < pair.mr < 0.025  # the demo mesh's vertices [::2]: about 0.019
  assert pair.meta["thinned_voxel"] == (0.0, 0.0)  # an even cloud is never thinned


def test_overlap_rule_keeps_the_ring_neighbours_only(kitti_set):
  ring, _ = kitti_set
  # pieces 120 deg wide, 72 deg apart: neighbours share 48 / 120 = 40 % of a piece, the others 0
  kept = sorted(p.meta["scan_index"] for p in ring.pairs)
  assert kept == [(0, 1), (0, 4), (1, 2), (2, 3), (3, 4)]
  assert len(ring.candidates) == 10
  for i, j, f in ring.candidates:
    if (i, j) in kept:
      assert 0.35 < f < 0.5, (i, j, f)
    else:
      assert f < 0.05, (i, j, f)


def test_a_pair_below_thirty_percent_is_left_out(tmp_path):
  # 90 deg wide, 72 deg apart: neighbours share 18 / 90 = 20 % (plus the 2 mr band) < 30 %
  write_scan_folder(tmp_path / "thin", n=5, width=90.0)
  with pytest.raises(ValueError, match=r"30%.*largest is 2\d\.\d%"):
    datasets.read_scan_set(tmp_path / "thin", use_cache=False)
  low = datasets.read_scan_set(tmp_path / "thin", min_overlap=0.15, use_cache=False)
  assert sorted(p.meta["scan_index"] for p in low.pairs) == [(0, 1), (0, 4), (1, 2), (2, 3),
                                                               (3, 4)]
  assert all(0.18 < p.meta["overlap"] < 0.3 for p in low.pairs)


def test_overlap_is_deterministic_and_measured_on_a_subsample(kitti_set):
  ring, _ = kitti_set
  pair = ring.pairs[0]
  a = scan_sets.overlap(pair.model_points, pair.scene_points, pair.transform, 2 * pair.mr)
  b = scan_sets.overlap(pair.model_points, pair.scene_points, pair.transform, 2 * pair.mr)
  full = scan_sets.overlap(pair.model_points, pair.scene_points, pair.transform, 2 * pair.mr,
                           n_points=len(pair.model_points))
  assert a == b == pair.meta["overlap"]
  assert abs(a - full) < 0.03  # 2000 points: within a few percent of the whole cloud's figure


def test_split_by_scan_holds_out_the_last_scans(kitti_set):
  ring, _ = kitti_set
  train, val = datasets.split_by_scan(ring)
  assert [p.meta["scan_index"] for p in val] == [(3, 4)]
  assert sorted(p.meta["scan_index"] for p in train) == [(0, 1), (1, 2)]


def test_training_correspondences_are_ground_truth_neighbours(kitti_set):
  ring, _ = kitti_set
  pair = ring.pairs[0]
  mi, si = datasets.training_correspondences(pair)
  assert len(mi) > 1000 and len(np.unique(si)) == len(si) and np.all(np.diff(mi) > 0)
  gap = np.linalg.norm(pair.model_in_scene()[mi] - pair.scene_points[si], axis=1)
  assert gap.max() <= 0.5 * pair.mr
  excluded, _ = datasets.repeatability_keypoints(pair, 1000, 0)
  assert not np.intersect1d(mi, excluded).size


def test_scans_without_a_pose_and_ignored_files(tmp_path):
  folder = tmp_path / "seq"
  poses = write_scan_folder(folder)
  (folder / "README.md").write_text("my scans")
  (folder / "notes.txt").write_text("not a scan")  # .txt is a cloud suffix, but a minority here
  lines = kitti_lines(poses).splitlines()
  lines[2] = " ".join(["nan"] * 12)
  (folder / "poses.txt").write_text("# my trajectory\n" + "\n".join(lines) + "\n\n")
  s = datasets.read_scan_set(folder, use_cache=False)
  assert s.ignored == ("README.md", "notes.txt")
  assert all(2 not in p.meta["scan_index"] for p in s.pairs) and len(s.pairs) == 3
  assert "scan2.npy" in s.notes[0]
  assert np.isnan(s.poses[2]).all()


def test_poses_off_orthonormal_are_projected_with_one_warning(tmp_path):
  folder = tmp_path / "rough"
  poses = write_scan_folder(folder)
  rough = poses.copy()
  rough[:, :3, :3] *= 1.0004  # as 3DMatch's printed gt.log: about 8e-4 off orthonormal
  (folder / "poses.txt").write_text(kitti_lines(rough))
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    s = datasets.read_scan_set(folder, use_cache=False)
  projected = [w for w in caught if issubclass(w.category, ProjectedRotation)]
  assert len(projected) == 1 and "5 pose(s)" in str(projected[0].message)
  r = s.poses[1][:3, :3]
  np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)


def _error(folder: Path, exc=ValueError) -> str:
  with pytest.raises(exc) as info:
    datasets.read_scan_set(folder, use_cache=False)
  return str(info.value)


def test_folder_without_a_pose_file_is_named(tmp_path):
  folder = tmp_path / "bare"
  write_scan_folder(folder)
  (folder / "poses.txt").unlink()
  msg = _error(folder, FileNotFoundError)
  assert str(folder) in msg and "poses.txt" in msg and "gt.log" in msg and ".conf" in msg


def test_two_pose_files_are_refused(tmp_path):
  folder = tmp_path / "two"
  write_scan_folder(folder)
  (folder / "gt.log").write_text("")
  msg = _error(folder)
  assert "poses.txt" in msg and "gt.log" in msg


def test_pose_count_other_than_the_scan_count_is_named(tmp_path):
  folder = tmp_path / "short"
  poses = write_scan_folder(folder)
  (folder / "poses.txt").write_text(kitti_lines(poses[:4]))
  msg = _error(folder)
  assert "poses.txt: lines: expected 5 poses" in msg and "found 4" in msg and "scan0.npy" in msg


@pytest.mark.parametrize("line,fragment", [
    ("1 0 0 0 0 1 0 0 0 0 1", "line 3: expected 12 numbers"),
    ("1 0 0 0 0 1 0 0 0 0 1 x", "line 3: expected 12 numbers"),
    ("1 0 0 0 0 1 0 0 0 0 1 nan", "line 3: expected 12 finite numbers"),
    ("2 0 0 0 0 1 0 0 0 0 1 0", "line 3: expected an orthonormal rotation block"),
])
def test_malformed_pose_line_names_file_and_line(tmp_path, line, fragment):
  folder = tmp_path / "bad"
  poses = write_scan_folder(folder)
  lines = kitti_lines(poses).splitlines()
  lines[2] = line
  (folder / "poses.txt").write_text("\n".join(lines) + "\n")
  msg = _error(folder)
  assert str(folder / "poses.txt") in msg and fragment in msg


def test_gt_log_records_of_absent_fragments_are_skipped_and_bad_records_named(tmp_path):
  folder = tmp_path / "frag"
  write_scan_folder(folder, "3dmatch")
  (folder / "cloud_bin_4.npy").unlink()
  s = datasets.read_scan_set(folder, use_cache=False)
  assert sorted(p.meta["scan_index"] for p in s.pairs) == [(1, 0), (2, 1), (3, 2)]
  assert "4 of 10 records" in s.notes[0]
  assert s.pairs[0].name == "cloud_bin_1->cloud_bin_0"  # "i j": fragment j onto fragment i
  (folder / "gt.log").write_text("0 1 5\n1 0 0 0\n0 1 0 0\n0 0 1 0\n")
  assert "gt.log" in _error(folder) and "truncated" in _error(folder)


def test_conf_naming_an_absent_scan_is_named(tmp_path):
  folder = tmp_path / "conf"
  write_scan_folder(folder, "stanford")
  (folder / "part3.npy").unlink()
  msg = _error(folder, FileNotFoundError)
  assert "scans.conf" in msg and "part3.npy" in msg


def test_natural_name_order():
  names = ["scan10.ply", "scan2.ply", "scan1.ply", "000010.bin", "000002.bin"]
  assert sorted(names, key=scan_sets.natural_key) == ["000002.bin", "000010.bin", "scan1.ply",
                                                      "scan2.ply", "scan10.ply"]
  assert scan_sets.cloud_suffix("a.TXT.gz") == ".txt.gz" and scan_sets.cloud_suffix("a.log") is None
  assert scan_sets.cloud_suffix("n.pcd.bin") is None


def test_uneven_cloud_is_thinned_to_its_working_resolution_and_cached_on_disk(tmp_path):
  # a sweep-like cloud: a dense disc near the sensor, a sparse ring far away
  rng = np.random.default_rng(0)
  near = np.c_[rng.uniform(-2, 2, (40000, 2)), np.zeros(40000)]
  far = np.c_[rng.uniform(-40, 40, (6000, 2)), rng.uniform(-0.01, 0.01, 6000)]
  path = tmp_path / "sweep.npy"
  np.save(path, np.concatenate([near, far]))
  datasets.clear_cache()
  scan = datasets.load_scan(path, cache_dir=tmp_path / "cache")
  assert scan.resolution.uneven and scan.voxel > 0 and scan.raw_count == 46000
  assert len(scan.points) < 20000 and scan.faces is None
  assert scan.resolution.mr > 3 * scan.resolution.mean_spacing
  assert len(list((tmp_path / "cache" / "scans").glob("*.npz"))) == 1
  datasets.clear_cache()
  again = datasets.load_scan(path, cache_dir=tmp_path / "cache")  # from the .npz
  np.testing.assert_array_equal(again.points, scan.points)
  assert again.resolution == scan.resolution and not again.points.flags.writeable


def test_bunny_conf_folder_gives_the_bunny_loaders_pairs(data_root, tmp_path):
  s = datasets.read_scan_set(data_root / "stanford_bunny_scans", cache_dir=tmp_path)
  assert s.format == "stanford" and s.ignored == ("SOURCE.txt",)
  bunny = {p.name: p for p in datasets.load_bunny_pairs(data_root)}
  ours = {p.name: p for p in s.pairs}
  p, q = ours["bun000->bun045"], bunny["bun000->bun045"]
  np.testing.assert_allclose(p.transform, q.transform, atol=1e-12)
  assert p.mr == pytest.approx(q.mr, rel=1e-12) and p.model_viewpoint is None
  assert 0.85 < p.meta["overlap"] < 0.95


@pytest.mark.parametrize("text,expected", [("0 0 1\n", [0.0, 0.0, 1.0]),
                                           ("# the sensor\nnone\n", None)])
def test_viewpoint_file_sets_every_pairs_sensor_position(tmp_path, text, expected):
  folder = tmp_path / "vp"
  write_scan_folder(folder, "stanford")
  assert datasets.read_scan_set(folder, use_cache=False).pairs[0].model_viewpoint is None
  (folder / "viewpoint.txt").write_text(text)
  s = datasets.read_scan_set(folder, use_cache=False)
  assert "viewpoint.txt" not in s.ignored
  for p in s.pairs:
    for got in (p.model_viewpoint, p.scene_viewpoint):
      if expected is None:
        assert got is None
      else:
        np.testing.assert_array_equal(got, expected)


def test_bad_viewpoint_file_is_named(tmp_path):
  folder = tmp_path / "vp"
  write_scan_folder(folder)
  (folder / "viewpoint.txt").write_text("0 0\n")
  msg = _error(folder)
  assert "viewpoint.txt: viewpoint: expected 3 finite numbers" in msg


def test_disk_cache_keeps_only_figures_of_an_even_scan_and_heals_a_damaged_file(tmp_path):
  path = tmp_path / "scan.npy"
  np.save(path, synthetic_pieces(n=1)[0][0])
  cache = tmp_path / "cache"
  datasets.clear_cache()
  first = datasets.load_scan(path, cache_dir=cache)
  (stored,) = (cache / "scans").glob("*.npz")
  with np.load(stored) as f:
    assert "points" not in f.files and float(f["voxel"]) == 0.0  # the file is read again
  stored.write_bytes(b"not an npz")  # damaged: measured again and replaced
  datasets.clear_cache()
  again = datasets.load_scan(path, cache_dir=cache)
  np.testing.assert_array_equal(again.points, np.load(path))
  assert again.resolution == first.resolution
  with np.load(stored) as f:
    assert float(f["resolution"][0]) == first.resolution.mr
