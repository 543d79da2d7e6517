"""The pre-0.7 paths and names, forwarded with a DeprecationWarning in 0.7, are gone in 0.8 (and
so are the few paths 0.8 and 0.9 moved, without an alias):
each old module path fails to import (ModuleNotFoundError) and each old name fails to resolve
(AttributeError); each new home exists; nothing of the project's own (package, tests,
benchmarks, scripts, README) mentions an old module path.

The tables below are the record of what 0.8 and 0.9 removed or moved (CHANGELOG.md, "0.8.0"
and "0.9.0", summarise them); an entry names the path's home today.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# The 0.7 alias modules: old module path -> its home since 0.7.
MOVED: dict[str, str] = {
    "lrf_jax.batches": "lrf_jax.learning.batches",
    "lrf_jax.checkpoints": "lrf_jax.learning.checkpoints",
    "lrf_jax.chunks": "lrf_jax.search.chunks",
    "lrf_jax.cli_help": "lrf_jax.cli.help",
    "lrf_jax.config": "lrf_jax.learning.config",
    "lrf_jax.configs": "lrf_jax.learning.configs",
    "lrf_jax.configs.ablation": "lrf_jax.learning.configs.ablation",
    "lrf_jax.configs.default": "lrf_jax.learning.configs.default",
    "lrf_jax.configs.noise_aug": "lrf_jax.learning.configs.noise_aug",
    "lrf_jax.configs.plus": "lrf_jax.learning.configs.plus",
    "lrf_jax.configs.plus_crop": "lrf_jax.learning.configs.plus_crop",
    "lrf_jax.configs.plus_soft": "lrf_jax.learning.configs.plus_soft",
    "lrf_jax.configs.smoke": "lrf_jax.learning.configs.smoke",
    "lrf_jax.console": "lrf_jax.cli.console",
    "lrf_jax.data_sources": "lrf_jax.learning.data_sources",
    "lrf_jax.device_search": "lrf_jax.search.device",
    "lrf_jax.engine": "lrf_jax.search.engine",
    "lrf_jax.frames_cli": "lrf_jax.cli.frames",
    "lrf_jax.icp_host": "lrf_jax.registration.icp_host",
    "lrf_jax.keypoints": "lrf_jax.geometry.keypoints",
    "lrf_jax.losses": "lrf_jax.learning.losses",
    "lrf_jax.metrics": "lrf_jax.frames.metrics",  # in lrf_jax.evaluation in 0.7
    "lrf_jax.model": "lrf_jax.frames.weights",  # lrf_jax.learning.model in 0.7 (init_params still)
    "lrf_jax.multiway_cli": "lrf_jax.cli.multiway",
    "lrf_jax.multiway_figures": "lrf_jax.multiway.figures",
    "lrf_jax.neighborhoods": "lrf_jax.search.neighborhoods",
    "lrf_jax.networks": "lrf_jax.learning.networks",
    "lrf_jax.normals": "lrf_jax.geometry.normals",
    "lrf_jax.plot": "lrf_jax.cli.plot",
    "lrf_jax.pose_graph": "lrf_jax.multiway.pose_graph",
    "lrf_jax.register_cli": "lrf_jax.cli.register",
    "lrf_jax.registration_graph": "lrf_jax.registration.graph",
    "lrf_jax.registration_host": "lrf_jax.registration.host",
    "lrf_jax.resolution": "lrf_jax.geometry.resolution",
    "lrf_jax.sampling": "lrf_jax.geometry.sampling",
    "lrf_jax.train_lib": "lrf_jax.learning.train_lib",
    "lrf_jax.train_step": "lrf_jax.learning.train_step",
    # moved in 0.8, without an alias (no package-level import cycle)
    "lrf_jax.evaluation.metrics": "lrf_jax.frames.metrics",
    "lrf_jax.search.kernel_cache": "lrf_jax.kernel_cache",
    # moved in 0.9, without an alias: multiway is a package of its own above registration
    "lrf_jax.registration.multiway": "lrf_jax.multiway.pipeline",
    "lrf_jax.registration.multiway_tasks": "lrf_jax.multiway.tasks",
    "lrf_jax.registration.multiway_outputs": "lrf_jax.multiway.outputs",
    "lrf_jax.registration.multiway_figures": "lrf_jax.multiway.figures",
    "lrf_jax.registration.pose_graph": "lrf_jax.multiway.pose_graph",
    # moved in 0.9, without an alias: compute_frames and the normals rule of the methods'
    # prepare hooks are part of frames (frames_from_patches: lrf_jax.frames.patch_frames,
    # host_frames: lrf_jax.frames.host_path)
    "lrf_jax.api": "lrf_jax.frames.compute",
    "lrf_jax.prepare": "lrf_jax.frames.normals_rule",
}


# The names 0.7 forwarded with a warning: old dotted name -> its home since 0.7.
_OPS_HELPERS = (
    "DEGENERATE_EPS", "all_finite_rows", "centered_covariance", "directed_tangent_axis",
    "disambiguate_sign", "eigen_frame", "finite_or_zero", "frame_from_zx",
    "identity_where_invalid", "kabsch", "lexicographic_argmax", "majority_balance", "orient_like",
    "safe_norm", "safe_normalize", "sanitize", "smallest_eigvec", "tangent_projection",
    "toldi_normal", "weighted_covariance",
)
_WEIGHTS_NAMES = (
    "DEFAULT_WEIGHTS", "WEIGHTS_DIR", "apply_weights", "apply_weights_numpy", "default_params",
    "default_params_numpy", "load_params", "load_params_numpy", "save_params",
)
_REGISTRATION_MODULE_NAMES = {  # the pre-0.7 module `lrf_jax.registration`, outside `__all__`
    "options": ("ESTIMATORS", "KEYPOINTS"),
    "refine": ("fine_distance", "ICP_FINE_FACTOR", "ICP_FINE_MIN_MR", "ICP_POINTS"),
    "rivals": ("GRAPH_ANGLE_DEG", "GRAPH_SEEDS", "GRAPH_CONSENSUS", "GRAPH_NMS_RADII"),
    "evidence": ("VERDICT_FACTOR", "VERDICT_MARGIN", "VERDICT_CONTRAST", "VERDICT_FITNESS",
                 "VERDICT_GRAPH_FACTOR", "VERDICT_GRAPH_MARGIN", "VERDICT_GRAPH_FITNESS",
                 "CHANCE_SHUFFLES", "RIVAL_DEG", "Evidence", "overlap_contrast", "verdict"),
}
RENAMED: dict[str, str] = {
    "lrf_jax.io.cloud.read_kitti_bin": "lrf_jax.io.sweeps.read_kitti_bin",
    **{f"lrf_jax.geometry.{n}": f"lrf_jax.geometry.ops.{n}" for n in _OPS_HELPERS},
    "lrf_jax.geometry.Array": "jax.Array",  # 0.7 forwarded it to ops, which no longer had it
    **{f"lrf_jax.registration.{n}": f"lrf_jax.registration.{home}.{n}"
       for home, names in _REGISTRATION_MODULE_NAMES.items() for n in names},
    # "neighbour" -> "neighbor", one name per radius fraction
    "lrf_jax.frames.host_path.HOST_NEIGHBOUR_BUDGET":
        "lrf_jax.frames.host_path.HOST_NEIGHBOR_BUDGET",
    "lrf_jax.frames.board.MARGIN": "lrf_jax.frames.board.MARGIN_RATIO",
    "lrf_jax.frames.board.MIN_Z_NEIGHBOURS": "lrf_jax.frames.board.MIN_Z_NEIGHBORS",
    "lrf_jax.frames.flare.MARGIN": "lrf_jax.frames.flare.MARGIN_RATIO",
    "lrf_jax.frames.flare.MIN_Z_NEIGHBOURS": "lrf_jax.frames.flare.MIN_Z_NEIGHBORS",
    "lrf_jax.frames.flare.MIN_TANGENT_NEIGHBOURS": "lrf_jax.frames.flare.MIN_TANGENT_NEIGHBORS",
    "lrf_jax.frames.lrf_net.MIN_Z_NEIGHBOURS": "lrf_jax.frames.lrf_net.MIN_Z_NEIGHBORS",
    "lrf_jax.frames.lrf_net_plus.AREA_NEIGHBOURS": "lrf_jax.frames.lrf_net_plus.AREA_NEIGHBORS",
    "lrf_jax.frames.mian.MIN_NEIGHBOURS": "lrf_jax.frames.mian.MIN_NEIGHBORS",
    "lrf_jax.frames.ps.CONTOUR_RATIO": "lrf_jax.frames.ps.MARGIN_RATIO",
    "lrf_jax.frames.shot.MIN_NEIGHBOURS": "lrf_jax.frames.shot.MIN_NEIGHBORS",
    # the registry's verb (`register` means aligning scans)
    "lrf_jax.register_method": "lrf_jax.add_method",
    "lrf_jax.frames.register_method": "lrf_jax.frames.add_method",
    "lrf_jax.frames.register": "lrf_jax.frames.add_method",
    "lrf_jax.descriptors.DescriptorSpec.host_fn":
        "lrf_jax.descriptors.DescriptorSpec.host_descriptors",
    # moved in 0.8, without an alias: the weight network's inference half left the training
    # package (frames no longer import learning); its initialisation stayed
    **{f"lrf_jax.learning.model.{n}": f"lrf_jax.frames.weights.{n}" for n in _WEIGHTS_NAMES},
    "lrf_jax.frames.ablation.init_variant_params": "lrf_jax.learning.model.init_variant_params",
    # moved in 0.8: `register` split into its options, stages, rivals, ICP stage and result
    **{f"lrf_jax.registration.pipeline.{n}": f"lrf_jax.registration.{home}.{n}"
       for home, names in (("refine", ("ICP_POINTS", "ICP_FINE_FACTOR", "ICP_FINE_MIN_MR",
                                       "fine_distance", "overlap_points")),
                           ("rivals", ("GRAPH_ANGLE_DEG", "GRAPH_SEEDS", "GRAPH_CONSENSUS",
                                       "GRAPH_NMS_RADII", "REST_FACTOR")),
                           ("options", ("ESTIMATORS", "KEYPOINTS")))
       for n in names},
    # lrf-frames' computation left the command line (the data-set layer runs it too)
    **{f"lrf_jax.cli.frames.{n}": f"lrf_jax.batch.scan_frames.{n}"
       for n in ("select_keypoints", "read_transform", "pair_keypoints")},
    "lrf_jax.geometry.cloud.CloudInput": "lrf_jax.geometry.cloud.CheckedCloud",
    # moved in 0.9: ICP's target normals left the ICP module (no module over 600 lines)
    **{f"lrf_jax.registration.icp_host.{n}": f"lrf_jax.registration.icp_normals.{n}"
       for n in ("NORMAL_RADIUS_RATIO", "NORMAL_RADIUS_SPACING", "estimate_target_normals",
                 "normal_radius")},
    # 0.9: each host fast path on every neighbor is data of its method's spec (a
    # `host_path.BallKernel`), no longer a wrapper function of the method's module
    **{f"lrf_jax.frames.{m}.{m}_frames_host": f"lrf_jax.frames.{m}.SPEC.host_frames"
       for m in ("board", "flare", "gframes", "mian", "ps", "rops", "shot", "toldi")},
}


@pytest.fixture
def this_checkout_only(monkeypatch):
  """Imports resolve in this checkout's lrf_jax alone: a meta-path finder that answers for
  `lrf_jax` from another folder (the editable install of another checkout in the same
  environment) would otherwise answer for each module this checkout no longer has."""
  import lrf_jax
  here = Path(lrf_jax.__file__).resolve().parent
  for finder in list(sys.meta_path):
    try:
      spec = finder.find_spec("lrf_jax", None)
    except Exception:  # a finder that cannot answer is left in place
      continue
    if spec is not None and spec.origin and Path(spec.origin).resolve().parent != here:
      monkeypatch.setattr(sys, "meta_path", [f for f in sys.meta_path if f is not finder])


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_module_path_does_not_import(old, this_checkout_only, monkeypatch):
  for name in [n for n in sys.modules if n == old or n.startswith(old + ".")]:
    monkeypatch.delitem(sys.modules, name)  # loaded earlier through another finder
  with pytest.raises(ModuleNotFoundError):
    module = importlib.import_module(old)
    pytest.fail(f"{old} still imports (from {getattr(module, '__file__', None)} or "
                f"{list(getattr(module, '__path__', []))}; a stale folder left behind?)")


@pytest.mark.parametrize("old", sorted(o for o in MOVED if o.count(".") == 1))
def test_old_module_is_no_attribute_of_the_package(old):
  import lrf_jax
  with pytest.raises(AttributeError):
    getattr(lrf_jax, old.removeprefix("lrf_jax."))


@pytest.mark.parametrize("new", sorted(set(MOVED.values())))
def test_new_home_exists(new):
  assert importlib.util.find_spec(new) is not None, new


def _resolve(dotted: str):
  """The object `dotted` names: its longest importable module prefix, then attributes."""
  parts = dotted.split(".")
  for i in range(len(parts), 0, -1):
    try:
      obj = importlib.import_module(".".join(parts[:i]))
    except ModuleNotFoundError:
      continue
    for name in parts[i:]:
      obj = getattr(obj, name)
    return obj
  raise ModuleNotFoundError(dotted)


@pytest.mark.parametrize("old", sorted(RENAMED))
def test_old_name_does_not_resolve(old, this_checkout_only):
  parent = _resolve(old.rpartition(".")[0])  # the module (or class) is there, the name is not
  with pytest.raises(AttributeError):
    getattr(parent, old.rpartition(".")[2])


@pytest.mark.parametrize("old", sorted(RENAMED))
def test_new_name_resolves(old):
  _resolve(RENAMED[old])  # raises if it does not (`host_descriptors`' class default is None)


def test_the_registry_verb_is_add_method():
  import lrf_jax
  from lrf_jax.frames import spec
  assert lrf_jax.add_method is lrf_jax.frames.add_method is spec.add_method


def _sources() -> list[Path]:
  files = [*(ROOT / "lrf_jax").rglob("*.py"), *(ROOT / "tests").rglob("*.py"),
           *(ROOT / "benchmarks").glob("*.py"), *(ROOT / "tools").rglob("*.py"),
           ROOT / "train.py", ROOT / "evaluate.py"]
  return [f for f in files if f != Path(__file__).resolve()]


def _old(name: str) -> bool:
  return any(name == o or name.startswith(o + ".") for o in MOVED)


def test_nothing_of_ours_mentions_an_old_path():
  found = []
  for path in _sources():
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.Import):
        found += [f"{path}:{node.lineno} {a.name}" for a in node.names if _old(a.name)]
      elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        names = [f"{node.module}.{a.name}" for a in node.names]
        found += [f"{path}:{node.lineno} {n}" for n in [node.module, *names] if _old(n)]
      elif isinstance(node, ast.Constant) and isinstance(node.value, str):
        found += [f"{path}:{node.lineno} {m}" for m in re.findall(r"lrf_jax\.[\w.]+", node.value)
                  if _old(m)]
  for doc in (ROOT / "README.md", ROOT / "benchmarks" / "README.md"):
    found += [f"{doc.name} {m}" for m in re.findall(r"lrf_jax\.[\w.]+", doc.read_text())
              if _old(m)]
  assert found == []
