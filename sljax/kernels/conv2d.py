"""NHWC 2D convolution: XLA's forward and input gradient, a blocked kernel gradient on CPU."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jax import lax

from sljax.kernels.args import explicit_padding, ntuple
from sljax.kernels.blocks import (BLOCK_VALUES, block_shape, blocked, conv2d_kernel_grad,
                                  grad_block_values, plain_conv2d)
from sljax.kernels.impl import XLA_IMPLS, conv_impl
from sljax.kernels.vjp import vjp_saving_inputs


def _unblocked_forward(x, kernel, strides, padding, dilation, block_values):
  del block_values  # only the backward is blocked
  return plain_conv2d(x, kernel, strides, padding, dilation)


def _blocked_bwd(strides, padding, dilation, block_values, inputs, dy):
  # block_values: the kernel gradient's blocks (`grad_block_values`, resolved when the forward
  # is traced, so that the jitted layer is keyed by them).
  x, kernel = inputs
  dx = jax.vjp(lambda x: plain_conv2d(x, kernel, strides, padding, dilation), x)[1](dy)[0]
  # dL/dkernel over blocks of output rows (and whole images when they are small).
  n, ho = dy.shape[:2]
  kh, sh, dh = kernel.shape[0], strides[0], dilation[0]
  zero = jnp.zeros((), x.dtype)
  xp = lax.pad(x, zero, ((0, 0, 0), (*padding[0], 0), (*padding[1], 0), (0, 0, 0)))
  row_values = xp.shape[2] * xp.shape[3]
  _, rows = block_shape(n, ho, row_values, block_values)
  hb = -(-ho // rows) * rows
  need = sh * (hb - 1) + (kh - 1) * dh + 1
  xp = lax.pad(xp, zero, ((0, 0, 0), (0, max(0, need - xp.shape[1]), 0), (0, 0, 0), (0, 0, 0)))
  dyp = lax.pad(dy, zero, ((0, 0, 0), (0, hb - ho, 0), (0, 0, 0), (0, 0, 0)))

  def body(n0, r0, nb, rows, dk):
    xin = lax.dynamic_slice(xp, (n0, sh * r0, 0, 0),
                            (nb, sh * (rows - 1) + (kh - 1) * dh + 1) + xp.shape[2:])
    dyb = lax.dynamic_slice(dyp, (n0, r0, 0, 0), (nb, rows) + dy.shape[2:])
    return dk + conv2d_kernel_grad(xin, dyb, kernel.shape[:2], strides, ((0, 0), (0, 0)),
                                   dilation)

  dk = blocked(n, ho, row_values, block_values, body, jnp.zeros(kernel.shape, kernel.dtype))
  return dx, dk


_conv2d_blocked = vjp_saving_inputs(_unblocked_forward, _blocked_bwd, nondiff_argnums=(2, 3, 4, 5))


def conv2d(x: jax.Array, kernel: jax.Array, strides: Sequence[int] = (1, 1), padding=((1, 1),) * 2,
           dilation: Sequence[int] = (1, 1), impl: str | None = None,
           block_values: int = BLOCK_VALUES) -> jax.Array:
  """NHWC 2D convolution equal to lax.conv_general_dilated; on CPU its kernel gradient is blocked.

  The forward pass and dL/dx are XLA's own; dL/dkernel is summed over blocks of output rows
  (`block_values` input values each), which XLA:CPU computes 1.3-1.6x faster than in one
  piece at PSMNet's feature-extraction shapes.
  """
  strides, dilation = ntuple(strides, 2), ntuple(dilation, 2)
  padding = explicit_padding(padding, x.shape[1:3], kernel.shape[:2], strides, dilation)
  if conv_impl(impl) in XLA_IMPLS:
    return plain_conv2d(x, kernel, strides, padding, dilation)
  return _conv2d_blocked(x, kernel, strides, padding, dilation,
                         grad_block_values(int(block_values)))
