"""Chamfer loss (eq_cham) and the Siamese training loss: values, masks, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lrf_jax
from lrf_jax.learning.losses import batched_chamfer, chamfer, siamese_loss
from lrf_jax.search.neighborhoods import build_patches
from tests.lrf_testing import random_rotation


def numpy_chamfer(a, b, reduction):
  d = np.linalg.norm(a[:, None] - b[None], axis=-1)
  ab, ba = d.min(1).mean(), d.min(0).mean()
  return {"min": min(ab, ba), "max": max(ab, ba), "sum": ab + ba}[reduction]


@pytest.mark.parametrize("reduction", ["min", "max", "sum"])
def test_chamfer_matches_bruteforce_with_masks(reduction):
  rng = np.random.default_rng(0)
  a, b = rng.normal(size=(40, 3)), rng.normal(size=(55, 3)) + 0.3
  ma, mb = rng.random(40) < 0.7, rng.random(55) < 0.6
  a_pad = np.where(ma[:, None], a, 1e3)  # padding holds garbage far away
  got = jax.jit(chamfer, static_argnums=4)(a_pad, ma, b, mb, reduction)
  np.testing.assert_allclose(got, numpy_chamfer(a[ma], b[mb], reduction), rtol=1e-5)


def test_chamfer_is_asymmetric_min_of_directed_means():
  a = np.array([[0.0, 0, 0]])
  b = np.array([[0.0, 0, 0], [3.0, 0, 0]])
  one, two = np.ones(1, bool), np.ones(2, bool)
  assert float(chamfer(a, one, b, two, "min")) == 0.0
  np.testing.assert_allclose(chamfer(a, one, b, two, "max"), 1.5)


def test_batched_chamfer_equals_loop():
  rng = np.random.default_rng(1)
  a, b = rng.normal(size=(4, 16, 3)), rng.normal(size=(4, 16, 3))
  m = rng.random((4, 16)) < 0.8
  got = batched_chamfer(a, m, b, m, "min")
  want = [numpy_chamfer(a[i][m[i]], b[i][m[i]], "min") for i in range(4)]
  np.testing.assert_allclose(got, want, rtol=1e-5)


def test_gradient_finite_at_coincident_points():
  a = jnp.array(np.random.default_rng(2).normal(size=(30, 3)))
  m = jnp.ones(30, bool)
  for red in ("min", "max", "sum"):
    g = jax.grad(lambda x: chamfer(x, m, a, m, red))(a)  # noqa: B023 (called in this iteration)
    assert np.isfinite(np.asarray(g)).all()


def _pair_patches(pts, kp, r, rot, t, noise, seed):
  scene = pts @ rot.T + t + np.random.default_rng(seed).normal(scale=noise, size=pts.shape)
  return (build_patches(pts, kp, r, 64, seed=1), build_patches(scene, kp, r, 64, seed=2))


def test_siamese_loss_gradient_matches_finite_differences(br_bunny):
  pts, _, mr, xf = br_bunny
  kp = np.random.default_rng(0).choice(len(pts), 8, replace=False)
  with jax.enable_x64(True):
    pm, ps = _pair_patches(pts, kp, 15 * mr, xf[:3, :3], xf[:3, 3], 0.3 * mr, 0)
    pm, ps = (jax.tree.map(lambda x: jnp.asarray(x, jnp.float64) if x.dtype == np.float32
                           else jnp.asarray(x), p) for p in (pm, ps))
    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), lrf_jax.init_params(0))
    loss_fn = lambda p: siamese_loss(p, pm, ps)[0]
    grads = jax.grad(loss_fn)(params)
    leaves, tree = jax.tree.flatten(params)
    gleaves = jax.tree.leaves(grads)
    assert all(np.isfinite(np.asarray(g)).all() for g in gleaves)
    rng = np.random.default_rng(0)
    direction = [jnp.asarray(rng.normal(size=l.shape)) for l in leaves]
    # A tiny step: the loss is piecewise smooth (ReLU kinks, nearest-neighbor switches), and
    # finite differences only agree with autodiff inside one smooth piece.
    eps = 1e-9
    plus = jax.tree.unflatten(tree, [l + eps * d for l, d in zip(leaves, direction)])
    minus = jax.tree.unflatten(tree, [l - eps * d for l, d in zip(leaves, direction)])
    fd = (loss_fn(plus) - loss_fn(minus)) / (2 * eps)
    ad = sum(jnp.sum(g * d) for g, d in zip(gleaves, direction))
    np.testing.assert_allclose(ad, fd, rtol=1e-4, atol=1e-10)
    assert abs(float(ad)) > 0  # the loss does depend on the weights


def test_siamese_loss_zero_for_noise_free_pair_and_finite_grad(br_bunny):
  """Same neighbors on both sides (same seed) and a rigid motion: frames repeat, loss ~ 0."""
  pts, _, mr, xf = br_bunny
  kp = np.random.default_rng(1).choice(len(pts), 16, replace=False)
  scene = pts @ xf[:3, :3].T + xf[:3, 3]
  pm = jax.tree.map(jnp.asarray, build_patches(pts, kp, 15 * mr, 64, seed=1))
  ps = jax.tree.map(jnp.asarray, build_patches(scene, kp, 15 * mr, 64, seed=1))
  params = lrf_jax.init_params(0)
  (loss, aux), g = jax.value_and_grad(siamese_loss, has_aux=True)(params, pm, ps)
  assert float(loss) < 1e-3 * mr
  assert bool(aux["valid"].all())
  assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(g))


def test_loss_is_invariant_to_rigid_motion_of_either_side(br_bunny):
  pts, _, mr, xf = br_bunny
  kp = np.random.default_rng(2).choice(len(pts), 16, replace=False)
  pm, ps = _pair_patches(pts, kp, 15 * mr, xf[:3, :3], xf[:3, 3], 0.3 * mr, 3)
  rot = random_rotation(9)
  pm2 = pm._replace(offsets=pm.offsets @ rot.T.astype(np.float32),
                    z_cov=(rot @ pm.z_cov @ rot.T).astype(np.float32),
                    z_mean=(pm.z_mean @ rot.T).astype(np.float32))
  params = lrf_jax.init_params(0)
  to = lambda p: jax.tree.map(jnp.asarray, p)
  l1, _ = siamese_loss(params, to(pm), to(ps))
  l2, _ = siamese_loss(params, to(pm2), to(ps))
  np.testing.assert_allclose(l1, l2, rtol=1e-4)
