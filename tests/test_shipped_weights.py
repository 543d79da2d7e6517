"""The shipped LRF-Net weights: they load, are the default, and beat TOLDI on noisy BR."""

import json

import jax
import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets
from lrf_jax.evaluation import MethodRun, evaluate_pair
from lrf_jax.model import DEFAULT_WEIGHTS, WEIGHTS_DIR, load_params


def test_shipped_weights_are_the_default_and_documented():
  assert DEFAULT_WEIGHTS.exists()
  shipped = load_params(DEFAULT_WEIGHTS)
  for a, b in zip(_leaves(shipped), _leaves(lrf_jax.default_params())):
    np.testing.assert_array_equal(a, b)
  card = json.loads((WEIGHTS_DIR / "lrf_net.json").read_text())
  assert card["config"]["name"] == "default" and card["config"]["epochs"] == 20
  assert "selected_val_meancos" in card
  plus = json.loads((WEIGHTS_DIR / "lrf_net_plus.json").read_text())
  assert plus["config"]["x_mode"] == "softmax" and plus["config"]["name"] == "plus_soft"
  assert lrf_jax.METHODS["lrf_net_plus"].weights == "lrf_net_plus"
  for a, b in zip(_leaves(load_params(WEIGHTS_DIR / "lrf_net_plus.msgpack")),
                  _leaves(lrf_jax.default_params("lrf_net_plus"))):
    np.testing.assert_array_equal(a, b)


def test_default_params_first_called_inside_jit_do_not_leak_tracers():
  from lrf_jax.model import _default_params_cached
  _default_params_cached.cache_clear()
  jax.jit(lambda x: x + jax.tree.leaves(lrf_jax.default_params("lrf_net_plus"))[0].sum())(1.0)
  for leaf in jax.tree.leaves(lrf_jax.default_params("lrf_net_plus")):
    assert not isinstance(leaf, jax.core.Tracer)
  jax.jit(lambda x: x + jax.tree.leaves(lrf_jax.default_params("lrf_net_plus"))[0].sum())(2.0)


def _leaves(tree):
  return [np.asarray(x) for x in jax.tree.leaves(tree)]


def test_bad_parameter_file_is_refused(tmp_path):
  bad = tmp_path / "w.msgpack"
  bad.write_bytes(b"not msgpack at all")
  with pytest.raises(ValueError, match="w.msgpack"):
    load_params(bad)
  with pytest.raises(FileNotFoundError):
    load_params(tmp_path / "missing.msgpack")


@pytest.mark.parametrize("noise", [0.3, 0.5])
def test_shipped_weights_beat_toldi_on_noisy_br(data_root, noise):
  """The weights must beat TOLDI (the LRF they build on) on BR; 3 scenes x 300 keypoints."""
  runs = [MethodRun("lrf_net", "lrf_net"), MethodRun("toldi", "toldi")]
  got = {"lrf_net": [], "toldi": []}
  for scene in (0, 3, 5):  # bunny, armadillo, statuette
    pair = datasets.load_br_pair(scene, noise, data_root)
    for rec in evaluate_pair(pair, runs, experiment="t", n_keypoints=300):
      got[rec["method"]].append(rec["meancos"])
  assert np.mean(got["lrf_net"]) > np.mean(got["toldi"]), got


def test_lrf_net_plus_beats_lrf_net_and_uniform_on_noisy_br(data_root):
  """The z sign over the support (lrf_net_plus) removes most z flips on noisy BR."""
  runs = [MethodRun(m, m) for m in ("lrf_net_plus", "lrf_net", "uniform")]
  got = {r.label: [] for r in runs}
  for scene in (0, 3, 5):
    pair = datasets.load_br_pair(scene, 0.5, data_root)
    for rec in evaluate_pair(pair, runs, experiment="t", n_keypoints=300):
      got[rec["method"]].append(rec["meancos"])
  mean = {k: np.mean(v) for k, v in got.items()}
  assert mean["lrf_net_plus"] > mean["uniform"] > mean["lrf_net"], mean
