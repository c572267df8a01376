"""NDHWC 3D convolutions and transposed convolutions: XLA's, or the folded and phase kernels.

Each fast form is a custom VJP (`vjp_saving_inputs`) whose backward reuses the same
machinery: a folded conv's dL/dx is another folded conv (stride 1) or the phases (strides),
its dL/dkernel a sum of blocked 2D kernel gradients; a transposed conv's dL/dx is the
adjoint strided (folded) conv and its dL/dkernel that conv's kernel gradient.

The GPU forms (`gpu_conv_transpose3d`) take the same adjoint backward with XLA's convolutions:
differentiating the transposed conv as written (a conv of the s-dilated input) makes its
kernel gradient a conv of the dilated input with the output gradient as a kernel as large as
the output, which XLA:GPU cannot hand to cuDNN's weight-gradient kernel and runs in a slow
forward fallback (issue 36: 65% of PSMNet's GPU step).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from sljax.kernels.args import explicit_padding, ntuple, pairs
from sljax.kernels.blocks import BLOCK_VALUES, grad_block_values
from sljax.kernels.fold import (fold_forward, fold_kernel_grad, input_grad_padding,
                                tap_products_conv3d)
from sljax.kernels.impl import XLA_IMPLS, conv_impl
from sljax.kernels.phase import adjoint_padding, interleave_phases, phase_plan
from sljax.kernels.vjp import vjp_saving_inputs

DIMS_3D = ("NDHWC", "DHWIO", "NDHWC")


def lax_conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int],
               padding, lhs_dilation: Sequence[int] = (1, 1, 1)) -> jax.Array:
  """The plain XLA 3D convolution (reference and GPU/TPU path)."""
  return lax.conv_general_dilated(
      x, kernel, window_strides=tuple(strides), padding=padding,
      lhs_dilation=tuple(lhs_dilation), dimension_numbers=DIMS_3D)


def _flipped(kernel: jax.Array) -> jax.Array:
  """The kernel of the adjoint convolution: spatially flipped, in and out swapped."""
  return jnp.flip(kernel, (0, 1, 2)).swapaxes(3, 4)


# The kernels' non-differentiable arguments: strides, padding pairs, the layer's block size and
# its kernel gradients' (`grad_block_values`, resolved when the forward is traced: a static
# argument, so that a layer traced once under one `grad_blocks` is not reused under another).


def _fold_forward(x, kernel, strides, padding, block_values, grad_values):
  del grad_values  # the backward's
  return fold_forward(x, kernel, strides, padding, block_values)


def _fold_bwd(strides, padding, block_values, grad_values, inputs, dy):
  x, kernel = inputs
  # dL/dx: the transposed convolution, i.e. a convolution of the stride-dilated dy with the
  # flipped kernel; stride 1 is another folded conv, stride s the phases.
  pads = input_grad_padding(kernel.shape, strides, padding, x.shape, dy.shape)
  if strides == (1, 1, 1):
    dx = _fold(dy, _flipped(kernel), strides, pads, block_values, grad_values)
  else:
    dx = _phase(dy, _flipped(kernel), strides, pads, block_values, grad_values)
  return dx, fold_kernel_grad(x, dy, kernel.shape, strides, padding, grad_values)


_fold = vjp_saving_inputs(_fold_forward, _fold_bwd, nondiff_argnums=(2, 3, 4, 5))


def _phases(x, kernel, strides, padding, conv):
  """The transposed conv as its interleaved phases; conv(x, kernel, pads): the shared conv."""
  comb, pads, lq, lengths = phase_plan(x.shape, kernel, strides, padding)
  return interleave_phases(conv(x, comb, pads), strides, lq, lengths)


def _phase_forward(x, kernel, strides, padding, block_values, grad_values):
  del grad_values  # the backward's
  return _phases(x, kernel, strides, padding,
                 lambda x, k, pads: fold_conv3d(x, k, (1, 1, 1), pads, block_values))


def _phase_bwd(strides, padding, block_values, grad_values, inputs, dy):
  # The transposed conv is the adjoint of the stride-s conv with the flipped, in/out-swapped
  # kernel w; so dL/dx is that strided (folded) conv of dy and dL/dw its kernel gradient
  # with dy as input and x as output gradient, both cheaper than differentiating the phases.
  x, kernel = inputs
  w = _flipped(kernel)
  pads = adjoint_padding(kernel.shape, strides, padding, x.shape, dy.shape)
  dx = _fold(dy, w, strides, pads, block_values, grad_values)
  dw = fold_kernel_grad(dy, x, w.shape, strides, pads, grad_values)
  return dx, _flipped(dw)


_phase = vjp_saving_inputs(_phase_forward, _phase_bwd, nondiff_argnums=(2, 3, 4, 5))


def _backward_data_forward(x, kernel, strides, padding):
  # XLA:GPU hands a conv of the dilated input to cuDNN's backward-data kernel only when the
  # kernel is visibly reversed in the program; flax's kernel is unflipped, so it is reversed
  # twice, the first behind a barrier, which the simplifier cannot fold (XLA:GPU removes
  # barriers only after choosing the cuDNN calls). Otherwise the input is dilated explicitly:
  # 8x the multiplications at stride 2.
  reversed_once = lax.optimization_barrier(lax.rev(kernel, (0, 1, 2)))
  return lax_conv3d(x, lax.rev(reversed_once, (0, 1, 2)), (1, 1, 1), padding,
                    lhs_dilation=strides)


def _xla_phase_forward(x, kernel, strides, padding):
  return _phases(x, kernel, strides, padding,
                 lambda x, k, pads: lax_conv3d(x, k, (1, 1, 1), pads))


def _adjoint_bwd(strides, padding, inputs, dy):
  # As _phase_bwd, with XLA's convolutions: the transposed conv is the adjoint of the stride-s
  # conv with kernel w (flipped, in/out swapped), so dL/dx is that conv of dy (cuDNN's forward
  # kernel) and dL/dw the gradient of <that conv of dy, x> in w (its weight-gradient kernel).
  x, kernel = inputs
  pads = adjoint_padding(kernel.shape, strides, padding, x.shape, dy.shape)
  dx, kernel_vjp = jax.vjp(lambda w: lax_conv3d(dy, w, strides, pads), _flipped(kernel))
  return dx, _flipped(kernel_vjp(x)[0])


_backward_data = vjp_saving_inputs(_backward_data_forward, _adjoint_bwd, nondiff_argnums=(2, 3))
_xla_phase = vjp_saving_inputs(_xla_phase_forward, _adjoint_bwd, nondiff_argnums=(2, 3))


def fold_conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int], padding,
                block_values: int = BLOCK_VALUES) -> jax.Array:
  """Exact 3D conv as a sum over depth taps of 2D convs with depth folded into the batch.

  y[:, z] = sum_a conv2d(x_padded[:, s*z + a], kernel[a]), computed over blocks of output
  planes (`block_values` input values each). XLA:CPU runs 2D convolutions several times
  faster than 3D ones, and both on small blocks. Stride-1 layers with few outputs (PSMNet's
  32 -> 1 classifiers) take `tap_products_conv3d` instead.
  """
  strides = ntuple(strides, 3)
  pad = explicit_padding(padding, x.shape[1:4], kernel.shape[:3], strides)
  if strides == (1, 1, 1) and np.prod(kernel.shape[:3]) * kernel.shape[4] <= kernel.shape[3]:
    return tap_products_conv3d(x, kernel, pad)
  return _fold(x, kernel, strides, pad, int(block_values), grad_block_values(int(block_values)))


def phase_conv_transpose3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int],
                           padding: Sequence[tuple[int, int]],
                           block_values: int = BLOCK_VALUES) -> jax.Array:
  """Exact stride-s transposed conv via sub-pixel (phase) decomposition.

  Equal to conv of the s-dilated input padded by `padding` with `kernel` (unflipped), but
  never multiplies the inserted zeros: each of the s^3 output phases is a stride-1 conv of
  the undilated input; all phases share one conv with s^3*cout output channels whose kernel
  (over the union of input offsets) is gathered from `kernel` by 0/1 selection, then the
  phases are interleaved (pixel shuffle) and the output cropped to its exact size.
  """
  strides = ntuple(strides, 3)
  return _phase(x, kernel, strides, pairs(padding), int(block_values),
                grad_block_values(int(block_values)))


def gpu_conv_transpose3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int],
                         padding: Sequence[tuple[int, int]], phases: bool = False) -> jax.Array:
  """Exact stride-s transposed conv in XLA convolutions that cuDNN runs natively, both ways.

  Forward: cuDNN's backward-data convolution (the dilated-input conv with a reversed kernel),
  or with `phases` the phase decomposition's one stride-1 conv (s^3 * cout outputs) and a
  pixel shuffle. Backward: the adjoint stride-s conv of the output gradient (dL/dx) and that
  conv's weight gradient against x (dL/dkernel). Same kernel layout and values as the lax form.
  """
  strides = ntuple(strides, 3)
  return (_xla_phase if phases else _backward_data)(x, kernel, strides, pairs(padding))


def conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int] = (1, 1, 1),
           padding=((1, 1),) * 3, impl: str | None = None,
           block_values: int = BLOCK_VALUES) -> jax.Array:
  """NDHWC 3D convolution, numerically equal to lax.conv_general_dilated."""
  if conv_impl(impl) in XLA_IMPLS:
    return lax_conv3d(x, kernel, strides, padding)
  return fold_conv3d(x, kernel, strides, padding, block_values)


def conv_transpose3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int] = (2, 2, 2),
                     padding=((1, 2),) * 3, impl: str | None = None,
                     block_values: int = BLOCK_VALUES) -> jax.Array:
  """Transposed 3D conv = conv of the s-dilated input (flax's unflipped kernel layout)."""
  strides, impl = ntuple(strides, 3), conv_impl(impl)
  if impl == "lax" or (impl in XLA_IMPLS and strides == (1, 1, 1)):
    return lax_conv3d(x, kernel, (1, 1, 1), padding, lhs_dilation=strides)
  if isinstance(padding, str):
    raise ValueError(f"conv_transpose3d needs explicit (lo, hi) padding pairs, got {padding!r}")
  if impl in XLA_IMPLS:
    return gpu_conv_transpose3d(x, kernel, strides, padding, phases=impl == "gpu-phase")
  if strides == (1, 1, 1):
    return fold_conv3d(x, kernel, strides, pairs(padding), block_values)
  return phase_conv_transpose3d(x, kernel, strides, padding, block_values)
