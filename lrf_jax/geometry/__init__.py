"""Geometry shared by the pipeline's layers.

  ops.py         NaN-safe jnp helpers for one keypoint (frames from axes, covariance, sign rules,
                 Kabsch, `sanitize`), vmapped by every LRF method
  normals.py     PCA / mesh normals, their orientation, mesh curvature (numba)
  mesh.py        mesh neighborhoods: faces incident to a ball, RoPS' triangle slots (numba)
  resolution.py  mesh resolution (mr), the unit of every radius
  cloud.py       `CheckedCloud`: any cloud input (array, `Cloud`, path, `.points`), checked once
  sampling.py    voxel downsampling
  keypoints.py   ISS keypoints on the compiled engine

Importing this package is light (no JAX); each module pays for its own imports.
"""
