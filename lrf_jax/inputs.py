"""What `compute_frames` and `register` accept as a cloud: one rule for both.

* an (n, 3) array-like of coordinates;
* an `lrf_jax.io.Cloud` (its faces and normals are used);
* a path to any file `lrf_jax.io.read_cloud` opens (PLY, PCD, XYZ/TXT(.gz), NPY);
* any object with a `.points` attribute convertible to (n, 3) (e.g. Open3D's `PointCloud`, whose
  `.normals` are used when it has them), or with `.vertices` and `.triangles` (e.g. Open3D's
  `TriangleMesh`). Open3D itself is never imported.

Faces or normals given explicitly to the caller win over what the object carries.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from lrf_jax.io import Cloud, read_cloud
from lrf_jax.search.neighborhoods import validate_cloud, validate_faces, validate_normals


class CloudInput(NamedTuple):
  """A validated cloud: points (n, 3) float64, faces (f, 3) or None, normals (n, 3) or None."""

  points: np.ndarray
  faces: np.ndarray | None
  normals: np.ndarray | None


def as_cloud(x: Any, name: str = "points", *, faces: Any = None,
             normals: Any = None) -> CloudInput:
  """Read any accepted cloud input (see the module docstring) into a `CloudInput`.

  Args:
    x: the cloud.
    name: the argument's name, for error messages.
    faces: explicit (f, 3) triangles, winning over the object's.
    normals: explicit (n, 3) normals, winning over the object's.

  Raises:
    ValueError: not a non-empty (n, 3) cloud of finite floats (naming `name`), faces that are
      not (f, 3) indices into it or normals that are not (n, 3) real numbers (naming them).
    FileNotFoundError: a path that does not exist.
  """
  own_faces = own_normals = None
  if isinstance(x, (str, os.PathLike)):
    x = read_cloud(x)
  if isinstance(x, (Cloud, CloudInput)):  # CloudInput: an already validated cloud, kept whole
    pts, own_faces, own_normals = x.points, x.faces, x.normals
  elif hasattr(x, "vertices") and hasattr(x, "triangles"):  # a mesh object (Open3D TriangleMesh)
    pts = validate_cloud(x.vertices, name)
    tri = np.asarray(x.triangles)
    own_faces = tri.astype(np.int64) if tri.size else None
  elif hasattr(x, "points") and not isinstance(x, np.ndarray):  # a cloud object
    pts = validate_cloud(x.points, name)
    nrm = np.asarray(getattr(x, "normals", ()))
    own_normals = nrm.astype(np.float64) if nrm.size and nrm.shape == pts.shape else None
  else:
    pts = x
  pts = validate_cloud(pts, name)
  f = faces if faces is not None else own_faces
  n = normals if normals is not None else own_normals
  # Named after the argument when given explicitly, else after the cloud that carried them.
  return CloudInput(
      pts, None if f is None else validate_faces(f, len(pts), _own(faces, "faces", name)),
      None if n is None else validate_normals(n, len(pts), _own(normals, "normals", name)))


def _own(explicit: Any, what: str, name: str) -> str:
  return what if explicit is not None else f"{name} {what}"
