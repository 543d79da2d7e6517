"""`CheckedCloud`: a cloud whose every check has run, the one form in which the package takes a
cloud inward (`compute_frames`, `register`, `iss_keypoints`, `voxel_downsample`, the programs).

What it accepts (`CheckedCloud(x)`):

* an (n, 3) array-like of coordinates;
* an `lrf_jax.io.Cloud` (its faces and normals are used);
* a path to any file `lrf_jax.io.read_cloud` opens with its defaults (PLY, PCD, XYZ/TXT(.gz),
  NPY, .bin sweeps; LAS/LAZ, E57 with the `formats` extra);
* any object with a `.points` attribute convertible to (n, 3) (e.g. Open3D's `PointCloud`, whose
  `.normals` are used when it has them), or with `.vertices` and `.triangles` (e.g. Open3D's
  `TriangleMesh`). Open3D itself is never imported;
* a `CheckedCloud` (its checked arrays are kept, not checked again).

Faces or normals given explicitly win over what the object carries. The checks are those of
`lrf_jax.checks` (one message style), each run once, in the constructor.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from lrf_jax.checks import validate_cloud, validate_faces, validate_normals
from lrf_jax.io import Cloud, read_cloud


class CheckedCloud:
  """A checked cloud: points (n, 3) finite float64, faces (f, 3) int64 indices into them or None,
  normals (n, 3) real numbers (NaN rows: missing) or None. Frozen.

  Built only by its constructor, which runs every check once; what is derived from the cloud
  (`resolution`) is computed on first use and kept on it. It pickles as its three arrays (no
  derived values), so handing it to another process costs no more than the arrays.

  Args:
    x: the cloud (see the module docstring).
    faces: explicit (f, 3) triangles, winning over the object's.
    normals: explicit (n, 3) normals, winning over the object's.
    name: the argument's name, for error messages.

  Raises:
    ValueError: not a non-empty (n, 3) cloud of finite floats (naming `name`), faces that are
      not (f, 3) indices into it or normals that are not (n, 3) real numbers (naming them).
    FileNotFoundError: a path that does not exist.
  """

  __slots__ = ("points", "faces", "normals", "_resolution", "_working")
  points: np.ndarray
  faces: np.ndarray | None
  normals: np.ndarray | None
  _resolution: float | None
  _working: Any

  def __init__(self, x: Any, faces: Any = None, normals: Any = None, *,
               name: str = "points") -> None:
    own_faces = own_normals = None
    from_file = isinstance(x, (str, os.PathLike))
    if from_file:  # the reader checked the coordinates, naming the file and the field
      x = read_cloud(x)
    if isinstance(x, CheckedCloud):  # checked already: its arrays are kept as they are
      pts, own_faces, own_normals = x.points, x.faces, x.normals
    elif isinstance(x, Cloud):
      pts = x.points if from_file else validate_cloud(x.points, name)
      own_faces, own_normals = x.faces, x.normals
    elif hasattr(x, "vertices") and hasattr(x, "triangles"):  # a mesh object (Open3D TriangleMesh)
      pts = validate_cloud(x.vertices, name)
      tri = np.asarray(x.triangles)
      own_faces = tri.astype(np.int64) if tri.size else None
    elif hasattr(x, "points") and not isinstance(x, np.ndarray):  # a cloud object
      pts = validate_cloud(x.points, name)
      nrm = np.asarray(getattr(x, "normals", ()))
      own_normals = nrm.astype(np.float64) if nrm.size and nrm.shape == pts.shape else None
    else:
      pts = validate_cloud(x, name)
    # Named after the argument when given explicitly, else after the cloud that carried them;
    # a CheckedCloud's own faces and normals were checked when it was built.
    kept = isinstance(x, CheckedCloud)
    f = _checked(faces, own_faces, kept, len(pts), validate_faces, "faces", name)
    n = _checked(normals, own_normals, kept, len(pts), validate_normals, "normals", name)
    for slot, value in (("points", pts), ("faces", f), ("normals", n), ("_resolution", None),
                        ("_working", None)):
      object.__setattr__(self, slot, value)

  def __setattr__(self, name: str, value: Any) -> None:
    raise AttributeError(f"CheckedCloud is frozen: cannot set {name!r}")

  def __delattr__(self, name: str) -> None:
    raise AttributeError(f"CheckedCloud is frozen: cannot delete {name!r}")

  def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
    """Pickled as its checked arrays alone (derived values are recomputed where needed)."""
    return (_unpickle, (self.points, self.faces, self.normals))

  def __repr__(self) -> str:
    return (f"CheckedCloud({len(self.points)} points"
            + ("" if self.faces is None else f", {len(self.faces)} faces")
            + ("" if self.normals is None else ", normals") + ")")

  def with_normals(self, normals: Any) -> CheckedCloud:
    """The same checked points and faces with `normals` ((n, 3), checked) or without any
    (None); the points are not checked again.

    Raises:
      ValueError: normals that are not (n, 3) real numbers.
    """
    if normals is not None:
      normals = validate_normals(normals, len(self.points), "normals")
    return _unpickle(self.points, self.faces, normals)

  @property
  def resolution(self) -> float:
    """The mesh resolution mr (cloud units): mean edge length with faces, mean nearest-neighbor
    distance without (`lrf_jax.geometry.resolution.mesh_resolution`); computed once.

    Raises:
      ValueError: fewer than 2 points, or an empty face array.
    """
    mr = self._resolution
    if mr is None:
      from lrf_jax.geometry.resolution import mesh_resolution
      mr = mesh_resolution(self.points, self.faces)[0]
      object.__setattr__(self, "_resolution", mr)
    return mr

  @property
  def working_resolution(self) -> Any:
    """Its `lrf_jax.geometry.resolution.working_resolution` (a `Resolution`: `resolution` on a
    clean cloud or a mesh, the area-weighted spacing on an uneven one); computed once, and
    `resolution` with it, and kept for the last cloud measured (`cloud_cache.cache_last`: a
    caller passing the same array again, e.g. `compute_frames` over chunks of keypoints, does
    not measure it again).

    Raises:
      ValueError: as `resolution`, or a cloud without spacing.
    """
    res = self._working
    if res is None:  # also kept for the last cloud measured (the same points in a new object)
      from lrf_jax.geometry.cloud_cache import cache_last
      from lrf_jax.geometry.resolution import working_resolution
      res = cache_last("working_resolution", (self.points, self.faces),
                       lambda: working_resolution(self.points, self.faces))
      object.__setattr__(self, "_working", res)
      if self._resolution is None:  # the same mean spacing (edge length), measured once
        object.__setattr__(self, "_resolution", res.mean_spacing)
    return res


def _checked(explicit: Any, own: Any, kept: bool, n_points: int, check: Any, what: str,
             name: str) -> Any:
  """The faces (or normals) a cloud carries: the explicit ones checked, else its own, checked
  unless they come from a `CheckedCloud` (`kept`)."""
  if explicit is not None:
    return check(explicit, n_points, what)
  if own is None or kept:
    return own
  return check(own, n_points, f"{name} {what}")


def _unpickle(points: np.ndarray, faces: np.ndarray | None,
              normals: np.ndarray | None) -> CheckedCloud:
  cloud = object.__new__(CheckedCloud)
  for slot, value in (("points", points), ("faces", faces), ("normals", normals),
                      ("_resolution", None), ("_working", None)):
    object.__setattr__(cloud, slot, value)
  return cloud


def as_cloud(x: Any, name: str = "points", *, faces: Any = None,
             normals: Any = None) -> CheckedCloud:
  """`CheckedCloud(x, faces, normals, name=name)`, and `x` itself when it is a `CheckedCloud`
  and no faces or normals are given (see `CheckedCloud`)."""
  if isinstance(x, CheckedCloud) and faces is None and normals is None:
    return x
  return CheckedCloud(x, faces, normals, name=name)
