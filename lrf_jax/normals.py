"""Deprecated alias of `lrf_jax.geometry.normals` (moved there in 0.7); removed in the next release."""

from lrf_jax import _deprecated
from lrf_jax.geometry import normals as _new

__getattr__, __dir__, __all__ = _deprecated.alias(__name__, _new)
