"""Flax modules over the kernels: parameters exactly those of `nn.Conv` / `nn.ConvTranspose`.

{"kernel": (k..., cin, cout)[, "bias": (cout,)]}, created in float32 and cast with the input
to the computation dtype as nn.Conv does. Padding follows PyTorch: an int p pads p on both
sides of every spatial dimension.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Callable, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp

from sljax.kernels.args import PaddingLike, ntuple, resolve_padding, transpose_padding
from sljax.kernels.blocks import BLOCK_VALUES
from sljax.kernels.conv2d import conv2d
from sljax.kernels.conv3d import conv3d, conv_transpose3d

Initializer = Callable[..., jax.Array]


class ConvBase(nn.Module):
  """What every convolution module shares: kernel and bias, dtype, implementation, blocks.

  Subclasses set `ndim` (spatial dimensions) and define `convolve(x, kernel)`: the convolution
  of x with the cast kernel, no bias (the kernel function call). ConvBase itself is not used.
  """

  ndim: ClassVar[int] = 3

  features: int
  kernel_size: int | Sequence[int] = (3, 3, 3)
  strides: int | Sequence[int] = (1, 1, 1)
  padding: PaddingLike | None = None
  use_bias: bool = False
  kernel_init: Initializer = nn.initializers.lecun_normal()
  bias_init: Initializer = nn.initializers.zeros_init()
  dtype: Any = None  # computation dtype; None: that of the input and kernel (as nn.Conv)
  impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D
  block_values: int = BLOCK_VALUES

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Applies the convolution to x (N, spatial..., C)."""
    shape = ntuple(self.kernel_size, self.ndim) + (x.shape[-1], self.features)
    kernel = self.param("kernel", self.kernel_init, shape, jnp.float32)
    dtype = self.dtype or jnp.result_type(x, kernel)
    y = self.convolve(x.astype(dtype), kernel.astype(dtype))
    if self.use_bias:
      bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
      y = y + bias.astype(dtype)
    return y


class Conv3D(ConvBase):
  """Drop-in for nn.Conv on NDHWC input (same params); PyTorch-style int padding."""

  def convolve(self, x: jax.Array, kernel: jax.Array) -> jax.Array:
    """The 3D convolution."""
    return conv3d(x, kernel, ntuple(self.strides, 3),
                  resolve_padding(self.padding, kernel.shape[:3]), self.impl, self.block_values)


class ConvTranspose3D(ConvBase):
  """PyTorch ConvTranspose3d(k, stride, padding, output_padding) semantics, nn.ConvTranspose params.

  The kernel has flax's layout (kd, kh, kw, cin, cout) and is applied without flipping to
  the stride-dilated input (flax `transpose_kernel=False`), so a PyTorch weight
  (cin, cout, kd, kh, kw) converts by flipping its three spatial axes and transposing to
  (kd, kh, kw, cin, cout). The defaults (k=3, s=2, p=1, op=1) double every spatial size,
  as PSMNet's hourglasses need; the lax padding is (k-1-p, k-1-p+op) = (1, 2).
  """

  strides: int | Sequence[int] = (2, 2, 2)
  padding: int | Sequence[int] = 1
  output_padding: int | Sequence[int] = 1

  def convolve(self, x: jax.Array, kernel: jax.Array) -> jax.Array:
    """The transposed 3D convolution."""
    padding = transpose_padding(kernel.shape[:3], self.padding, self.output_padding)
    return conv_transpose3d(x, kernel, ntuple(self.strides, 3), padding, self.impl,
                            self.block_values)


class Conv2D(ConvBase):
  """Drop-in for a 2D nn.Conv on NHWC input (same params): XLA's convolution, blocked kernel grad."""

  ndim: ClassVar[int] = 2

  kernel_size: int | Sequence[int] = (3, 3)
  strides: int | Sequence[int] = (1, 1)
  padding: PaddingLike = "SAME"
  use_bias: bool = True
  kernel_dilation: int | Sequence[int] = (1, 1)

  def convolve(self, x: jax.Array, kernel: jax.Array) -> jax.Array:
    """The 2D convolution."""
    return conv2d(x, kernel, ntuple(self.strides, 2),
                  resolve_padding(self.padding, kernel.shape[:2]),
                  ntuple(self.kernel_dilation, 2), self.impl, self.block_values)
