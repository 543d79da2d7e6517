"""The optional parts of the install, and the error that names the one a call needs.

`pip install lrf_jax` (the core) computes frames, descriptors and registrations: jax, numpy,
numba, scipy and the file readers. The rest is in extras (`pyproject.toml`):

* `train`: flax, optax, orbax-checkpoint (and matplotlib for the training curves): `train.py`,
  `lrf_jax.learning`'s training step, loop and checkpoints;
* `eval`: matplotlib, fast-simplification and flax: `evaluate.py`'s figures, its decimation
  nuisance and the ablation's regressor variants;
* `plot`: matplotlib alone: the `--png` figures of `lrf-frames` and `lrf-register`, the figures of
  `register_all`.

A module that needs an extra imports it inside `try` and raises `missing_extra(...)` from the
ImportError, so that the message says what to install instead of only what is missing.
"""

from __future__ import annotations

import importlib.util
import sys
from typing import Any

EXTRAS = {
    "train": ("flax", "optax", "orbax-checkpoint", "matplotlib"),
    "eval": ("matplotlib", "fast-simplification", "flax"),
    "plot": ("matplotlib",),
    "ray": ("ray",),
    "viz": ("viser",),
    "formats": ("laspy", "pye57"),
}


# The module each extra's package is imported as.
_MODULES = {"flax": "flax", "optax": "optax", "orbax-checkpoint": "orbax.checkpoint",
            "matplotlib": "matplotlib", "fast-simplification": "fast_simplification", "ray": "ray",
            "viser": "viser", "laspy": "laspy", "pye57": "pye57"}


class MissingExtraError(ImportError):
  """An optional package is not installed; the message names the extra that installs it."""


def missing_extra(package: str | None, extra: str, what: str) -> MissingExtraError:
  """The error to raise (from the ImportError) when `what` needs a package of `extra`.

  Args:
    package: the module that failed to import (`ImportError.name`; None: the extra's packages).
    extra: a key of `EXTRAS`.
    what: what needed it, for the message ("training", "the figures", ...).

  Returns:
    A `MissingExtraError` whose message names the package and the install command.
  """
  name = package.split(".")[0] if package else ", ".join(EXTRAS[extra])
  return MissingExtraError(
      f"{what} needs {name}, which is not installed: pip install 'lrf_jax[{extra}]' (the "
      f"'{extra}' extra: {', '.join(EXTRAS[extra])})", name=package)


def pyplot(extra: str = "plot", what: str = "the figures") -> Any:
  """matplotlib.pyplot on the file-only Agg backend, or a `MissingExtraError` naming `extra`."""
  matplotlib_module(extra, what).use("Agg")
  import matplotlib.pyplot as plt
  return plt


def matplotlib_module(extra: str = "plot", what: str = "the figures") -> Any:
  """The matplotlib module itself (colormaps), or a `MissingExtraError` naming `extra`."""
  try:
    import matplotlib
  except ImportError as e:
    raise missing_extra(e.name, extra, what) from e
  return matplotlib


def require(extra: str, what: str) -> None:
  """Check, before any work, that every package of `extra` is installed (without importing
  them): a job that needs them at its end (evaluate.py's figures) fails at its start instead.

  Raises:
    MissingExtraError: naming the first missing package and the extra.
  """
  for package in EXTRAS[extra]:
    if not _installed(_MODULES[package]):
      raise missing_extra(_MODULES[package], extra, what)


def _installed(module: str) -> bool:
  top = module.split(".")[0]
  if top in sys.modules:
    return sys.modules[top] is not None
  try:
    return importlib.util.find_spec(module) is not None
  except (ImportError, ValueError):
    return False
