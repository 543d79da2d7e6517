"""LRF methods behind one registry: `METHODS[name]` describes how to compute and what is needed.

Every method lives in one module of this package: its pure jitted frame function, its host
`prepare` hook when it has one, and its `MethodSpec` (`SPEC`). This file only collects them, in
the order `METHODS` lists them. Every method returns `(frames (N, 3, 3), valid (N,))` with rows
x, y, z, det +1, identity where invalid; `lrf_jax.compute_frames` is the one public entry that
does the search, the preparation and the jitted, chunked evaluation for any of them. The LRF-Net
family shares its construction (`lrf_net.py`: lrf_net and uniform; `ablation.py`: the paper's
variants; `lrf_net_plus.py`: its host hooks and entry; `weights.py`: the weight network's
forward pass, parameter files and shipped weights). `metrics.py`: MeanCos, how repeatable frames are.
"""

from __future__ import annotations

from lrf_jax.frames import (ablation, board, flare, gframes, lrf_net, lrf_net_plus, mian, ps,
                            rops, shot, toldi)
from lrf_jax.frames.board import board_frames
from lrf_jax.frames.flare import flare_frames
from lrf_jax.frames.gframes import gframes_frames
from lrf_jax.frames.lrf_net import lrf_net_frames, uniform_frames
from lrf_jax.frames.mian import mian_frames
from lrf_jax.frames.ps import ps_frames
from lrf_jax.frames.rops import rops_frames
from lrf_jax.frames.shot import shot_frames
from lrf_jax.frames.spec import (DEFAULT_METHOD, RADIUS_MR, KEYPOINT, SLOT, TRIANGLE, TRIANGLE_MASK, METHODS,
                                 MethodRegistry, MethodSpec, add_method, method_spec)
from lrf_jax.frames.toldi import toldi_frames

for _spec in (lrf_net.SPEC, ablation.SPEC, lrf_net_plus.SPEC, lrf_net.UNIFORM_SPEC, toldi.SPEC,
              mian.SPEC, shot.SPEC, rops.SPEC, board.SPEC, flare.SPEC, ps.SPEC, gframes.SPEC):
  add_method(_spec)
del _spec

__all__ = ["DEFAULT_METHOD", "RADIUS_MR", "KEYPOINT", "METHODS", "MethodRegistry", "MethodSpec", "SLOT", "TRIANGLE",
           "TRIANGLE_MASK", "add_method", "method_spec", "board_frames", "flare_frames", "gframes_frames", "lrf_net_frames",
           "mian_frames", "ps_frames", "rops_frames", "shot_frames", "toldi_frames", "uniform_frames"]
