"""Readers and writers for point clouds, meshes and rigid poses.

    from lrf_jax import io
    cloud = io.read_cloud("scan.ply")             # Cloud(points (n, 3) float64, faces, normals)
    T = io.read_xf("Scene0-rs0.xf")               # (4, 4), model -> scene
    poses = io.read_stanford_conf("bun.conf")     # {scan: world-from-scan (4, 4)}

Every bad input raises ValueError (FileNotFoundError for a missing file) naming the file, the
field and what was expected versus found; so does a file that cannot be opened for reading (e.g.
no read permission) and a path that is a symbolic link loop (`SymlinkLoopError`, also an
OSError with errno ELOOP). A normal that is not finite (NaN/inf) is read as a NaN row, a missing
normal, and keeps its point (`check_normals`).

`.las`/`.laz` (`read_las`) and `.e57` (`read_e57`) need the `formats` extra (laspy[lazrs],
pye57: `pip install 'lrf_jax[formats]'`); without it reading one raises `MissingReaderError`
(a ValueError naming the extra). A `.bin` sweep is KITTI's 16-byte (x, y, z, reflectance)
points unless `bin_layout="xyz"` (12-byte x, y, z points; `lrf_jax.io.sweeps`).
"""

from lrf_jax.io.cloud import Cloud, read_npy
from lrf_jax.io.e57 import read_e57
from lrf_jax.io.las import read_las
from lrf_jax.io.pcd import read_pcd
from lrf_jax.io.ply import PlyMesh, read_ply, write_ply
from lrf_jax.io.poses import (LogEntry, quaternion_to_matrix, read_3dmatch_log,
                              read_stanford_conf, read_xf, write_xf)
from lrf_jax.io.reader import read_cloud
from lrf_jax.io.sweeps import BIN_LAYOUTS, read_kitti_bin
from lrf_jax.io.text import read_xyz
from lrf_jax.io.validation import (MissingReaderError, SymlinkLoopError, check_normals,
                                   check_points, check_rigid)

__all__ = [
    "BIN_LAYOUTS",
    "Cloud",
    "LogEntry",
    "MissingReaderError",
    "PlyMesh",
    "SymlinkLoopError",
    "check_normals",
    "check_points",
    "check_rigid",
    "quaternion_to_matrix",
    "read_3dmatch_log",
    "read_cloud",
    "read_e57",
    "read_kitti_bin",
    "read_las",
    "read_npy",
    "read_pcd",
    "read_ply",
    "read_stanford_conf",
    "read_xf",
    "read_xyz",
    "write_ply",
    "write_xf",
]
