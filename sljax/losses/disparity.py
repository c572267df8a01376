"""Disparity losses (SPEC 3): the paper's L2 (default) or the reference smooth-L1.

Ground truth counts only where it is finite and 0 <= d < maxdisp (PSMNet's reference mask);
PSMNet's three training outputs are weighted 0.5 / 0.7 / 1.0.
"""

from collections.abc import Sequence

import jax
import jax.numpy as jnp

PSMNET_OUTPUT_WEIGHTS = (0.5, 0.7, 1.0)
DISP_LOSSES = ("l2", "smooth_l1")


def disparity_mask(gt: jax.Array, maxdisp: float) -> jax.Array:
  """Valid ground truth: finite and within [0, maxdisp)."""
  return jnp.isfinite(gt) & (gt >= 0) & (gt < maxdisp)


def pointwise_loss(err: jax.Array, kind: str) -> jax.Array:
  """Per-pixel loss of an error: squared ('l2') or Huber with delta 1 ('smooth_l1')."""
  if kind == "l2":
    return jnp.square(err)
  if kind == "smooth_l1":
    a = jnp.abs(err)
    return jnp.where(a < 1.0, 0.5 * jnp.square(err), a - 0.5)
  raise ValueError(f"unknown disparity loss {kind!r}; choose from {DISP_LOSSES}")


def masked_disparity_loss(pred: jax.Array, gt: jax.Array, mask: jax.Array,
                          kind: str = "l2") -> jax.Array:
  """Mean per-pixel loss of pred vs gt over mask (0 when the mask is empty)."""
  safe_gt = jnp.where(mask, gt, 0.0)
  err = jnp.where(mask, pred - safe_gt, 0.0)
  m = mask.astype(pred.dtype)
  return jnp.sum(pointwise_loss(err, kind) * m) / jnp.maximum(jnp.sum(m), 1.0)


def disparity_loss(preds: Sequence[jax.Array], gt: jax.Array, maxdisp: float,
                   kind: str = "l2",
                   weights: Sequence[float] | None = None) -> jax.Array:
  """Weighted sum of masked losses of several predictions (PSMNet: 0.5/0.7/1.0; one output: 1)."""
  preds = tuple(preds)
  if weights is None:
    weights = PSMNET_OUTPUT_WEIGHTS if len(preds) == 3 else (1.0,) * len(preds)
  if len(weights) != len(preds):
    raise ValueError(f"{len(preds)} predictions but {len(weights)} weights")
  mask = disparity_mask(gt, maxdisp)
  return sum(w * masked_disparity_loss(p, gt, mask, kind) for w, p in zip(weights, preds))


def masked_mae(pred: jax.Array, gt: jax.Array, maxdisp: float) -> tuple[jax.Array, jax.Array]:
  """(sum of |pred - gt|, count) over valid ground truth, for exact means across batches."""
  mask = disparity_mask(gt, maxdisp)
  err = jnp.where(mask, jnp.abs(pred - jnp.where(mask, gt, 0.0)), 0.0)
  return jnp.sum(err), jnp.sum(mask.astype(jnp.float32))
