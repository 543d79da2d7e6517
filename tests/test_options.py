"""`RegisterOptions`: every default of `register` held once, checked on construction, read by
`register`, its stages and every command line that registers."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from lrf_jax import datasets
from lrf_jax.registration import options as options_module
from lrf_jax.registration import pipeline, refine, stages
from lrf_jax.registration.evidence import Evidence, decide
from lrf_jax.registration.options import DEFAULTS, FIELDS, RegisterOptions

CLI = Path(__file__).resolve().parents[1] / "lrf_jax" / "cli"


@pytest.fixture(scope="module")
def demo():
  return datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)


def _register_parser_defaults() -> RegisterOptions:
  """The options lrf-register passes to `register` when given no flag."""
  from lrf_jax.cli.register import build_parser, register_options
  return options_module.resolve(None, register_options(build_parser().parse_args(["a", "b"])))


def test_every_option_is_a_flag_of_lrf_register_with_the_options_default():
  assert _register_parser_defaults() == DEFAULTS


def test_a_default_changed_in_the_options_changes_register_and_every_command_line(monkeypatch):
  changed = RegisterOptions(radius_mr=12.5, n_keypoints=1234, icp_mode="point_to_point",
                            icp_fine=False, seed=7)
  monkeypatch.setattr(options_module, "DEFAULTS", changed)
  assert _register_parser_defaults() == changed
  from lrf_jax.cli import batch as batch_cli
  assert options_module.resolve(None, batch_cli._register_options([])) == changed  # lrf-batch
  from lrf_jax.cli.register import build_parser
  text = " ".join(build_parser().format_help().split())
  assert "(default: 12.5)" in text and "at most 1234" in text
  assert options_module.resolve(None, {}) is changed  # what `register` reads when given none


def test_the_options_are_checked_once_at_construction_and_name_the_field():
  with pytest.raises(ValueError, match=r"^radius_mr: expected a positive"):
    RegisterOptions(radius_mr=-1.0)
  with pytest.raises(ValueError, match=r"^estimator: expected one of"):
    DEFAULTS.with_overrides(estimator="magic")
  with pytest.raises(ValueError, match=r"^method: unknown LRF method"):
    RegisterOptions(method="nope")
  with pytest.raises(ValueError, match=r"^source_viewpoint:"):
    RegisterOptions(source_viewpoint=[1.0, 2.0])
  with pytest.raises(TypeError, match="unknown option 'radius'"):
    DEFAULTS.with_overrides(radius=3.0)
  with pytest.raises(dataclasses.FrozenInstanceError):
    DEFAULTS.seed = 3  # type: ignore[misc]


def test_the_options_are_plain_data_that_pickle_and_compare():
  opts = RegisterOptions(source_viewpoint=np.array([0, 0, 1]), ratio=0.9, n_keypoints=500)
  assert opts.source_viewpoint == (0.0, 0.0, 1.0)
  assert pickle.loads(pickle.dumps(opts)) == opts
  assert len(pickle.dumps(opts)) < 1000
  assert hash(opts) == hash(RegisterOptions(source_viewpoint=(0, 0, 1), ratio=0.9,
                                            n_keypoints=500))
  assert set(opts.as_dict()) == set(FIELDS)


def test_the_default_method_and_descriptor_are_registered():
  """`RegisterOptions` skips the registries for the defaults (they load every method)."""
  from lrf_jax.descriptors import DESCRIPTORS
  from lrf_jax.frames import METHODS
  assert DEFAULTS.method in METHODS and DEFAULTS.descriptor in DESCRIPTORS


def test_register_with_options_equals_register_with_keywords(demo):
  kw = dict(mr=demo.mr, n_keypoints=400, n_correspondences=200, seed=3)
  a = pipeline.register(demo.model_points, demo.scene_points, **kw)
  b = pipeline.register(demo.model_points, demo.scene_points, RegisterOptions(**kw))
  c = pipeline.register(demo.model_points, demo.scene_points, RegisterOptions(seed=3),
                        mr=demo.mr, n_keypoints=400, n_correspondences=200)
  for other in (b, c):
    np.testing.assert_array_equal(a.transform, other.transform)
    assert (a.success, a.reason) == (other.success, other.reason)
  with pytest.raises(TypeError, match="unknown option"):
    pipeline.register(demo.model_points, demo.scene_points, n_keypoint=400)


def test_the_stages_one_by_one_give_registers_result(demo):
  """The stages are the pipeline: run by hand, with their typed results, they give `register`'s
  transform and verdict bit for bit."""
  opts = RegisterOptions(mr=demo.mr, n_keypoints=400)  # the default count: its own evidence
  reg = pipeline.register(demo.model_points, demo.scene_points, opts)
  timer = stages.StageTimer()
  prepared = stages.prepare(demo.model_points, demo.scene_points, opts)
  assert isinstance(prepared, stages.Prepared) and prepared.mr == demo.mr
  features = stages.describe(prepared, opts.description, None, timer)
  assert features.frames[0][0].shape == (400, 3, 3)
  matches = stages.match(features, opts)
  assert matches.own and len(matches.source) == len(reg.correspondences)
  hyps = stages.hypothesize(prepared, features, matches, opts.hypotheses)
  assert hyps is not None and len(hyps.rotations) == len(hyps.counts)
  verified = stages.verify(prepared, hyps, opts.hypotheses, opts.icp.icp_mr, matches.own)
  refined = refine.refine(prepared, verified, opts.icp, timer)
  np.testing.assert_array_equal(refined.transform, reg.transform)
  evidence = Evidence(n_inliers=int(verified.evidence_mask.sum()), chance_inliers=hyps.chance,
                      rival_inliers=verified.rival, fitness=refined.fitness, contrast=0.0,
                      estimator=opts.estimator, degeneracy=refined.degeneracy,
                      free_direction=refined.free_direction)
  assert decide(evidence).success == reg.success
  assert set(timer.seconds) == {"frames", "descriptors", "icp", "verification"}


def _literal_defaults(path: Path) -> list[str]:
  """`default=` values of argparse options that are literals other than None, False, [] and
  argparse.SUPPRESS."""
  out = []
  for node in ast.walk(ast.parse(path.read_text())):
    if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
      for kw in node.keywords:
        if kw.arg == "default" and isinstance(kw.value, ast.Constant) and kw.value.value not in (
            None, False):
          out.append(f"{path.name}:{node.lineno} {kw.value.value!r}")
  return out


def test_the_command_lines_type_almost_no_default_themselves():
  found = [d for path in sorted(CLI.glob("*.py")) for d in _literal_defaults(path)]
  assert len(found) <= 3, found


def test_register_flags_read_back_as_registers_keywords():
  from lrf_jax.cli.options import add_register_flags, register_overrides, register_problem
  ap = argparse.ArgumentParser()
  add_register_flags(ap)
  args = ap.parse_args(["--keypoints", "iss", "--icp", "point_to_point", "--correspondences",
                        "300", "--no-icp-fine", "--source-viewpoint", "0", "0", "1"])
  kw = register_overrides(args)
  assert kw["keypoints"] == "iss" and kw["icp_mode"] == "point_to_point"
  assert kw["n_correspondences"] == 300 and kw["icp_fine"] is False
  assert kw["source_viewpoint"] == (0.0, 0.0, 1.0)
  assert register_problem(ap.parse_args(["--radius-mr", "-2"])) == (
      "--radius-mr: expected a positive number of mesh resolutions, got -2.0")
  assert register_problem(ap.parse_args(["--keypoints", "0"])).startswith("--keypoints:")
