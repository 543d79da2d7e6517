"""The kernel cache heals instead of failing the run (`lrf_jax.kernel_cache`): an unreadable
entry is set aside and compiled again, a read-only cache is read and what it lacks is saved
elsewhere (never in the package's folder), and a save that fails (a full disk) leaves the kernel
compiled in memory. Each case says so in one line on stderr, and none is an input error.

Every run is a fresh process on one small kernel (`select_correspondences`' occupancy kernel,
compiled in a second or two) with its caches under the test's temporary folder."""

from __future__ import annotations

import contextlib
import errno
import os
import pickle
import shutil
import stat
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import lrf_jax
from lrf_jax import compilation_cache

REPO = Path(__file__).resolve().parents[1]
PACKAGE = Path(lrf_jax.__file__).resolve().parent
KERNEL = "matching._occupancy_knn_kernel"
COMPILING = "lrf_jax: compiling kernels"

pytestmark = pytest.mark.skipif(os.name != "posix", reason="file modes and locks: POSIX")

_RUN = """
import numpy as np
import lrf_jax
from lrf_jax.descriptors import select_correspondences
rng = np.random.default_rng(0)
q = np.where(rng.random((40, 30)) < 0.5, 100.0, rng.random((40, 30))).astype(np.float32)
print(select_correspondences(q, q[::-1], n=10))
"""

_DISK_FULL = """
import errno, os
from numba.core import caching

def fails(self, filepath):
  raise OSError({errno}, os.strerror({errno}), filepath)

caching.IndexDataCacheFile._open_for_write = fails  # every write of the cache fails
"""


def _run(cache: Path, home: Path, prelude: str = "", prefix: tuple[str, ...] = (),
         **extra: str) -> subprocess.CompletedProcess:
  """The kernel in a fresh process with NUMBA_CACHE_DIR `cache` and its other caches (the
  fallbacks among them) under `home`; `extra`: more environment variables."""
  env = {k: v for k, v in os.environ.items()
         if k not in ("NUMBA_CACHE_DIR", "LRF_JAX_CACHE_DIR", "XDG_CACHE_HOME")}
  (home / "tmp").mkdir(parents=True, exist_ok=True)
  env.update(NUMBA_CACHE_DIR=str(cache), XDG_CACHE_HOME=str(home / "xdg"),
             TMPDIR=str(home / "tmp"), LRF_JAX_PARALLEL_COMPILE="0",
             PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]),
             **extra)
  script = textwrap.dedent(prelude) + textwrap.dedent(_RUN)
  return subprocess.run([*prefix, sys.executable, "-c", script], env=env, capture_output=True,
                        text=True, timeout=300, cwd=home)


def _notes(stderr: str) -> list[str]:
  """lrf_jax's lines on stderr other than the compile notice."""
  return [line for line in stderr.splitlines()
          if line.startswith("lrf_jax:") and not line.startswith(COMPILING)]


def _files(folder: Path) -> dict[str, int]:
  return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")
          if p.is_file()}


def _package_entries(since: float) -> list[Path]:
  """Entries of the kernel written into the package's own folders since `since`."""
  return [p for p in PACKAGE.rglob(f"{KERNEL}*.nb*") if p.stat().st_mtime >= since]


@pytest.fixture(scope="module")
def warm(tmp_path_factory) -> tuple[Path, str]:
  """A cache holding the kernel, and the output of the run that compiled it."""
  root = tmp_path_factory.mktemp("warm")
  out = _run(root / "cache", root)
  assert out.returncode == 0, out.stderr
  assert COMPILING in out.stderr
  return root / "cache", out.stdout


def _copy(warm_cache: Path, to: Path) -> Path:
  shutil.copytree(warm_cache, to, symlinks=True)
  return to


def _entry(cache: Path, suffix: str) -> Path:
  (path,) = cache.rglob(f"{KERNEL}*{suffix}")
  return path


@pytest.mark.parametrize("damage", ["truncated-index", "garbage-index", "truncated-data",
                                    "data-not-a-kernel"])
def test_an_unreadable_entry_is_set_aside_and_compiled_again(warm, tmp_path, damage):
  """Before: every run failed with UnpicklingError (or worse) until the cache was deleted."""
  cache = _copy(warm[0], tmp_path / "cache")
  path = _entry(cache, ".nbi" if damage.endswith("index") else ".nbc")
  data = path.read_bytes()
  path.write_bytes({"truncated-index": data[:20], "garbage-index": os.urandom(len(data)),
                    "truncated-data": data[:200],
                    "data-not-a-kernel": pickle.dumps(("not", "a", "kernel"))}[damage])
  out = _run(cache, tmp_path)
  assert out.returncode == 0, out.stderr
  assert out.stdout == warm[1]
  notes = _notes(out.stderr)
  assert len(notes) == 1 and str(path) in notes[0] and "unreadable" in notes[0], out.stderr
  assert "could not read" not in out.stderr and "Traceback" not in out.stderr
  assert len(list(path.parent.glob(path.name + ".corrupt-*"))) == 1  # set aside, kept
  assert COMPILING in out.stderr
  again = _run(cache, tmp_path)  # healed: loads, says nothing
  assert again.returncode == 0 and again.stdout == warm[1], again.stderr
  assert COMPILING not in again.stderr and not _notes(again.stderr), again.stderr


def _mount_read_only_works(folder: Path) -> bool:
  probe = folder / "probe"
  probe.mkdir()
  try:
    out = subprocess.run(["unshare", "-m", "sh", "-c",
                          'mount --bind "$0" "$0" && mount -o remount,bind,ro "$0" && '
                          '! touch "$0/x" 2>/dev/null', str(probe)],
                         capture_output=True, timeout=30)
  except (OSError, subprocess.TimeoutExpired):
    return False
  finally:
    shutil.rmtree(probe, ignore_errors=True)
  return out.returncode == 0


