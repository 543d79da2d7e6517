"""Mesh resolution, as the datasets use it: `lrf_jax.geometry.resolution` (kept here for old imports)."""

from lrf_jax.geometry.resolution import MrDefinition, mesh_resolution, unique_edges

__all__ = ["MrDefinition", "mesh_resolution", "unique_edges"]
