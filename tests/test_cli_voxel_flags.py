"""The voxel flags of the command-line programs (0.9: "one voxel flag per meaning, named by its
unit"): `--voxel-size` thins clouds in cloud units (lrf-register, its multiway form, lrf-frames,
lrf-batch), `--keypoint-voxel-mr` picks one keypoint per voxel of S mr (lrf-frames, lrf-batch
frames; `--voxel-mr` before 0.9) and `--merge-voxel-mr` thins merged.ply by voxels of S mr (the
multiway form; `--voxel` before 0.9). The old names are further names of the same flags for
this release: they parse to the same option, give the same result, show in the help, and a
message names the flag as the user typed it. Everything here is cheap (a few small clouds; no
registration runs)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from lrf_jax.cli import batch as batch_cli
from lrf_jax.cli import frames as frames_cli
from lrf_jax.cli import multiway as multiway_cli
from lrf_jax.cli import register as register_cli
from lrf_jax.cli.options import TYPED_FLAGS, as_typed
from tests.lrf_testing import cli_error

# Each renamed flag: (its name, its old name, the dest both set).
RENAMED = (("--keypoint-voxel-mr", "--voxel-mr", "voxel_mr"),
           ("--merge-voxel-mr", "--voxel", "merge_voxel_mr"))
OLD_NAMES = {old: new for new, old, _ in RENAMED}


def _batch_parser(job: str) -> argparse.ArgumentParser:
  sub = next(a for a in batch_cli.build_parser()._actions
             if isinstance(a, argparse._SubParsersAction))
  return sub.choices[job]


PARSERS = {"lrf-frames": frames_cli.build_parser, "lrf-register": register_cli.build_parser,
           "lrf-register (multiway)": multiway_cli.build_parser,
           "lrf-batch frames": lambda: _batch_parser("frames"),
           "lrf-batch register": lambda: register_cli.build_parser(suppress_defaults=True),
           "lrf-batch": batch_cli.build_parser}


@pytest.mark.parametrize("program", sorted(PARSERS))
def test_every_voxel_flag_names_its_unit_and_its_old_name(program):
  """Each voxel flag is `--voxel-size` (cloud units) or ends in `-voxel-mr` (mr); its other
  names are the old names of 0.9's renames, and its help says so."""
  ap = PARSERS[program]()
  voxel = [a for a in ap._actions if any("voxel" in s for s in a.option_strings)]
  assert voxel or program == "lrf-batch"
  for action in voxel:
    name, *aliases = action.option_strings
    assert name == "--voxel-size" or name.endswith("-voxel-mr"), (program, name)
    for old in aliases:
      assert OLD_NAMES[old] == name, (program, old)
      assert f"old name: {old}" in " ".join(action.help.split()), (program, action.help)
  help_text = " ".join(ap.format_help().split())
  for new, old, _ in RENAMED:
    if new in help_text:
      assert f"{new} S, {old} S" in help_text, program


@pytest.mark.parametrize("build,argv,new,old,dest", [
    (frames_cli.build_parser, ["c.ply", "--out", "f.npz"], *RENAMED[0]),
    (lambda: _batch_parser("frames"), ["c.ply", "--out", "o"], *RENAMED[0]),
    (multiway_cli.build_parser, ["a", "b", "c", "--out-dir", "d"], *RENAMED[1])])
def test_the_new_and_the_old_name_set_the_same_option(build, argv, new, old, dest):
  given = {}
  for flag in (new, old, f"{old}=0.5"):
    extra = [flag] if "=" in flag else [flag, "0.5"]
    args = vars(build().parse_args([*argv, *extra]))
    assert args.pop(TYPED_FLAGS) == {new: flag.split("=")[0]}
    given[flag] = args
  assert given[new] == given[old] == given[f"{old}=0.5"] and given[new][dest] == 0.5
  assert TYPED_FLAGS not in vars(build().parse_args(argv))  # neither given


def test_the_frames_jobs_table_of_flags_is_lrf_frames():
  """`items.FRAMES_OPTIONS` (keyword -> flag) names each keyword's flag as lrf-frames has it."""
  from lrf_jax.batch.items import FRAMES_OPTIONS
  from lrf_jax.batch.scan_frames import frame_flag
  ap = frames_cli.build_parser()
  for keyword, flag in FRAMES_OPTIONS.items():
    assert frame_flag(keyword) == flag and ap._option_string_actions[flag].dest == keyword


def test_a_message_names_the_flag_as_typed():
  args = frames_cli.build_parser().parse_args(["c.ply", "--out", "f", "--voxel-mr", "3"])
  message = "--keypoint-voxel-mr and --keypoints: give one (--keypoint-voxel-mr picks ...)"
  assert as_typed(message, args) == "--voxel-mr and --keypoints: give one (--voxel-mr picks ...)"
  assert as_typed("--keypoint-voxel-mrs: --voxel-size", args) == "--keypoint-voxel-mrs: --voxel-size"
  new = frames_cli.build_parser().parse_args(["c.ply", "--out", "f", "--keypoint-voxel-mr", "3"])
  assert as_typed(message, new) == message
  assert as_typed(message, argparse.Namespace()) == message


