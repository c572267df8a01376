"""3D convolution by folding depth into the batch: forward and kernel gradient (no VJP here).

y[:, z] = sum_a conv2d(x_padded[:, s*z + a], kernel[a]): a kd x kh x kw conv is the sum over
its kd depth taps of 2D convs of the depth-shifted input with depth folded into the batch
(exact; strides and any padding), computed over blocks of output planes (`block_values`).
A depth kernel of three taps at depth stride 1 (PSMNet's stride-1 layers, and their input
gradients) runs by pairs of output planes instead: Winograd's F(2, 3) in depth, four 2D
convolutions per two planes instead of six (`pair_forward`).
`sljax.kernels.conv3d` makes these a differentiable function.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from sljax.kernels.blocks import blocked, conv2d_kernel_grad, plain_conv2d


def depth_plan(depth: int, kd: int, sd: int, padding: tuple[int, int]):
  """Output planes split into those whose kd taps all lie inside the input and the others.

  Output plane z reads input planes sd*z + a - lo, a < kd. Returns (do, first, count,
  edges): the interior planes first .. first + count - 1 read no padding (so the input
  needs no padded copy); edges lists (z, valid taps) for the rest.
  """
  lo, hi = padding
  do = (depth + lo + hi - kd) // sd + 1
  first = min(max(0, -(-lo // sd)), do)
  last = min((depth - kd + lo) // sd, do - 1)
  count = max(0, last - first + 1)
  edges = [(z, [a for a in range(kd) if 0 <= sd * z + a - lo < depth])
           for z in range(do) if not first <= z < first + count]
  return do, first, count, edges


def pad_depth(x: jax.Array, padding) -> tuple[jax.Array, tuple[tuple[int, int], ...]]:
  """x with its depth padding applied (zero planes; a negative side crops) and the padding
  that is left (none in depth).

  With the padding in the input every output plane is interior (`depth_plan` finds no edges),
  so one loop body of kd convolutions covers the whole layer. The edge planes, unrolled, were
  about a third of the convolutions of PSMNet-MTL's training step (issue 42: the program
  traced, lowered and compiled before the first step, and the size of the compile cache's
  entry, whose loading grows faster than linearly with it); the price is a padded copy of
  the input and the products with its zero planes (exact zeros, so the sums are unchanged).
  """
  lo, hi = padding[0]
  if lo == 0 and hi == 0:
    return x, tuple(padding)
  zero = jnp.zeros((), x.dtype)
  x = lax.pad(x, zero, ((0, 0, 0), (lo, hi, 0), (0, 0, 0), (0, 0, 0), (0, 0, 0)))
  return x, ((0, 0),) + tuple(padding[1:])


def tap_planes(x: jax.Array, n0, z0, nb: int, tz: int, kd: int, sd: int,
               lo: int) -> list[jax.Array]:
  """Input planes sd*z + a - lo of the interior block z0 .. z0 + tz - 1, [nb * tz, H, W, C]."""
  if tz == 1:
    return [lax.dynamic_slice(x, (n0, sd * z0 + a - lo, 0, 0, 0), (nb, 1) + x.shape[2:]
                              ).reshape((nb,) + x.shape[2:]) for a in range(kd)]
  size = (nb, sd * (tz - 1) + kd) + x.shape[2:]
  xin = lax.dynamic_slice(x, (n0, sd * z0 - lo, 0, 0, 0), size)
  return [lax.slice_in_dim(xin, a, a + sd * (tz - 1) + 1, sd, axis=1).reshape((nb * tz,) + size[2:])
          for a in range(kd)]


def fold_forward(x: jax.Array, kernel: jax.Array, strides: tuple[int, int, int],
                 padding: tuple[tuple[int, int], ...], block_values: int) -> jax.Array:
  """The folded 3D convolution of NDHWC x with a DHWIO kernel (explicit padding pairs): by
  pairs of output planes where the depth kernel has three taps and stride 1, else by taps."""
  x, padding = pad_depth(x, padding)
  if kernel.shape[0] == 3 and strides[0] == 1 and x.shape[1] >= 4:
    return pair_forward(x, kernel, strides[1:], padding[1:], block_values)
  return tap_forward(x, kernel, strides, padding, block_values)


def tap_forward(x: jax.Array, kernel: jax.Array, strides: tuple[int, int, int],
                padding: tuple[tuple[int, int], ...], block_values: int) -> jax.Array:
  """The folded conv as the sum over depth taps of 2D convs of the shifted planes."""
  x, padding = pad_depth(x, padding)
  n, depth = x.shape[:2]
  kd, sd, lo = kernel.shape[0], strides[0], padding[0][0]
  do, first, count, edges = depth_plan(depth, kd, sd, padding[0])

  def conv(xa, a):
    return plain_conv2d(xa, kernel[a], strides[1:], padding[1:])

  out_hw = [(x.shape[2 + i] + sum(padding[1 + i]) - kernel.shape[1 + i]) // strides[1 + i] + 1
            for i in range(2)]
  out = jnp.zeros((n, do, *out_hw, kernel.shape[4]), x.dtype)
  for z, taps in edges:
    y = sum((conv(x[:, sd * z + a - lo], a) for a in taps), jnp.zeros_like(out[:, 0]))
    out = out.at[:, z].set(y)

  def body(n0, z0, nb, tz, out):
    y = None
    for a, xa in enumerate(tap_planes(x, n0, first + z0, nb, tz, kd, sd, lo)):
      ya = conv(xa, a)
      y = ya if y is None else y + ya
    return lax.dynamic_update_slice(out, y.reshape((nb, tz) + y.shape[1:]),
                                    (n0, first + z0, 0, 0, 0))

  return blocked(n, count, int(np.prod(x.shape[2:])), block_values, body, out)


def pair_kernels(kernel: jax.Array) -> jax.Array:
  """The four 2D kernels of Winograd's F(2, 3) over depth, from a depth-3 DHWIO kernel."""
  g0, g1, g2 = kernel[0], kernel[1], kernel[2]
  return jnp.stack([g0, (g0 + g1 + g2) * 0.5, (g0 - g1 + g2) * 0.5, g2])


