"""Deprecated alias of `lrf_jax.learning.configs.noise_aug` (moved there in 0.7); removed in the next release."""

from lrf_jax import _deprecated
from lrf_jax.learning.configs import noise_aug as _new

__getattr__, __dir__, __all__ = _deprecated.alias(__name__, _new)
