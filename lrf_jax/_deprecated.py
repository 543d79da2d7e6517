"""Aliases that keep the pre-0.7 module paths importable for one release.

0.7 moved the flat modules of `lrf_jax/` into packages that follow the pipeline (`search/`,
`geometry/`, `registration/`, `learning/`, `evaluation/`, `cli/`). Each old path is a
thin module that calls `alias` and so re-exports its new home's names; importing it warns once
(`DeprecationWarning`). The aliases are removed in the next release.
"""

from __future__ import annotations

import warnings
from types import ModuleType
from typing import Any
from collections.abc import Callable

REMOVED_IN = "the next release"

# old module -> its new home (each old path is a module that calls `alias`). Besides these, two
# old modules became packages of the same name: `lrf_jax.geometry` (its jnp helpers are in
# `lrf_jax.geometry.ops`) and `lrf_jax.registration` (its interface is re-exported, its other
# names forwarded); both forward the old names with a warning.
MOVED: dict[str, str] = {
    "lrf_jax.batches": "lrf_jax.learning.batches",
    "lrf_jax.checkpoints": "lrf_jax.learning.checkpoints",
    "lrf_jax.chunks": "lrf_jax.search.chunks",
    "lrf_jax.cli_help": "lrf_jax.cli.help",
    "lrf_jax.config": "lrf_jax.learning.config",
    "lrf_jax.configs": "lrf_jax.learning.configs",
    "lrf_jax.configs.ablation": "lrf_jax.learning.configs.ablation",
    "lrf_jax.configs.default": "lrf_jax.learning.configs.default",
    "lrf_jax.configs.noise_aug": "lrf_jax.learning.configs.noise_aug",
    "lrf_jax.configs.plus": "lrf_jax.learning.configs.plus",
    "lrf_jax.configs.plus_crop": "lrf_jax.learning.configs.plus_crop",
    "lrf_jax.configs.plus_soft": "lrf_jax.learning.configs.plus_soft",
    "lrf_jax.configs.smoke": "lrf_jax.learning.configs.smoke",
    "lrf_jax.console": "lrf_jax.cli.console",
    "lrf_jax.data_sources": "lrf_jax.learning.data_sources",
    "lrf_jax.device_search": "lrf_jax.search.device",
    "lrf_jax.engine": "lrf_jax.search.engine",
    "lrf_jax.frames_cli": "lrf_jax.cli.frames",
    "lrf_jax.icp_host": "lrf_jax.registration.icp_host",
    "lrf_jax.keypoints": "lrf_jax.geometry.keypoints",
    "lrf_jax.losses": "lrf_jax.learning.losses",
    "lrf_jax.metrics": "lrf_jax.evaluation.metrics",
    "lrf_jax.model": "lrf_jax.learning.model",
    "lrf_jax.multiway": "lrf_jax.registration.multiway",
    "lrf_jax.multiway_cli": "lrf_jax.cli.multiway",
    "lrf_jax.multiway_figures": "lrf_jax.registration.multiway_figures",
    "lrf_jax.neighborhoods": "lrf_jax.search.neighborhoods",
    "lrf_jax.networks": "lrf_jax.learning.networks",
    "lrf_jax.normals": "lrf_jax.geometry.normals",
    "lrf_jax.plot": "lrf_jax.cli.plot",
    "lrf_jax.pose_graph": "lrf_jax.registration.pose_graph",
    "lrf_jax.register_cli": "lrf_jax.cli.register",
    "lrf_jax.registration_graph": "lrf_jax.registration.graph",
    "lrf_jax.registration_host": "lrf_jax.registration.host",
    "lrf_jax.resolution": "lrf_jax.geometry.resolution",
    "lrf_jax.sampling": "lrf_jax.geometry.sampling",
    "lrf_jax.train_lib": "lrf_jax.learning.train_lib",
    "lrf_jax.train_step": "lrf_jax.learning.train_step",
}


def warn_moved(old: str, new: str, stacklevel: int = 2) -> None:
  """A `DeprecationWarning`: `old` moved to `new` (`stacklevel` as `warnings.warn`'s, counted
  from the caller of this function)."""
  warnings.warn(f"{old} is deprecated and will be removed in {REMOVED_IN} of lrf_jax; "
                f"import {new} instead", DeprecationWarning, stacklevel=stacklevel + 1)


def alias(old: str, *modules: ModuleType, warn: bool = True
          ) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
  """(`__getattr__`, `__dir__`, `__all__`) of the deprecated module `old`: every name of
  `modules` (searched in order), the private ones included. Warns once (a module runs once)
  unless `warn` is False."""
  if warn:
    warn_moved(old, " or ".join(m.__name__ for m in modules), stacklevel=3)
  names = sorted({n for m in modules for n in getattr(
      m, "__all__", [k for k in vars(m) if not k.startswith("_")])})

  def __getattr__(name: str) -> Any:
    for m in modules:
      if hasattr(m, name):
        return getattr(m, name)
    raise AttributeError(f"module {old!r} has no attribute {name!r}")

  def __dir__() -> list[str]:
    return sorted({n for m in modules for n in dir(m)})

  return __getattr__, __dir__, names


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
