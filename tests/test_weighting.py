"""Weighting strategies against hand computations."""

import math

import jax
import numpy as np
import pytest

from sljax.losses import weighting as wt


def test_constant_weights():
  np.testing.assert_array_equal(wt.constant_weights("stl"), [0, 1])
  np.testing.assert_array_equal(wt.constant_weights("cg_a"), [10, 1])
  np.testing.assert_array_equal(wt.constant_weights("cg_b"), [0.5, 1])
  with pytest.raises(ValueError):
    wt.constant_weights("epr")


def test_dwa_first_two_epochs_are_one():
  np.testing.assert_array_equal(wt.dwa_weights([]), [1, 1])
  np.testing.assert_array_equal(wt.dwa_weights([(3.0, 2.0)]), [1, 1])
  np.testing.assert_array_equal(wt.epoch_weights("epr", [(3.0, 2.0)]), [1, 1])


def test_dwa_hand_computed():
  history = [(9.0, 9.0), (4.0, 1.0), (2.0, 0.8)]  # only the last two epochs count
  w_sl, w_d = 2.0 / 4.0, 0.8 / 1.0
  e_sl, e_d = math.exp(2 * w_sl), math.exp(2 * w_d)
  expect = [2 * e_sl / (e_sl + e_d), 2 * e_d / (e_sl + e_d)]
  got = wt.dwa_weights(history)
  np.testing.assert_allclose(got, expect, rtol=1e-6)
  np.testing.assert_allclose(got.sum(), 2.0, rtol=1e-6)
  # Equal ratios -> equal weights.
  np.testing.assert_allclose(wt.dwa_weights([(2, 4), (1, 2)]), [1, 1], rtol=1e-6)


def test_uncertainty_loss_value_and_gradient_wrt_log_sigma():
  l_sl, l_d, s_sl, s_d = 0.7, 3.0, 0.3, -0.2
  total, w = wt.uncertainty_loss(l_sl, l_d, s_sl, s_d)
  sig_sl, sig_d = math.exp(s_sl), math.exp(s_d)
  expect = 0.5 / (2 * sig_sl**2) * l_sl + 1 / (2 * sig_d**2) * l_d + math.log(sig_sl) + math.log(sig_d)
  np.testing.assert_allclose(total, expect, rtol=1e-6)
  np.testing.assert_allclose(w, [0.5 / (2 * sig_sl**2), 1 / (2 * sig_d**2)], rtol=1e-6)
  g_sl, g_d = jax.grad(lambda a, b: wt.uncertainty_loss(l_sl, l_d, a, b)[0], argnums=(0, 1))(s_sl, s_d)
  # d/ds [c * exp(-2s) * L + s] = -2 c exp(-2s) L + 1
  np.testing.assert_allclose(g_sl, -2 * 0.25 * math.exp(-2 * s_sl) * l_sl + 1, rtol=1e-5)
  np.testing.assert_allclose(g_d, -2 * 0.5 * math.exp(-2 * s_d) * l_d + 1, rtol=1e-5)


def test_uncertainty_init_and_epoch_weights():
  u = wt.init_uncertainty()
  assert float(u["log_sigma_sl"]) == 0.0 and float(u["log_sigma_disp"]) == 0.0
  np.testing.assert_array_equal(wt.epoch_weights("unc", [(1, 1), (2, 2), (3, 3)]), [1, 1])
  np.testing.assert_array_equal(wt.epoch_weights("cg_a", []), [10, 1])


def test_weighted_loss():
  total, w = wt.weighted_loss(2.0, 3.0, np.array([10.0, 1.0]))
  assert float(total) == 23.0
  np.testing.assert_array_equal(w, [10, 1])


def test_step_weights_vectors():
  np.testing.assert_array_equal(wt.step_weights("cg_a", []), [10, 1, 0])
  np.testing.assert_array_equal(wt.step_weights("stl", []), [0, 1, 0])
  np.testing.assert_array_equal(wt.step_weights("unc", [(1, 1), (2, 2)]), [1, 1, 1])
  np.testing.assert_allclose(wt.step_weights("epr", [(4, 1), (2, 0.8)])[:2],
                             wt.dwa_weights([(4, 1), (2, 0.8)]))


def test_combined_loss_matches_each_strategy_and_zero_sigma_gradient():
  l_sl, l_d = 0.7, 3.0
  for name in ("stl", "cg_a", "cg_b", "epr"):
    w = wt.step_weights(name, [(4, 1), (2, 0.8)])
    f = lambda a, b: wt.combined_loss(l_sl, l_d, w, a, b)[0]
    np.testing.assert_allclose(f(0.0, 0.0), w[0] * l_sl + w[1] * l_d, rtol=1e-6)
    g = jax.grad(f, argnums=(0, 1))(0.3, -0.2)
    assert float(g[0]) == 0.0 and float(g[1]) == 0.0
  w = wt.step_weights("unc", [])
  total, eff = wt.combined_loss(l_sl, l_d, w, 0.3, -0.2)
  ref_total, ref_eff = wt.uncertainty_loss(l_sl, l_d, 0.3, -0.2)
  np.testing.assert_allclose(total, ref_total, rtol=1e-6)
  np.testing.assert_allclose(eff, ref_eff, rtol=1e-6)
  # The step differentiates combined_loss: its log-sigma gradient must be unc's (hand formula).
  g = jax.grad(lambda a, b: wt.combined_loss(l_sl, l_d, w, a, b)[0], argnums=(0, 1))(0.3, -0.2)
  np.testing.assert_allclose(g, [-2 * 0.25 * math.exp(-0.6) * l_sl + 1,
                                 -2 * 0.5 * math.exp(0.4) * l_d + 1], rtol=1e-5)
