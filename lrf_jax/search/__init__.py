"""Neighborhood search: points -> neighborhoods.

  engine.py         the compiled engine's interface (numba, multi-threaded, cached on disk)
  grid.py           its uniform grid (points binned by cell and rank) and threads
  balls.py          ball counts and moments, the patch kernel
  ball_lists.py     ball lists (every point within r), any-within
  nearest.py        k nearest neighbors, the ICP kernels' pairing step
  neighborhoods.py  `build_patches` -> `Patches` (offsets, mask, r/3 normal statistics), the
                    cloud's `SearchIndex` (the arguments' checks: `lrf_jax.checks`)
  device.py         the same `Patches` from jitted voxel grids on the accelerator
  chunks.py         the one pad / run / slice loop over keypoint chunks
"""