def pair_forward(x: jax.Array, kernel: jax.Array, strides_hw: Sequence[int], padding_hw,
                 block_values: int) -> jax.Array:
  """The folded conv of a depth-3, depth-stride-1 kernel over x padded in depth, by pairs of
  output planes: Winograd's F(2, 3) in depth, four 2D convolutions per pair instead of six.

  Output planes 2p and 2p + 1 read input planes d0..d3 = 2p .. 2p + 3:
  y0 = m1 + m2 + m3, y1 = m2 - m3 - m4 with m1 = conv(d0 - d2, g0), m2 = conv(d1 + d2,
  (g0 + g1 + g2) / 2), m3 = conv(d2 - d1, (g0 - g1 + g2) / 2), m4 = conv(d1 - d3, g2), exact
  up to float rounding (the sums' order). An odd plane count takes one zero plane more and
  drops the extra output.
  """
  n, depth = x.shape[:2]
  do = depth - 2
  if do % 2:
    x = lax.pad(x, jnp.zeros((), x.dtype), ((0, 0, 0), (0, 1, 0), (0, 0, 0), (0, 0, 0), (0, 0, 0)))
  pairs = (do + 1) // 2
  g = pair_kernels(kernel)
  out_hw = [(x.shape[2 + i] + sum(padding_hw[i]) - kernel.shape[1 + i]) // strides_hw[i] + 1
            for i in range(2)]
  out = jnp.zeros((n, 2 * pairs, *out_hw, kernel.shape[4]), x.dtype)

  def body(n0, p0, nb, tp, out):
    xin = lax.dynamic_slice(x, (n0, 2 * p0, 0, 0, 0), (nb, 2 * tp + 2) + x.shape[2:])
    d = [lax.slice_in_dim(xin, j, j + 2 * tp - 1, 2, axis=1).reshape((nb * tp,) + x.shape[2:])
         for j in range(4)]
    m = [plain_conv2d(t, g[i], strides_hw, padding_hw)
         for i, t in enumerate((d[0] - d[2], d[1] + d[2], d[2] - d[1], d[1] - d[3]))]
    y = jnp.stack([m[0] + m[1] + m[2], m[1] - m[2] - m[3]], axis=1)
    return lax.dynamic_update_slice(out, y.reshape((nb, 2 * tp) + y.shape[2:]),
                                    (n0, 2 * p0, 0, 0, 0))

  # A pair counts as one plane in the blocking (blocks of one pair at PSMNet's 1/4 resolution,
  # as the taps' blocks of one plane): two pairs a block were no faster (within 5%, Zen 5).
  out = blocked(n, pairs, int(np.prod(x.shape[2:])), block_values, body, out)
  return out[:, :do] if do % 2 else out