@pytest.mark.parametrize("flag", ["--keypoint-voxel-mr", "--voxel-mr"])
@pytest.mark.parametrize("extra,fragment", [
    (["0.01"], "{flag}: 0.01 mr is below 0.1 mr"),
    (["-1"], "{flag}: expected a positive number"),
    (["5", "--keypoints", "10"], "{flag} and --keypoints: give one of them ({flag} picks")])
def test_lrf_frames_and_lrf_batch_frames_name_the_flag_typed(cloud_npy, tmp_path, capsys, flag,
                                                             extra, fragment):
  fragment = fragment.format(flag=flag)
  assert frames_cli.main([str(cloud_npy), "--out", str(tmp_path / "f.npz"), flag, *extra]) == 2
  err = cli_error(capsys)
  assert fragment in err, err
  other = "--voxel-mr" if flag == "--keypoint-voxel-mr" else "--keypoint-voxel-mr"
  assert other not in err, err
  assert batch_cli.main(["frames", str(cloud_npy), "--out", str(tmp_path / "b"), "--no-progress",
                         flag, *extra]) == 2
  err = cli_error(capsys)
  assert fragment in err and other not in err, err
  assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("flag", ["--merge-voxel-mr", "--voxel"])
def test_multiway_names_the_flag_typed(tmp_path, capsys, flag):
  scans = [str(tmp_path / f"{k}.npy") for k in "abc"]  # not read: refused before
  assert register_cli.main([*scans, "--out-dir", str(tmp_path / "m"), flag, "-1"]) == 2
  err = cli_error(capsys)
  assert err.startswith(f"error: {flag}: expected a positive number"), err


def test_lrf_frames_and_lrf_batch_frames_give_the_same_keypoints_under_either_name(
    cloud_npy, tmp_path):
  """`--keypoint-voxel-mr 5` and `--voxel-mr 5`: the same .npz, from lrf-frames and from
  lrf-batch frames."""
  common = ["--method", "toldi", "--radius-mr", "5"]
  assert frames_cli.main([str(cloud_npy), "--out", str(tmp_path / "new.npz"),
                          "--keypoint-voxel-mr", "5", *common]) == 0
  assert frames_cli.main([str(cloud_npy), "--out", str(tmp_path / "old.npz"),
                          "--voxel-mr", "5", *common]) == 0
  assert batch_cli.main(["frames", str(cloud_npy), "--out", str(tmp_path / "batch"),
                         "--no-progress", "--voxel-mr", "5", *common]) == 0
  new, old = np.load(tmp_path / "new.npz"), np.load(tmp_path / "old.npz")
  batch = np.load(tmp_path / "batch" / "scan.npz")
  n = len(np.load(cloud_npy))
  assert 5 < len(new["keypoints"]) < n // 2  # the voxels picked the keypoints
  for other in (old, batch):
    assert sorted(other.files) == sorted(new.files)
    for key in new.files:
      assert np.array_equal(new[key], other[key]), key


def test_multiway_writes_the_same_merged_model_under_either_name(tmp_path, monkeypatch):
  """`--merge-voxel-mr 1` and `--voxel 1`: the same merged.ply, thinned (`register_all`
  replaced by identity poses at mr 1: the outputs are under test)."""
  from lrf_jax import multiway
  from lrf_jax.multiway import pipeline

  def run(clouds, *, names, **kw):
    n = len(names)
    return multiway.MultiwayResult(names=tuple(names), poses=np.tile(np.eye(4), (n, 1, 1)),
                                   in_model=np.ones(n, bool), reference=0, edges=(), mr=1.0,
                                   seconds=0.0)
  monkeypatch.setattr(pipeline, "register_all", run)
  scans = []
  for k in range(3):
    scans.append(str(tmp_path / f"s{k}.npy"))
    np.save(scans[-1], np.random.default_rng(k).normal(size=(30, 3)))
  merged = {}
  for flag in ("--merge-voxel-mr", "--voxel", None):
    out = tmp_path / f"model{flag}"
    voxel = [] if flag is None else [flag, "1"]
    assert register_cli.main([*scans, "--out-dir", str(out), "--quiet", "--no-figures",
                              *voxel]) == 0
    merged[flag] = (out / "merged.ply").read_bytes()
  assert merged["--merge-voxel-mr"] == merged["--voxel"] != merged[None]
  assert len(merged["--voxel"]) < len(merged[None])  # fewer points


def test_a_shortened_flag_is_refused_not_read_as_another():
  """`lrf-register a b --voxel 1` (two scans) was read as `--voxel-size 1` (argparse's
  abbreviations): a merged-model voxel in mr taken as a thinning voxel in cloud units. Every
  program now refuses a flag it does not spell out."""
  import pytest
  from lrf_jax.cli import batch, frames, register
  for parser, argv in ((register.build_parser(), ["a.ply", "b.ply", "--voxel", "1"]),
                       (frames.build_parser(), ["a.ply", "--keypoint", "10"]),
                       (batch.build_parser(), ["register", "p.tsv", "--out", "o", "--voxel",
                                               "1"])):
    with pytest.raises(SystemExit):
      parser.parse_args(argv)
