"""The shipped LRF-Net weights: they load, are the default, and beat TOLDI on noisy BR."""

import json

import jax
import numpy as np
import pytest

import lrf_jax
from lrf_jax import datasets
from lrf_jax.evaluation import MethodRun, evaluate_pair
from lrf_jax.frames.weights import DEFAULT_WEIGHTS, WEIGHTS_DIR, load_params


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


def test_points_only_weights_load_and_are_documented():
  """lrf_net_plus_points.msgpack: lrf_net_plus's network trained with z from the points alone
  (preset plus_points); shipped beside the default weights, not instead of them."""
  card = json.loads((WEIGHTS_DIR / "lrf_net_plus_points.json").read_text())
  assert card["config"]["name"] == "plus_points" and card["config"]["z_view"] == "voted"
  rows = card["validation_curve"]["rows"]
  assert len(rows) == card["config"]["epochs"]
  assert card["selected_val_meancos"] == max(r[2] for r in rows)
  points = lrf_jax.default_params("lrf_net_plus_points")
  plus = lrf_jax.default_params("lrf_net_plus")
  assert jax.tree.structure(points) == jax.tree.structure(plus)
  assert all(np.isfinite(a).all() for a in _leaves(points))
  assert any(not np.array_equal(a, b) for a, b in zip(_leaves(points), _leaves(plus)))


def test_default_params_first_called_inside_jit_do_not_leak_tracers():
  from lrf_jax.frames.weights import default_params_cached
  default_params_cached.cache_clear()
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


def test_flax_free_forward_and_reader_equal_flax():
  # weights.apply_weights and weights.load_params avoid importing flax; they must be the flax
  # module's forward pass (the definition of the network) and flax's msgpack reader, on every
  # shipped file and a fresh save; apply_weights in jax.numpy, and in numpy as the host
  # kernels' weight table (float32) and the tests' reference (float64) evaluate it.
  from flax import serialization

  from lrf_jax.frames import weights as model
  from lrf_jax.learning.model import init_params
  from lrf_jax.learning.networks import WeightNet
  files = sorted(model.WEIGHTS_DIR.rglob("*.msgpack"))
  assert files
  for path in files:
    ours = model.load_params(path)
    ref = serialization.msgpack_restore(path.read_bytes())
    assert jax.tree.structure(ours) == jax.tree.structure(ref), path
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(ref)):
      assert a.dtype == b.dtype and a.shape == b.shape
      np.testing.assert_array_equal(np.asarray(a), b)
  attrs = jax.random.uniform(jax.random.key(1), (5, 7, 2), minval=-1.0, maxval=1.0)
  for widths in [(16, 32, 64), (8, 4)]:
    params = init_params(3, 2, widths)
    want = WeightNet(widths=widths).apply({"params": params}, attrs)
    np.testing.assert_allclose(model.apply_weights(params, attrs), want, rtol=1e-6, atol=1e-7)
    for dtype in (np.float32, np.float64):
      got = model.apply_weights(params, np.asarray(attrs), np, dtype)
      assert isinstance(got, np.ndarray) and got.dtype == dtype and got.shape == want.shape
      np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_inference_imports_neither_flax_nor_the_datasets(tmp_path):
  # Registering or computing frames in a fresh process must not pay for flax or the dataset
  # loaders (each a few tenths of a second of import time).
  import subprocess
  import sys
  code = ("import sys, lrf_jax, lrf_jax.registration, lrf_jax.cli.register; "
          "heavy = sorted(m for m in ('flax', 'optax', 'orbax', 'lrf_jax.datasets', 'pypcd4') "
          "if m in sys.modules); print(heavy); sys.exit(1 if heavy else 0)")
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
  assert out.returncode == 0, out.stdout + out.stderr


def test_flax_free_regressor_equals_flax():
  """The ablation's "dr" regressor: `frames.ablation.apply_regressor` (no flax) is the flax
  module's forward pass, padded points and an empty patch included."""
  from lrf_jax.frames.ablation import apply_regressor
  from lrf_jax.learning.networks import PointRegressor, init_regressor
  feats = jax.random.normal(jax.random.key(2), (4, 9, 6))
  mask = jax.random.uniform(jax.random.key(3), (4, 9)) < 0.7
  mask = mask.at[0].set(False)
  for f in (6, 3):
    params = init_regressor(5, f)
    want = PointRegressor().apply({"params": params}, feats[..., :f], mask)
    got = jax.jit(apply_regressor)(params, feats[..., :f], mask)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
