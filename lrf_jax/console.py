"""Deprecated alias of `lrf_jax.cli.console` (moved there in 0.7); removed in the next release.

The console scripts of an install made before 0.7 (`lrf-frames`, `lrf-register`) call
`lrf_jax.console:frames` / `:register`; a fresh install points them at `lrf_jax.cli.console`.
This alias does not warn: the warning would be printed on every command of such an install,
to users who did not write the import (reinstalling is the fix).
"""

from lrf_jax import _deprecated
from lrf_jax.cli import console as _new

__getattr__, __dir__, __all__ = _deprecated.alias(__name__, _new, warn=False)
