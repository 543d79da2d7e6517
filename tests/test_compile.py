"""lrf-compile (`lrf_jax.cli.compile`): exit code 3 when a group failed, Ctrl-C ends the running
workers at once, and a numba cache it cannot write is one error before any work. (Its parallel
compile workers: tests/test_parallel_compile.py.)"""

from __future__ import annotations

import time

import pytest


def test_lrf_compile_exit_code_is_3_when_a_group_failed(monkeypatch, capsys):
  """Before: 1 (the convention: 3 when some items failed, the others done)."""
  import concurrent.futures
  from lrf_jax.cli import compile as compile_cli

  class Threads(concurrent.futures.ThreadPoolExecutor):  # the groups in this process
    def __init__(self, max_workers, mp_context=None):
      super().__init__(max_workers)

  def fails():
    raise ValueError("boom")
  monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", Threads)
  monkeypatch.setattr(compile_cli, "groups", lambda: {"ok": lambda: None, "bad": fails})
  assert compile_cli.main(["--jobs", "1"]) == 3
  assert "error: bad: ValueError: boom" in capsys.readouterr().err


def test_lrf_compile_stop_ends_running_workers_at_once():
  """Before: Ctrl-C sent to lrf-compile alone (kill -INT, a supervisor) waited for the groups in
  flight to finish (245 s seen) before exiting."""
  import multiprocessing as mp
  from concurrent.futures import ProcessPoolExecutor
  from lrf_jax.cli import compile as compile_cli
  pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"))
  fut = pool.submit(time.sleep, 300)
  deadline = time.monotonic() + 60
  while not fut.running() and time.monotonic() < deadline:
    time.sleep(0.1)
  t0 = time.monotonic()
  compile_cli._stop(pool)
  assert time.monotonic() - t0 < 30


def test_lrf_compile_into_a_cache_it_cannot_write_is_one_error_before_the_work(tmp_path,
                                                                                monkeypatch,
                                                                                capsys):
  """Before: with a read-only NUMBA_CACHE_DIR, lrf-compile compiled for 40 s, said "compiled 1
  of 1 groups ... into <that folder>" and exited 0, keeping nothing."""
  from lrf_jax.cli import compile as compile_cli
  blocker = tmp_path / "file"
  blocker.write_text("x")  # a folder under a file cannot be created, even by root
  monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "numba"))
  monkeypatch.setattr(compile_cli, "groups",
                      lambda: {"g": lambda: pytest.fail("the work started")})
  monkeypatch.setattr(compile_cli, "_run_group", lambda name: pytest.fail("the work started"))
  rc = compile_cli.main(["--jobs", "1"])
  err = capsys.readouterr().err
  assert rc == 2 and err.startswith("error: the cache of numba's kernels"), err
  assert str(blocker / "numba") in err and "not writable" in err
