"""lrf_jax: learned (LRF-Net) and hand-crafted local reference frames in JAX.

    import lrf_jax
    frames, valid = lrf_jax.compute_frames(points, keypoints, radius, method="lrf_net")

Conventions: frames are (..., 3, 3) with rows x, y, z (they map world vectors into the LRF),
right-handed, det +1; invalid frames are the identity with `valid == False`.
"""

from lrf_jax import engine
from lrf_jax.api import compute_frames, frames_from_patches, mesh_resolution
from lrf_jax.caches import clear_caches
from lrf_jax.engine import set_num_threads
from lrf_jax.frames import METHODS, MethodSpec, register_method
from lrf_jax.frames.lrf_net import lrf_net_frames
from lrf_jax.keypoints import iss_keypoints
from lrf_jax.losses import batched_chamfer, chamfer, siamese_loss
from lrf_jax.metrics import meancos, repeatability_summary
from lrf_jax.model import default_params, init_params, load_params, save_params
from lrf_jax.neighborhoods import Patches, build_patches
from lrf_jax.multiway import register_all
from lrf_jax.registration import register
from lrf_jax.sampling import voxel_downsample

__version__ = "0.6.0"

__all__ = [
    "METHODS",
    "MethodSpec",
    "Patches",
    "batched_chamfer",
    "build_patches",
    "chamfer",
    "clear_caches",
    "compute_frames",
    "default_params",
    "engine",
    "frames_from_patches",
    "init_params",
    "iss_keypoints",
    "load_params",
    "lrf_net_frames",
    "meancos",
    "mesh_resolution",
    "register",
    "register_all",
    "register_method",
    "repeatability_summary",
    "save_params",
    "set_num_threads",
    "siamese_loss",
    "voxel_downsample",
]
