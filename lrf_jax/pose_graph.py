"""Deprecated alias of `lrf_jax.registration.pose_graph` (moved there in 0.7); removed in the next release."""

from lrf_jax import _deprecated
from lrf_jax.registration import pose_graph as _new

__getattr__, __dir__, __all__ = _deprecated.alias(__name__, _new)
