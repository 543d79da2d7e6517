"""Training on scan sets (`lrf_jax.learning.data_sources`, `TrainConfig.scans`): the overrides,
the split into training and validation pairs, the training keypoints' correspondences, and
train.py end to end on a tiny synthetic folder (checkpoints, metrics, resume)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import datasets
from lrf_jax.learning import config as config_lib
from lrf_jax.learning import data_sources
from tests.lrf_testing import cli_error
from tests.test_datasets_scan_sets import write_scan_folder

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import train  # noqa: E402


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
  """Two synthetic scan sets: "ring" (5 scans, KITTI layout) and "frags" (gt.log)."""
  base = tmp_path_factory.mktemp("scans")
  write_scan_folder(base / "ring")
  write_scan_folder(base / "frags", "3dmatch", seed=1)
  return base


def _config(**overrides) -> config_lib.TrainConfig:
  return config_lib.replace(config_lib.load_config("smoke"), **overrides)


def test_scans_override_alone_trains_on_the_scans(folders):
  cfg = _config(**config_lib.parse_overrides([f"scans={folders / 'ring'},{folders / 'frags'}"]))
  assert cfg.data == "scans" and cfg.scans == (str(folders / "ring"), str(folders / "frags"))
  mixed = config_lib.replace(config_lib.load_config("default"),
                             **config_lib.parse_overrides(["data=br+scans", "scans=a"]))
  assert mixed.data == "br+scans" and mixed.scans == ("a",)
  again = config_lib.replace(mixed, scans="b")  # a config that reads scans keeps its data
  assert again.data == "br+scans"
  from_json = config_lib.TrainConfig.from_dict({"scans": ["a"]})
  assert from_json.data == "scans" and from_json.scans == ("a",)


@pytest.mark.parametrize("overrides,fragment", [
    (dict(data="scans"), "config.scans"),
    (dict(data="br", scans="a"), "config.scans: given"),
    (dict(data="demo", val_scans="a"), "config.val_scans: given"),
    (dict(scans="a,b", val_scans="b"), "config.val_scans"),
    (dict(scans="a", scan_share="1.5"), "config.scan_share"),
    (dict(data="mine"), "config.data"),
])
def test_inconsistent_scan_fields_are_named(overrides, fragment):
  with pytest.raises(ValueError, match=fragment):
    _config(**overrides)


def test_split_one_folder_by_scan_several_by_folder(folders):
  ring, frags = str(folders / "ring"), str(folders / "frags")
  train_pairs, val = data_sources.scan_split(_config(scans=ring))
  assert [p.meta["scan_index"] for p in val] == [(3, 4)]
  assert {p.dataset for p in train_pairs} == {"ring"}
  assert not {p.meta["scan_index"] for p in train_pairs} & {(3, 4), (0, 4)}
  train_pairs, val = data_sources.scan_split(_config(scans=f"{ring},{frags}"))
  assert {p.dataset for p in train_pairs} == {"ring"} and len(train_pairs) == 5
  assert {p.dataset for p in val} == {"frags"}
  train_pairs, val = data_sources.scan_split(_config(scans=ring, val_scans=frags))
  assert len(train_pairs) == 5 and {p.dataset for p in val} == {"frags"}
  train_pairs, val = data_sources.scan_split(_config(scans=f"{ring},{frags}", val_pairs=0))
  assert len(train_pairs) == 10 and val == []
  assert "held-out scan set(s)" in data_sources.validation_label(_config(scans=f"{ring},{frags}"))
  assert len(data_sources.validation_pairs(_config(scans=ring, val_scans=frags,
                                                   val_pairs=2))) == 2


def test_training_keypoints_of_scans_correspond_under_the_ground_truth(folders):
  cfg = _config(scans=str(folders / "ring"), val_pairs=0, num_train_keypoints=3000)
  clouds = data_sources.training_clouds(cfg)
  pairs = data_sources.scan_split(cfg)[0]
  assert len(clouds.models) == len(pairs) == 5 and len(clouds.keypoints) == 3000
  assert len({int(c) for c in clouds.keypoints[:, 0]}) == 5  # drawn over every pair
  # scans alone: every pair scaled to mr 1 / radius_mr (a support radius of 1)
  np.testing.assert_allclose(clouds.mr, 1.0 / cfg.radius_mr)
  np.testing.assert_allclose(clouds.radii, 1.0)
  for c, pair in enumerate(pairs):
    scale = clouds.mr[c] / pair.mr
    # each side is its cloud reordered and scaled: the same points
    for got, want in ((clouds.models[c], pair.model_points), (clouds.scenes[c], pair.scene_points)):
      assert got.shape == want.shape
      np.testing.assert_allclose(np.unique(got / scale, axis=0), np.unique(want, axis=0),
                                 rtol=1e-12, atol=1e-12)
    rows = clouds.keypoints[clouds.keypoints[:, 0] == c, 1]
    moved = datasets.transform_points(pair.transform, clouds.models[c][rows] / scale)
    gap = np.linalg.norm(moved - clouds.scenes[c][rows] / scale, axis=1)
    assert gap.max() <= 0.5 * pair.mr * (1 + 1e-9)


def test_more_keypoints_than_corresponding_points_is_one_clear_error(folders):
  cfg = _config(scans=str(folders / "ring"), val_pairs=0, num_train_keypoints=10**6,
                batch_size=64)
  with pytest.raises(ValueError, match="lower num_train_keypoints"):
    data_sources.training_clouds(cfg)


def test_br_and_scans_mix_by_scan_share(folders, data_root, monkeypatch, tmp_path):
  monkeypatch.setenv("LRF_CACHE", str(tmp_path))
  cfg = config_lib.replace(config_lib.load_config("smoke"), data="br+scans",
                           scans=str(folders / "ring"), data_root=str(data_root),
                           num_train_keypoints=1000, scan_share=0.25)
  clouds = data_sources.training_clouds(cfg)
  assert len(clouds.models) == 18 + 2  # BR's noise-free pairs, then the ring's training pairs
  on_scans = clouds.keypoints[:, 0] >= 18
  assert on_scans.sum() == 250 and len(clouds.keypoints) == 1000
  # the scans scaled to BR's median mr: the Chamfer loss weighs both sources alike
  np.testing.assert_allclose(clouds.mr[18:], np.median(clouds.mr[:18]))
  assert 1e-4 < clouds.mr[0] < 3e-3  # BR in metres, as stored (mean edge lengths of 0.5-1.5 mm)
  assert clouds.names[0].startswith("Scene") and clouds.names[-1].startswith("ring/")


def test_train_py_trains_resumes_and_validates_on_a_scan_set(folders, tmp_path, capsys,
                                                             monkeypatch):
  monkeypatch.setenv("LRF_CACHE", str(tmp_path / "cache"))
  work = tmp_path / "run"
  args = ["--config", "smoke", "--workdir", str(work), "--no-progress",
          f"scans={folders / 'ring'}", "num_train_keypoints=128", "log_every=1"]
  assert train.main(args + ["epochs=1"]) == 0
  cfg = json.loads((work / "config.json").read_text())
  assert cfg["data"] == "scans" and cfg["scans"] == [str(folders / "ring")]
  rows = [json.loads(line) for line in (work / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows] == [1, 2] and rows[-1]["val_per_pair"].keys() == {"scan3->scan4"}
  assert 0.0 < rows[-1]["val_meancos"] <= 1.0 and np.isfinite(rows[-1]["loss"])
  for name in ("curves.png", "final_params.msgpack", "best_params.msgpack"):
    assert (work / name).is_file(), name
  capsys.readouterr()
  # the same run, one epoch longer: resumed from its checkpoint (another config is refused)
  assert train.main(args + ["epochs=1", "batch_size=32"]) == 2
  assert "another config" in cli_error(capsys)
  assert train.main(args + ["epochs=2", "--replace-config"]) == 0
  assert "resuming from step 2" in capsys.readouterr().err
  rows = [json.loads(line) for line in (work / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in rows if "loss" in r] == [1, 2, 3, 4]


def test_train_py_names_a_folder_without_poses(tmp_path, capsys):
  (tmp_path / "empty").mkdir()
  np.save(tmp_path / "empty" / "a.npy", np.zeros((10, 3)))
  rc = train.main(["--config", "smoke", "--workdir", str(tmp_path / "run"), "--no-progress",
                   f"scans={tmp_path / 'empty'}"])
  assert rc == 2
  msg = cli_error(capsys)
  assert str(tmp_path / "empty") in msg and "poses.txt" in msg
