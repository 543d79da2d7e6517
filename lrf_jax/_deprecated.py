"""The pre-0.7 names that still read, with a `DeprecationWarning`, for one release."""

from __future__ import annotations

import warnings
from typing import Any
from collections.abc import Callable

REMOVED_IN = "the next release"


def warn_moved(old: str, new: str, stacklevel: int = 2) -> None:
  """A `DeprecationWarning`: `old` moved to `new` (`stacklevel` as `warnings.warn`'s, counted
  from the caller of this function)."""
  warnings.warn(f"{old} is deprecated and will be removed in {REMOVED_IN} of lrf_jax; "
                f"import {new} instead", DeprecationWarning, stacklevel=stacklevel + 1)


# old module-level name -> its new name (`module.OLD` -> `module.NEW`), for one release. 0.7 spells
# "neighbor" the American way throughout (as numpy, scipy, scikit-learn and Open3D do) and gives
# each radius fraction one name; each module listed sets `__getattr__ = renamed(__name__,
# globals())`, which forwards its old names with a warning naming the new one.
RENAMED: dict[str, str] = {
    "lrf_jax.api.HOST_NEIGHBOUR_BUDGET": "HOST_NEIGHBOR_BUDGET",
    "lrf_jax.frames.board.MARGIN": "MARGIN_RATIO",
    "lrf_jax.frames.board.MIN_Z_NEIGHBOURS": "MIN_Z_NEIGHBORS",
    "lrf_jax.frames.flare.MARGIN": "MARGIN_RATIO",
    "lrf_jax.frames.flare.MIN_Z_NEIGHBOURS": "MIN_Z_NEIGHBORS",
    "lrf_jax.frames.flare.MIN_TANGENT_NEIGHBOURS": "MIN_TANGENT_NEIGHBORS",
    "lrf_jax.frames.lrf_net.MIN_Z_NEIGHBOURS": "MIN_Z_NEIGHBORS",
    "lrf_jax.frames.lrf_net_plus.AREA_NEIGHBOURS": "AREA_NEIGHBORS",
    "lrf_jax.frames.mian.MIN_NEIGHBOURS": "MIN_NEIGHBORS",
    "lrf_jax.frames.ps.CONTOUR_RATIO": "MARGIN_RATIO",
    "lrf_jax.frames.shot.MIN_NEIGHBOURS": "MIN_NEIGHBORS",
}


def renamed(module: str, namespace: dict[str, Any]) -> Callable[[str], Any]:
  """`__getattr__` of `module` (whose globals are `namespace`): each of its old names in `RENAMED`
  gives the new name's value and warns (`DeprecationWarning`) naming the new name."""
  old_names = {k.rpartition(".")[2]: v for k, v in RENAMED.items()
               if k.rpartition(".")[0] == module}

  def __getattr__(name: str) -> Any:
    if name in old_names:
      warn_moved(f"{module}.{name}", f"{module}.{old_names[name]}")
      return namespace[old_names[name]]
    raise AttributeError(f"module {module!r} has no attribute {name!r}")

  return __getattr__
