"""Datasets as model/scene `Pair`s, nuisances, repeatability keypoints and training keypoints.

    from lrf_jax import datasets
    pairs = datasets.load_br(noise=0.3)                 # 18 Pairs, exact correspondences
    model_idx, scene_idx = datasets.repeatability_keypoints(pairs[0], n=1000, seed=0)
    demo = datasets.load_demo(4, seed=0)                # synthetic, no download
    rooms = datasets.load_threedmatch_scenes()          # 3DMatch fragment pairs (metres)
    mine = datasets.load_scan_set("my_scans/")          # your own scans + poses.txt / gt.log / .conf

Real data is found under an explicit root, else $LRF_DATA, else `<repo>/data`
(`find_data_root`); see data/README.md for where to obtain each set.
"""

from lrf_jax.datasets.bologna import (BR_MODELS, BR_NOISE_LEVELS, BR_SCENE_MODELS,
                                      br_ground_truth, load_br, load_br_model, load_br_pair)
from lrf_jax.datasets.cache import Mesh, Scan, cache_info, clear_cache, load_mesh, load_scan
from lrf_jax.datasets.nuisances import (Decimation, add_gaussian_noise, decimate, points_only,
                                        random_rigid_motion, rotate_about_axis, rotation_matrix,
                                        with_decimation, with_noise, with_random_motion,
                                        with_rotation)
from lrf_jax.datasets.pair import Pair, repeatability_keypoints, transform_points
from lrf_jax.geometry.resolution import mesh_resolution, unique_edges
from lrf_jax.datasets.root import (DATASETS, ENV_VAR, DataNotFoundError, dataset_dir,
                                   find_data_root)
from lrf_jax.datasets.scan_sets import (ScanSet, load_scan_set, read_scan_set, split_by_scan,
                                        training_correspondences)
from lrf_jax.datasets.stanford import BUNNY_SCAN_ORDER, bunny_poses, load_bunny_pairs
from lrf_jax.datasets.synthetic import hidden_point_removal, load_demo, make_demo_mesh, \
    make_demo_pair, make_street_pair
from lrf_jax.datasets.threedmatch import load_threedmatch_scenes, read_pairs_tsv
from lrf_jax.datasets.training import TrainingSet, build_training_set, default_cache_dir
from lrf_jax.datasets.uwa3m import UWA3M_OBJECTS, load_uwa3m, read_pseudo_gt
from lrf_jax.datasets.uwaor import (UWAOR_OBJECTS, load_uwaor, load_uwaor_model,
                                    load_uwaor_scene, uwaor_ground_truth)

__all__ = [
    "BR_MODELS",
    "BR_NOISE_LEVELS",
    "BR_SCENE_MODELS",
    "BUNNY_SCAN_ORDER",
    "DATASETS",
    "DataNotFoundError",
    "Decimation",
    "ENV_VAR",
    "Mesh",
    "Pair",
    "Scan",
    "ScanSet",
    "TrainingSet",
    "UWA3M_OBJECTS",
    "UWAOR_OBJECTS",
    "add_gaussian_noise",
    "br_ground_truth",
    "build_training_set",
    "bunny_poses",
    "cache_info",
    "clear_cache",
    "dataset_dir",
    "decimate",
    "default_cache_dir",
    "find_data_root",
    "hidden_point_removal",
    "load_br",
    "load_br_model",
    "load_br_pair",
    "load_bunny_pairs",
    "load_demo",
    "load_mesh",
    "load_scan",
    "load_scan_set",
    "load_threedmatch_scenes",
    "load_uwa3m",
    "load_uwaor",
    "load_uwaor_model",
    "load_uwaor_scene",
    "make_demo_mesh",
    "make_demo_pair",
    "make_street_pair",
    "mesh_resolution",
    "points_only",
    "random_rigid_motion",
    "read_pairs_tsv",
    "read_pseudo_gt",
    "read_scan_set",
    "repeatability_keypoints",
    "rotate_about_axis",
    "rotation_matrix",
    "split_by_scan",
    "training_correspondences",
    "transform_points",
    "unique_edges",
    "uwaor_ground_truth",
    "with_decimation",
    "with_noise",
    "with_random_motion",
    "with_rotation",
]
