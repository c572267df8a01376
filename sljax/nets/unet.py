"""UNet (Ronneberger et al. 2015) on a channel-concatenated stereo pair, two heads.

* head "sl": 2t logits per pixel, split into the left view's t pattern logits ("sl_logits")
  and the right view's ("sl_logits_right"); the paper's structured-light network.
* head "disp": one channel z, disparity = sigmoid(z) * image width ("disparity"); the paper's
  direct-disparity comparison network.

Each level: two 3x3 conv-BN-ReLU; 2x2 max pooling down; 2x2 stride-2 transposed conv up,
concatenated with the skip connection. Widths base * 2^level, level 0..depth.

Default depth 4, base width 32 (7.8 M parameters). Depth 4 gives a receptive field of about
170 pixels (173 measured from input gradients at the centre of a 512-wide image; at most
5 (2^d - 1) + 4 * 2^d + 4 (2^d - 1) + 1 = 200), wider than the widest stripe (128 columns for
the coarsest pattern of a 256-column binary code at 256 px), so every pixel can see a stripe
edge; base 32 instead of the original 64 costs a quarter of the compute, which keeps training
at 256x256 practical on a CPU.

Any H x W works: the pair is edge-padded at the bottom and right to a multiple of 2^depth and
the outputs are cropped back; "disp" scales by the original width.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from sljax.errors import require
from sljax.kernels import ResolvesConvImpl, max_pool_2x2
from sljax.nets.layers import ConvBN2D, UpConv2x2, conv_init

HEADS = ("sl", "disp")
INPUT_ZERO = 0.5  # the [0, 1] input that the centring 2x - 1 maps to 0: the pad value at test time


class DoubleConv(ResolvesConvImpl, nn.Module):
  """Two 3x3 conv-BN-ReLU."""

  features: int
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies both layers."""
    x = nn.relu(ConvBN2D(self.features, conv_impl=self.conv_impl, name="convbn_0")(x, train))
    return nn.relu(ConvBN2D(self.features, conv_impl=self.conv_impl, name="convbn_1")(x, train))


class UNet(ResolvesConvImpl, nn.Module):
  """UNet on [left; right]; apply(variables, left, right, train) -> output dict (see module doc)."""

  head: str = "sl"
  t: int = 8
  depth: int = 4
  base_width: int = 32
  in_channels: int = 3
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, left: jax.Array, right: jax.Array, train: bool = False) -> dict:
    """Predicts pattern logits (head 'sl') or disparity (head 'disp') for [0, 1] images."""
    require(self.head in HEADS, f"UNet head must be one of {HEADS}, got {self.head!r}")
    require(self.depth >= 1 and self.base_width >= 1,
            f"UNet depth and base_width must be positive, got {self.depth}, {self.base_width}")
    require(self.head != "sl" or self.t > 0, f"t must be positive, got {self.t}")
    require(left.ndim == 4 and left.shape == right.shape,
            f"left and right must be BxHxWxC batches of the same shape, got {left.shape} and "
            f"{right.shape}")
    require(left.shape[-1] == self.in_channels,
            f"the model expects {self.in_channels} channel(s) per view, got {left.shape[-1]}")
    _, h, w, _ = left.shape
    impl = self.conv_impl
    m = 2 ** self.depth
    ph, pw = -h % m, -w % m
    x = jnp.concatenate([left, right], axis=-1)
    if ph or pw:
      # Edge padding keeps the border statistics close to the image (zeros would add edges).
      x = jnp.pad(x, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    # Centre the [0, 1] inputs; the network has no other normalisation of its input.
    x = 2.0 * x - 1.0
    skips = []
    for level in range(self.depth):
      x = DoubleConv(self.base_width * 2 ** level, impl, name=f"down{level}")(x, train)
      skips.append(x)
      x = max_pool_2x2(x)  # even sizes: the input is padded to a multiple of 2^depth
    x = DoubleConv(self.base_width * 2 ** self.depth, impl, name="bottleneck")(x, train)
    for level in reversed(range(self.depth)):
      feat = self.base_width * 2 ** level
      x = UpConv2x2(feat, kernel_init=conv_init, name=f"upconv{level}")(x)
      x = jnp.concatenate([skips[level], x], axis=-1)
      x = DoubleConv(feat, impl, name=f"up{level}")(x, train)
    x = x[:, :h, :w]
    if self.head == "sl":
      z = nn.Conv(2 * self.t, (1, 1), kernel_init=conv_init, name="head")(x)
      return {"sl_logits": z[..., :self.t], "sl_logits_right": z[..., self.t:]}
    z = nn.Conv(1, (1, 1), kernel_init=conv_init, name="head")(x)
    return {"disparity": jax.nn.sigmoid(z[..., 0]) * w}
