"""The verdict's evidence under learned weights other than the shipped object weights: counted on
the object weights' description of the default detector's keypoints (`stages.evidence_description`,
`stages.default_evidence`), pairwise and in multiway's features, so weights tuned on the scans
being registered cannot claim a pose the object weights' evidence does not support."""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets
from lrf_jax.frames.weights import WEIGHTS_DIR, load_params
from lrf_jax.registration import effort, stages
from lrf_jax.registration.options import DescribeOptions, resolve
from lrf_jax.registration.scan_features import describe_scan, register_scans

REPO = Path(__file__).resolve().parents[1]
KW = dict(effort="fast", n_keypoints=500, seed=0)


def _evidence(pair, params=None, **kw):
  """One pass's (matches, features, the evidence's world points and frames)."""
  prepared, features, matches = effort.one_pass(pair.model_points, pair.scene_points,
                                                resolve(None, {**KW, **kw}), params,
                                                stages.StageTimer())
  if matches.own:
    points = stages._keypoint_points(prepared, features, matches.evidence_source,
                                     matches.evidence_target)
  else:
    points = matches.evidence_points
  return matches, features, points


def test_which_descriptions_are_judged_on_other_evidence():
  assert stages.evidence_description(DescribeOptions(), None) is None
  assert stages.evidence_description(DescribeOptions(method="shot"), None) is None
  assert stages.evidence_description(DescribeOptions(method="lrf_net"), None) is None
  for described in (stages.evidence_description(DescribeOptions(weights="rooms"), None),
                    stages.evidence_description(DescribeOptions(), {"any": "params"})):
    assert described == DescribeOptions()
  radius = stages.evidence_description(DescribeOptions(weights="streets", radius_mr=20.0), None)
  assert radius == DescribeOptions(radius_mr=20.0)  # only the weights are replaced


@pytest.mark.parametrize("weights", ["rooms", "file", "params"])
def test_other_weights_are_judged_on_the_object_weights_evidence(weights, tmp_path):
  """weights="rooms", a parameter file or params: the correspondences the winner comes from
  are the run's own, the verdict's evidence exactly the default call's (world points and
  frames)."""
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  path = tmp_path / "w.msgpack"
  shutil.copy(WEIGHTS_DIR / "lrf_net.msgpack", path)  # other weights than lrf_net_plus's own
  kw = {"rooms": {"weights": "rooms"}, "file": {"weights": str(path)},
        "params": {"params": load_params(path)}}[weights]
  default, f_default, ev_default = _evidence(pair)
  other, f_other, ev_other = _evidence(pair, **kw)
  assert default.own and not other.own
  assert np.abs(f_other.frames[0][0] - f_default.frames[0][0]).max() > 1e-3  # its own frames
  assert len(ev_default[0]) > 50
  for a, b in zip(ev_default, ev_other):
    np.testing.assert_array_equal(a, b)


def test_multiway_features_carry_the_object_weights_evidence(monkeypatch):
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  mr = float(datasets.mesh_resolution(pair.model_points)[0])
  plain = describe_scan(pair.model_points, mr=mr, n_keypoints=500)
  rooms = describe_scan(pair.model_points, mr=mr, n_keypoints=500, weights="rooms")
  assert plain.evidence == () and len(rooms.evidence) == 1
  np.testing.assert_array_equal(rooms.evidence[0].side.keypoints, plain.runs[0].side.keypoints)
  np.testing.assert_array_equal(rooms.evidence[0].frames[0], plain.runs[0].frames[0])
  assert np.abs(rooms.runs[0].frames[0] - plain.runs[0].frames[0]).max() > 1e-3
  target = describe_scan(pair.scene_points, mr=mr, n_keypoints=500, weights="rooms")
  seen = []
  real = stages.with_evidence
  monkeypatch.setattr(stages, "with_evidence", lambda m, sampled, features: (
      seen.append(features), real(m, sampled, features))[1])
  reg = register_scans(rooms, target, n_keypoints=500, weights="rooms")
  assert reg.estimated and len(seen) == 1  # the verdict counted on the evidence runs
  np.testing.assert_array_equal(seen[0].frames[0][0], plain.runs[0].frames[0])
  with pytest.raises(ValueError, match=r"weights: the features were described with 'rooms'"):
    register_scans(rooms, describe_scan(pair.scene_points, mr=mr, n_keypoints=500),
                   n_keypoints=500, weights="rooms")
  own = describe_scan(pair.scene_points, mr=mr, n_keypoints=500,
                      params=load_params(WEIGHTS_DIR / "lrf_net.msgpack"))
  with pytest.raises(ValueError, match=r"params: the source was described with 0 evidence"):
    register_scans(plain, own, n_keypoints=500)


def test_the_room_weights_do_not_claim_a_flipped_room_of_their_own_scene(data_root):
  """The room weights were tuned on 3DMatch's hotel3; on a crop of its pair (benchmarks'
  hotel3/crop->30%-2, seed 0) their own pooled evidence claimed a pose 179 deg off (38
  consistent correspondences against a rival's 9). Judged on the object weights' evidence it
  is not sure."""
  sys.path.insert(0, str(REPO / "benchmarks"))
  try:
    from scene_cases import make_cases
  finally:
    sys.path.remove(str(REPO / "benchmarks"))
  case = next(c for c in make_cases(data_root, 0, kinds=("room",))
              if c.name == "hotel3/crop->30%-2")
  reg = lrf_jax.register(case.source, case.target, weights="rooms", seed=0)
  rel = reg.transform[:3, :3].T @ case.gt[:3, :3]
  degrees = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
  assert reg.success is False or degrees < 15.0, (degrees, reg.reason)
