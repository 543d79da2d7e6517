"""Geometry shared by the pipeline's layers.

  ops.py         NaN-safe jnp helpers for one keypoint (frames from axes, covariance, sign rules,
                 Kabsch, `sanitize`), vmapped by every LRF method
  normals.py     PCA / mesh normals, their orientation, mesh curvature (numba)
  mesh.py        mesh neighborhoods: faces incident to a ball, RoPS' triangle slots (numba)
  resolution.py  mesh resolution (mr), the unit of every radius
  sampling.py    voxel downsampling
  keypoints.py   ISS keypoints on the compiled engine

Importing this package is light (no JAX); each module pays for its own imports. The jnp helpers
were `lrf_jax.geometry.<name>` before 0.7: those names still resolve here, with a
`DeprecationWarning`, until the next release (`lrf_jax.geometry.ops.<name>` now).
"""

from __future__ import annotations

from typing import Any

_OPS_NAMES = frozenset({
    "Array", "DEGENERATE_EPS", "all_finite_rows", "centered_covariance", "directed_tangent_axis",
    "disambiguate_sign", "eigen_frame", "finite_or_zero", "frame_from_zx", "identity_where_invalid",
    "kabsch", "lexicographic_argmax", "majority_balance", "orient_like", "safe_norm",
    "safe_normalize", "sanitize", "smallest_eigvec", "tangent_projection", "toldi_normal",
    "weighted_covariance",
})
_warned = False


def __getattr__(name: str) -> Any:
  """The pre-0.7 `lrf_jax.geometry.<helper>` names, forwarded to `ops` (deprecated)."""
  global _warned
  if name not in _OPS_NAMES:
    raise AttributeError(f"module 'lrf_jax.geometry' has no attribute {name!r}")
  import lrf_jax.geometry.ops as ops  # pylint: disable=import-outside-toplevel
  if not _warned:
    _warned = True
    from lrf_jax import _deprecated  # pylint: disable=import-outside-toplevel
    _deprecated.warn_moved(f"lrf_jax.geometry.{name}", "lrf_jax.geometry.ops", stacklevel=2)
  return getattr(ops, name)
