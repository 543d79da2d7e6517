"""Progress bars that tell the truth: a tqdm bar's clock restarted after its first item."""

from __future__ import annotations

from typing import Any


def restart_clock(bar: Any) -> None:
  """Time a tqdm bar's rate and ETA from now on, keeping its count: called after a stage's
  first item, whose time (a first run compiles the stage's kernels in it) says nothing about
  the others'.

  Args:
    bar: a `tqdm` bar (its count `n` is kept; its start time and rate are reset).
  """
  n = bar.n
  bar.reset()
  bar.n = bar.last_print_n = bar.initial = n
  bar.refresh()
