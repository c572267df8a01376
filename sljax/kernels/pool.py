"""2x2 max pooling whose gradient is elementwise masks (XLA:CPU's select-and-scatter is slow)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from sljax.kernels.vjp import vjp_saving_inputs


def _windows_2x2(x: jax.Array) -> jax.Array:
  """[B, H, W, C] -> [B, H/2, 2, W/2, 2, C] (a reshape: no data moves)."""
  b, h, w, c = x.shape
  return x.reshape(b, h // 2, 2, w // 2, 2, c)


def _max_pool_forward(x: jax.Array) -> jax.Array:
  return jnp.max(_windows_2x2(x), axis=(2, 4))


def _max_pool_bwd(inputs, g):
  (x,) = inputs
  win = _windows_2x2(x)
  eq = win == jnp.max(win, axis=(2, 4), keepdims=True)
  e00, e01, e10, e11 = eq[:, :, 0, :, 0], eq[:, :, 0, :, 1], eq[:, :, 1, :, 0], eq[:, :, 1, :, 1]
  first = [[e00, e01 & ~e00], [e10 & ~(e00 | e01), e11 & ~(e00 | e01 | e10)]]
  sel = jnp.stack([jnp.stack(row, axis=3) for row in first], axis=2)  # [B, H/2, 2, W/2, 2, C]
  return (jnp.where(sel, g[:, :, None, :, None], 0).reshape(x.shape).astype(g.dtype),)


_max_pool = vjp_saving_inputs(_max_pool_forward, _max_pool_bwd)


def max_pool_2x2(x: jax.Array) -> jax.Array:
  """nn.max_pool(x, (2, 2), strides=(2, 2)) on NHWC x with even height and width.

  The gradient goes to the first maximum of each window (row-major), as XLA's
  select-and-scatter (and PyTorch) do, but as elementwise masks on a reshape: XLA:CPU's
  select-and-scatter is several times slower. Splitting ties instead (jnp.max's own gradient)
  changes training on images with flat regions, where ties are common.
  """
  return _max_pool(x)