@contextlib.contextmanager
def _read_only(cache: Path, scratch: Path) -> Iterator[tuple[str, ...]]:
  """Make `cache` read-only for the runs inside the block; yields the prefix of their command.
  A user's files: `chmod -R a-w`. Root writes whatever the modes say: a read-only bind mount
  in a mount namespace of the run's own (`unshare -m`), where the system allows it."""
  if os.geteuid() == 0:
    if not shutil.which("unshare") or not _mount_read_only_works(scratch):
      pytest.skip("root ignores file modes, and no read-only mount can be made here")
    yield ("unshare", "-m", "sh", "-c", 'mount --bind "$0" "$0" && mount -o remount,bind,ro '
           '"$0" && exec "$@"', str(cache))
    return
  modes = {p: p.stat().st_mode for p in [cache, *cache.rglob("*")]}
  for p, mode in modes.items():
    p.chmod(mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
  try:
    yield ()
  finally:
    for p, mode in modes.items():
      p.chmod(mode)


def test_a_read_only_warm_cache_is_loaded_not_compiled_again(warm, tmp_path):
  """Before: a read-only cache was ignored: every kernel was compiled again (97 s for
  lrf-register) into the package's own folder, silently."""
  cache = _copy(warm[0], tmp_path / "cache")
  before, since = _files(cache), time.time()
  with _read_only(cache, tmp_path) as prefix:
    out = _run(cache, tmp_path, prefix=prefix, NUMBA_DEBUG_CACHE="1")  # numba says what it loads
  assert out.returncode == 0, out.stderr
  loaded = [line for line in out.stdout.splitlines() if "data loaded from" in line]
  assert loaded and all(f"'{cache}{os.sep}" in line for line in loaded), out.stdout
  assert "\n".join(x for x in out.stdout.splitlines() if not x.startswith("[cache]")) + "\n" == \
      warm[1]
  assert COMPILING not in out.stderr and not _notes(out.stderr), out.stderr
  assert _files(cache) == before
  assert not list((tmp_path / "xdg").rglob("*.nbi")) and not list((tmp_path / "tmp").rglob("*.nbi"))
  assert not _package_entries(since)


def test_a_read_only_cache_compiles_what_it_lacks_into_a_fallback_it_names(warm, tmp_path):
  cache = tmp_path / "cache"
  cache.mkdir()
  since = time.time()
  with _read_only(cache, tmp_path) as prefix:
    out = _run(cache, tmp_path, prefix=prefix)
    assert out.returncode == 0, out.stderr
    assert out.stdout == warm[1]
    fallback = tmp_path / "xdg" / "lrf_jax" / "numba"
    notes = _notes(out.stderr)
    assert len(notes) == 1 and str(cache) in notes[0] and str(fallback) in notes[0], out.stderr
    assert list(fallback.rglob(f"{KERNEL}*.nbi"))
    again = _run(cache, tmp_path, prefix=prefix)  # loads from the fallback
  assert again.returncode == 0 and again.stdout == warm[1], again.stderr
  assert COMPILING not in again.stderr and not _notes(again.stderr), again.stderr
  assert not list(cache.iterdir())
  assert not _package_entries(since)


@pytest.mark.parametrize("error", ["ENOSPC", "EIO"])
def test_a_cache_that_cannot_be_written_leaves_the_kernel_compiled_in_memory(warm, tmp_path,
                                                                             error):
  """Before: a full disk under the cache raised OSError out of the computation, which the
  commands reported as "could not read an input"."""
  cache = tmp_path / "cache"
  out = _run(cache, tmp_path, prelude=_DISK_FULL.format(errno=f"errno.{error}"))
  assert out.returncode == 0, out.stderr
  assert out.stdout == warm[1]
  notes = _notes(out.stderr)
  assert len(notes) == 1 and "in memory only" in notes[0], out.stderr
  assert os.strerror(getattr(errno, error)) in notes[0]
  assert "could not read" not in out.stderr and "Traceback" not in out.stderr
  assert not list(cache.rglob("*.nbc"))


def test_a_shared_temporary_folder_is_no_fallback_unless_private(tmp_path, monkeypatch):
  """Kernels are pickles: a fallback in the temporary directory is used only when it is this
  user's folder that no one else may write."""
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file" / "x"))  # cannot be created
  (tmp_path / "file").write_text("")
  monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
  private = tmp_path / f"lrf_jax-{os.getuid()}"
  assert compilation_cache.numba_fallback_dirs(create=True) == [private / "numba"]
  assert stat.S_IMODE(private.stat().st_mode) == 0o700
  private.chmod(0o777)  # writable by anyone: not trusted
  assert compilation_cache.numba_fallback_dirs() == []
  assert compilation_cache.numba_fallback_dirs(create=True) == []
  shutil.rmtree(private)
  private.symlink_to(tmp_path)
  assert compilation_cache.numba_fallback_dirs(create=True) == []


def test_numba_cache_dir_falls_back_when_it_cannot_be_created(tmp_path, monkeypatch):
  """Before: a cache folder that could not be created left NUMBA_CACHE_DIR unset, and numba
  wrote the kernels into the package's own folder."""
  monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
  monkeypatch.delitem(sys.modules, "numba", raising=False)  # keep this process's numba settings
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file" / "x"))
  (tmp_path / "file").write_text("")
  monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
  assert compilation_cache.configure_numba_cache() == str(
      tmp_path / f"lrf_jax-{os.getuid()}" / "numba")
  assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / f"lrf_jax-{os.getuid()}" / "numba")
