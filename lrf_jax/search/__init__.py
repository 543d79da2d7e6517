"""Neighbourhood search: points -> neighbourhoods.

  engine.py         the compiled engine (numba): uniform grid, ball queries and patches, k-NN
  neighborhoods.py  `build_patches` -> `Patches` (offsets, mask, r/3 normal statistics), the
                    cloud's `SearchIndex`, the inputs' validation
  device.py         the same `Patches` from jitted voxel grids on the accelerator
  chunks.py         the one pad / run / slice loop over keypoint chunks
"""
