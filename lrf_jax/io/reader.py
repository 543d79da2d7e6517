"""`read_cloud`: any supported cloud or mesh file, the reader chosen by suffix."""

from __future__ import annotations

import os
from typing import Any

from lrf_jax.io.cloud import Cloud, read_npy
from lrf_jax.io.e57 import read_e57
from lrf_jax.io.las import read_las
from lrf_jax.io.pcd import read_pcd
from lrf_jax.io.ply import read_ply
from lrf_jax.io.sweeps import check_bin_layout, read_kitti_bin
from lrf_jax.io.text import read_xyz
from lrf_jax.io.validation import bad_input, require_file


_TEXT_SUFFIXES = (".xyz", ".txt", ".pts", ".asc")


# The suffixes of the readers of the `formats` extra (laspy[lazrs], pye57).
EXTRA_SUFFIXES = (".las", ".laz", ".e57")


def read_cloud(path: str | os.PathLike, *, bin_layout: str | None = None) -> Cloud:
  """Reads any supported point-cloud or mesh file, choosing the reader by suffix.

  Supported: `.ply` (`read_ply`), `.pcd` (`read_pcd`), `.npy` (`read_npy`), LiDAR sweeps `.bin`
  (`read_kitti_bin`: KITTI's 16-byte x, y, z, reflectance points by default, 12-byte x, y, z
  ones with `bin_layout="xyz"`; nuScenes' `.pcd.bin`, five floats a point, is refused),
  whitespace text `.xyz/.txt/.pts/.asc`, optionally gzip-compressed with a further `.gz`
  (`read_xyz`), and with the `formats` extra `.las`/`.laz` (`read_las`) and `.e57`
  (`read_e57`: every scan, its pose applied, the scans concatenated).

  Args:
    path: the file.
    bin_layout: the layout of a `.bin` sweep: "xyzi", "xyz" or None (the default layout,
      checked where the size fits both: `lrf_jax.io.sweeps`); ignored for other files.

  Returns:
    A Cloud (faces only for PLY meshes; normals where the file stores them).

  Raises:
    FileNotFoundError: missing file.
    MissingReaderError: a `.las`, `.laz` or `.e57` file without the `formats` extra (also a
      ValueError).
    ValueError: unsupported suffix, a bad `bin_layout`, or any error of the chosen reader.
  """
  check_bin_layout(bin_layout)
  p = require_file(path)
  suffixes = [s.lower() for s in p.suffixes]
  last = suffixes[-1] if suffixes else ""
  if last == ".gz" and len(suffixes) >= 2:
    last = suffixes[-2]
    if last not in _TEXT_SUFFIXES:
      raise bad_input(p, "suffix", "a text cloud when gzip'ed (" + ", ".join(_TEXT_SUFFIXES)
                      + " + .gz)", f"{suffixes[-2]}.gz")
  if last == ".ply":
    return read_ply(p, elements=False).to_cloud()  # a Cloud keeps no other elements
  if last == ".pcd":
    return read_pcd(p)
  if last == ".npy":
    return read_npy(p)
  if last in _TEXT_SUFFIXES:
    return read_xyz(p)
  if last in (".las", ".laz"):
    return read_las(p)
  if last == ".e57":
    return read_e57(p)
  if last == ".bin":
    if suffixes[-2:] == [".pcd", ".bin"]:  # nuScenes' sweeps: 20 bytes a point, not KITTI's 16
      raise bad_input(p, "suffix", "a KITTI .bin (float32 x, y, z, reflectance)",
                      "a nuScenes-style .pcd.bin (float32 x, y, z, intensity, ring: read as "
                      "KITTI's records it would give wrong points whenever its size is a "
                      "multiple of 16); save its first three columns as .npy: "
                      "np.fromfile(path, '<f4').reshape(-1, 5)[:, :3]")
    return read_kitti_bin(p, bin_layout=bin_layout)
  raise bad_input(p, "suffix", "one of .ply, .pcd, .npy, .bin, " + ", ".join(_TEXT_SUFFIXES)
                  + " (text optionally .gz), " + ", ".join(EXTRA_SUFFIXES) + " (the formats "
                  "extra)", repr("".join(p.suffixes) or "(none)"))


def cloud_source(path: Any, bin_layout: str | None = None) -> Any:
  """What a command line hands to `as_cloud`, `register` or `register_all` for an input
  `path` read with `bin_layout` (`--bin-layout`): the path itself, which they read with
  `read_cloud`'s defaults, unless a layout is given and the path names a `.bin` sweep; then
  the `Cloud` `read_cloud(path, bin_layout=bin_layout)` reads. Anything but a path is
  returned as it is.

  Raises:
    FileNotFoundError, ValueError: as `read_cloud`, for a `.bin` read here.
  """
  check_bin_layout(bin_layout, "--bin-layout")
  if bin_layout is None or not isinstance(path, (str, os.PathLike)):
    return path
  if os.fspath(path).lower().endswith(".bin"):
    return read_cloud(path, bin_layout=bin_layout)
  return path
