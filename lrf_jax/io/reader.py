"""`read_cloud`: any supported cloud or mesh file, the reader chosen by suffix."""

from __future__ import annotations

import os

from lrf_jax.io.cloud import Cloud, read_kitti_bin, read_npy
from lrf_jax.io.pcd import read_pcd
from lrf_jax.io.ply import read_ply
from lrf_jax.io.text import read_xyz
from lrf_jax.io.validation import bad_input, require_file


_TEXT_SUFFIXES = (".xyz", ".txt", ".pts", ".asc")


def read_cloud(path: str | os.PathLike) -> Cloud:
  """Reads any supported point-cloud or mesh file, choosing the reader by suffix.

  Supported: `.ply` (`read_ply`), `.pcd` (`read_pcd`), `.npy` (`read_npy`), KITTI Velodyne
  sweeps `.bin` (`read_kitti_bin`; nuScenes' `.pcd.bin`, five floats a point, is refused) and
  whitespace text `.xyz/.txt/.pts/.asc`, optionally gzip-compressed with a further `.gz`
  (`read_xyz`).

  Args:
    path: the file.

  Returns:
    A Cloud (faces only for PLY meshes; normals where the file stores them).

  Raises:
    FileNotFoundError: missing file.
    ValueError: unsupported suffix, or any error of the chosen reader.
  """
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
  if last == ".bin":
    if suffixes[-2:] == [".pcd", ".bin"]:  # nuScenes' sweeps: 20 bytes a point, not KITTI's 16
      raise bad_input(p, "suffix", "a KITTI .bin (float32 x, y, z, reflectance)",
                      "a nuScenes-style .pcd.bin (float32 x, y, z, intensity, ring: read as "
                      "KITTI's records it would give wrong points whenever its size is a "
                      "multiple of 16); save its first three columns as .npy: "
                      "np.fromfile(path, '<f4').reshape(-1, 5)[:, :3]")
    return read_kitti_bin(p)
  raise bad_input(p, "suffix", "one of .ply, .pcd, .npy, .bin, " + ", ".join(_TEXT_SUFFIXES)
                  + " (text optionally .gz)", repr("".join(p.suffixes) or "(none)"))
