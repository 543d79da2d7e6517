"""Mesh resolution, as the datasets use it: `lrf_jax.resolution` (kept here for old imports)."""

from lrf_jax.resolution import MrDefinition, mesh_resolution, unique_edges

__all__ = ["MrDefinition", "mesh_resolution", "unique_edges"]
