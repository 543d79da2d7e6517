"""Many scans into one model: `register_all(scans) -> MultiwayResult`.

  pipeline.py    `register_all`: candidates, the pairwise stage, the pose graph, the joint ICP
  options.py     `MultiwayOptions`: the pair options and the graph's, every default once
  candidates.py  which pairs are registered (all of a few scans; neighbours and D2 loop closures)
  tasks.py       the pairwise stage as tasks on an engine, each pair's record kept
  pose_graph.py  the robust pose graph over the pairs' edges
  joint_icp.py   every accepted pair's point-to-plane residuals, all poses at once
  result.py      `MultiwayResult`, `MultiwayEdge`
  outputs.py     the output folder: poses, edges.tsv, merged.ply, the manifest
  figures.py     merged.png and graph.png

The package sits above `lrf_jax.registration` (it registers each pair with `register`'s stages)
and below `lrf_jax.batch` and the command lines. The names below are its interface; every other
name is imported from its module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
  from lrf_jax.multiway.candidates import candidate_pairs
  from lrf_jax.multiway.joint_icp import refine_poses
  from lrf_jax.multiway.pipeline import register_all
  from lrf_jax.multiway.result import MultiwayEdge, MultiwayResult

__all__ = ["MultiwayEdge", "MultiwayResult", "candidate_pairs", "refine_poses", "register_all"]


def __getattr__(name: str) -> Any:
  """The names above, loaded on first use (`lrf-register --help` loads no registration code)."""
  if name == "candidate_pairs":
    from lrf_jax.multiway import candidates
    return candidates.candidate_pairs
  if name == "refine_poses":
    from lrf_jax.multiway import joint_icp
    return joint_icp.refine_poses
  if name == "register_all":
    from lrf_jax.multiway import pipeline
    return pipeline.register_all
  if name in ("MultiwayEdge", "MultiwayResult"):
    from lrf_jax.multiway import result
    return getattr(result, name)
  raise AttributeError(f"module 'lrf_jax.multiway' has no attribute {name!r}")