def fold_kernel_grad(x: jax.Array, dy: jax.Array, kernel_shape: Sequence[int],
                     strides: tuple[int, int, int], padding, block_values: int) -> jax.Array:
  """dL/dkernel of the folded conv: per depth tap, blocked 2D kernel gradients, summed."""
  x, padding = pad_depth(x, padding)
  n, depth = x.shape[:2]
  kd, sd, lo = kernel_shape[0], strides[0], padding[0][0]
  _, first, count, edges = depth_plan(depth, kd, sd, padding[0])

  def grad(xa, dya):
    return conv2d_kernel_grad(xa, dya, kernel_shape[1:3], strides[1:], padding[1:])

  dk = [jnp.zeros(tuple(kernel_shape[1:]), dy.dtype) for _ in range(kd)]
  for z, taps in edges:
    for a in taps:
      dk[a] = dk[a] + grad(x[:, sd * z + a - lo], dy[:, z])

  def body(n0, z0, nb, tz, dk):
    dyb = lax.dynamic_slice(dy, (n0, first + z0, 0, 0, 0), (nb, tz) + dy.shape[2:])
    dyb = dyb.reshape((nb * tz,) + dy.shape[2:])
    return tuple(g + grad(xa, dyb)
                 for g, xa in zip(dk, tap_planes(x, n0, first + z0, nb, tz, kd, sd, lo)))

  return jnp.stack(blocked(n, count, int(np.prod(x.shape[2:])), block_values, body, tuple(dk)))


def input_grad_padding(kernel_shape, strides, padding, x_shape, y_shape):
  """Padding of the s-dilated output gradient whose conv with the flipped kernel is dL/dx."""
  pads = []
  for i in range(3):
    k, s, lo = kernel_shape[i], strides[i], padding[i][0]
    lo_t = k - 1 - lo
    pads.append((lo_t, x_shape[1 + i] - (y_shape[1 + i] - 1) * s - 1 - lo_t + k - 1))
  return tuple(pads)


def tap_products_conv3d(x: jax.Array, kernel: jax.Array, padding) -> jax.Array:
  """Exact stride-1 3D conv for few outputs: all tap products in one matmul, then a shifted sum.

  z[p, t] = x[p] . kernel[t] for the kd*kh*kw taps t (a [P, cin] x [cin, taps*cout] product),
  y[o] = sum_t z[o + t - lo, t]. For PSMNet's 32 -> 1 classifiers z is smaller than x and
  the whole layer, gradients included, runs several times faster than as convolutions with
  one output channel.
  """
  kd, kh, kw, cin, cout = kernel.shape
  n = x.shape[0]
  taps = kd * kh * kw
  z = jnp.dot(x.reshape(-1, cin), kernel.transpose(3, 0, 1, 2, 4).reshape(cin, taps * cout))
  z = z.reshape(x.shape[:4] + (taps, cout))
  zero = jnp.zeros((), x.dtype)
  z = lax.pad(z, zero, ((0, 0, 0), *((lo, hi, 0) for lo, hi in padding), (0, 0, 0), (0, 0, 0)))
  out = [z.shape[1 + i] - kernel.shape[i] + 1 for i in range(3)]
  y = None
  for t, (a, i, j) in enumerate(np.ndindex(kd, kh, kw)):
    yt = lax.slice(z, (0, a, i, j, t, 0), (n, a + out[0], i + out[1], j + out[2], t + 1, cout))
    y = yt if y is None else y + yt
  return y.reshape((n, *out, cout))

