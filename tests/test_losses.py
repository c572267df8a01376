"""Losses against naive float64 NumPy loops and hand computations."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sljax.losses import disparity as dl
from sljax.losses import sl as sll


def _ref_sl(logits, targets, lam=1 / 80):
  """Loop reference: BCE over known targets + lam * mean squared [-1,0,1] derivative diff."""
  logits = logits.astype(np.float64)
  b, h, w, t = logits.shape
  bce_sum, bce_n, g_sum, g_n = 0.0, 0, 0.0, 0
  p = 1 / (1 + np.exp(-logits))
  for i in range(b):
    for y in range(h):
      for c in range(t):
        for x in range(w):
          tv = targets[i, y, x, c]
          if np.isfinite(tv):
            bce_sum += -(tv * math.log(p[i, y, x, c]) + (1 - tv) * math.log(1 - p[i, y, x, c]))
            bce_n += 1
          if 1 <= x <= w - 2:
            a, z = targets[i, y, x + 1, c], targets[i, y, x - 1, c]
            if np.isfinite(a) and np.isfinite(z):
              d_gt = a - z
              d_pr = p[i, y, x + 1, c] - p[i, y, x - 1, c]
              g_sum += (d_pr - d_gt) ** 2
              g_n += 1
  return bce_sum / bce_n, g_sum / g_n, bce_sum / bce_n + lam * g_sum / g_n


def test_sl_loss_matches_loop_reference_with_unknown_targets():
  rng = np.random.default_rng(0)
  logits = rng.normal(0, 3, (2, 3, 7, 4)).astype(np.float32)
  targets = (rng.random((2, 3, 7, 4)) > 0.5).astype(np.float32)
  targets[rng.random(targets.shape) < 0.2] = np.nan
  bce, grad, total = _ref_sl(logits, targets)
  np.testing.assert_allclose(sll.sl_bce(logits, targets), bce, rtol=1e-5)
  np.testing.assert_allclose(sll.sl_grad_l2(logits, targets), grad, rtol=1e-5)
  np.testing.assert_allclose(sll.sl_loss(logits, targets), total, rtol=1e-5)


def test_bce_stable_for_huge_logits_and_hand_value():
  logits = jnp.array([[[[100.0], [-100.0], [0.0]]]])  # 1x1x3x1
  targets = jnp.array([[[[1.0], [0.0], [1.0]]]])
  # Exact: ~0, ~0, log 2 -> mean log(2) / 3.
  np.testing.assert_allclose(sll.sl_bce(logits, targets), math.log(2) / 3, rtol=1e-6)
  g = jax.grad(lambda z: sll.sl_loss(z, targets))(logits)
  assert np.all(np.isfinite(g))


def test_sl_loss_all_unknown_is_zero_and_gradient_finite():
  logits = jnp.ones((1, 2, 5, 2))
  targets = jnp.full((1, 2, 5, 2), jnp.nan)
  assert float(sll.sl_loss(logits, targets)) == 0.0
  assert np.all(np.isfinite(jax.grad(lambda z: sll.sl_loss(z, targets))(logits)))


def test_disparity_mask_drops_inf_negative_and_out_of_range():
  gt = jnp.array([[1.0, jnp.inf, -1.0, 15.9, 16.0, 40.0, jnp.nan, 0.0]])
  np.testing.assert_array_equal(dl.disparity_mask(gt, 16),
                                [[True, False, False, True, False, False, False, True]])


@pytest.mark.parametrize("kind", ["l2", "smooth_l1"])
def test_disparity_loss_three_outputs_hand_computed(kind):
  gt = jnp.array([[2.0, jnp.inf, 5.0, 100.0]])  # inf and out-of-range (maxdisp 16) ignored
  p1 = jnp.array([[2.5, 7.0, 2.0, 0.0]])         # errors 0.5, -, -3
  p2 = jnp.array([[2.0, 7.0, 5.0, 0.0]])         # errors 0, -, 0
  p3 = jnp.array([[4.0, 7.0, 5.5, 0.0]])         # errors 2, -, 0.5
  f = (lambda e: e * e) if kind == "l2" else (lambda e: 0.5 * e * e if abs(e) < 1 else abs(e) - 0.5)
  expect = (0.5 * (f(0.5) + f(3)) / 2 + 0.7 * 0.0 + 1.0 * (f(2) + f(0.5)) / 2)
  got = dl.disparity_loss([p1, p2, p3], gt, 16, kind)
  np.testing.assert_allclose(got, expect, rtol=1e-6)
  g = jax.grad(lambda p: dl.disparity_loss([p1, p2, p], gt, 16, kind))(p3)
  assert np.all(np.isfinite(g)) and float(g[0, 1]) == 0.0 and float(g[0, 3]) == 0.0


def test_single_output_weight_one_and_mae():
  gt = jnp.array([[1.0, 3.0, jnp.inf]])
  pred = jnp.array([[2.0, 3.0, 9.0]])
  np.testing.assert_allclose(dl.disparity_loss([pred], gt, 16), 0.5, rtol=1e-6)
  s, n = dl.masked_mae(pred, gt, 16)
  assert float(s) == 1.0 and float(n) == 2.0
