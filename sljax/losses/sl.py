"""Structured-light reconstruction loss (SPEC 1, paper eq. 1-3).

L_sl = L_bce + lambda1 * L_grad with lambda1 = 1/80:
- L_bce: mean binary cross entropy from logits over the pattern elements whose target is known
  (NaN targets = projector shadow / undecodable are masked out).
- L_grad: mean squared difference between the horizontal derivatives of the target and of
  sigmoid(logits), both taken with the [-1, 0, 1] mask: D(x) = P(x + 1) - P(x - 1) per row and
  pattern channel. A derivative exists at interior columns 1..W-2 only where both neighbours'
  targets are known; the mean runs over those positions (the convolution's sign convention does
  not matter for a squared difference).
"""

import jax
import jax.numpy as jnp

SL_GRAD_WEIGHT = 1.0 / 80.0


def _masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
  """Mean of values where mask holds; 0 when nothing is valid (no NaN from empty masks)."""
  mask = mask.astype(values.dtype)
  return jnp.sum(values * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def bce_with_logits(logits: jax.Array, targets: jax.Array) -> jax.Array:
  """Elementwise binary cross entropy from logits, stable for large |logits|."""
  return jnp.maximum(logits, 0.0) - logits * targets + jnp.log1p(jnp.exp(-jnp.abs(logits)))


def horizontal_derivative(x: jax.Array) -> jax.Array:
  """[-1, 0, 1] derivative along width (axis -2 of ...xHxWxt): x[w+1] - x[w-1], width W-2."""
  return x[..., 2:, :] - x[..., :-2, :]


def sl_bce(logits: jax.Array, targets: jax.Array) -> jax.Array:
  """Mean BCE over known (finite) targets; logits and targets ...xWxt."""
  known = jnp.isfinite(targets)
  t = jnp.where(known, targets, 0.0)
  return _masked_mean(bce_with_logits(logits, t), known)


def sl_grad_l2(logits: jax.Array, targets: jax.Array) -> jax.Array:
  """Mean squared difference of [-1, 0, 1] horizontal derivatives of sigmoid(logits) and targets."""
  known = jnp.isfinite(targets)
  t = jnp.where(known, targets, 0.0)
  valid = known[..., 2:, :] & known[..., :-2, :]
  diff = horizontal_derivative(jax.nn.sigmoid(logits)) - horizontal_derivative(t)
  return _masked_mean(jnp.square(diff), valid)


def sl_loss(logits: jax.Array, targets: jax.Array,
            grad_weight: float = SL_GRAD_WEIGHT) -> jax.Array:
  """L_sl = BCE + grad_weight * derivative L2; logits/targets BxHxWxt, NaN targets unknown."""
  return sl_bce(logits, targets) + grad_weight * sl_grad_l2(logits, targets)
