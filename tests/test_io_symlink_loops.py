"""A symbolic link loop given as an input or an output: every reader raises `SymlinkLoopError`
(a ValueError and an OSError with errno ELOOP) naming the path as given, and no output helper
raises a RuntimeError or writes over the link."""

from __future__ import annotations

import errno
import os

import pytest

from lrf_jax import io
from lrf_jax.io import atomic
from lrf_jax.io.validation import SymlinkLoopError, file_problem

READERS = [io.read_cloud, io.read_ply, io.read_npy, io.read_xyz, io.read_pcd, io.read_kitti_bin,
           io.read_xf, io.read_stanford_conf, io.read_3dmatch_log]


@pytest.fixture
def loops(tmp_path, monkeypatch):
  """In a fresh working directory: `loop` and `loop.ply` (links to themselves), and `a` and `b`
  (links to each other)."""
  monkeypatch.chdir(tmp_path)
  os.symlink("loop", "loop")
  os.symlink("loop.ply", "loop.ply")
  os.symlink("b", "a")
  os.symlink("a", "b")
  return tmp_path


@pytest.mark.parametrize("reader", READERS, ids=lambda r: r.__name__)
@pytest.mark.parametrize("path", ["loop", "loop.ply", "a", "./loop.ply"])
def test_every_reader_names_a_symlink_loop(loops, reader, path):
  with pytest.raises(SymlinkLoopError) as e:
    reader(path)
  assert isinstance(e.value, ValueError) and isinstance(e.value, OSError)
  assert e.value.errno == errno.ELOOP and e.value.filename == path
  assert str(e.value) == (f"{path}: file: expected a readable file, found a symbolic link loop "
                          "(ELOOP: too many levels of symbolic links)")


def test_a_path_through_a_looping_folder_says_so(loops):
  with pytest.raises(SymlinkLoopError, match=r"^loop/scan\.ply: .*a path that goes through a "
                                             r"symbolic link loop \(ELOOP"):
    io.read_cloud("loop/scan.ply")
  assert file_problem("loop/scan.ply").startswith("goes through a symbolic link loop")
  assert file_problem("missing.ply") == "no such file"


def test_output_checks_name_a_loop_instead_of_raising(loops):
  assert atomic.loop_problem("loop") == ("is a symbolic link loop (ELOOP: too many levels of "
                                         "symbolic links)")
  assert atomic.loop_problem("new.txt") is None
  assert not atomic.same_file("loop", "other")  # Path.resolve raised RuntimeError here
  assert atomic.output_problem("out.txt", "--out", [("SOURCE", "loop")]) is None
  assert atomic.output_problem("loop", "--out") == (
      "--out: loop is a symbolic link loop (ELOOP: too many levels of symbolic links); expected a "
      "regular file or a new name")
  assert atomic.output_problem("loop/T.txt", "--out").startswith(
      "--out: loop/T.txt goes through a symbolic link loop")


@pytest.mark.parametrize("path", ["loop", "a"])
def test_writing_to_a_loop_is_refused_and_the_link_kept(loops, path):
  with pytest.raises(atomic.OutputPathError, match="is a symbolic link loop") as e:
    with atomic.atomic_write(path) as f:
      f.write(b"x")
  assert e.value.errno == errno.ELOOP and path in str(e.value)
  assert os.path.islink(path)
  assert sorted(os.listdir()) == ["a", "b", "loop", "loop.ply"]  # no temporary file left
