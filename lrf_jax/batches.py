"""Deprecated alias of `lrf_jax.learning.batches` (moved there in 0.7); removed in the next release."""

from lrf_jax import _deprecated
from lrf_jax.learning import batches as _new

__getattr__, __dir__, __all__ = _deprecated.alias(__name__, _new)
