"""Shared building blocks: PyTorch-faithful initialisers, conv + BatchNorm blocks, linear resizing.

BatchNorm uses PyTorch's defaults (momentum 0.1 there, i.e. flax momentum 0.9; epsilon 1e-5) so
that reference weights and training recipes carry over, and its running variance averages the
unbiased batch variance as PyTorch's does (flax's own averages the biased one). In training its
gradient is written out (two reductions per group instead of autodiff's three: fewer YNNPACK
thunks for XLA:CPU to load and set up); the forward is flax's.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import flax.linen as nn
from flax.linen import normalization
import jax
import jax.numpy as jnp
from jax import lax
import numpy as np

from sljax.kernels import Conv2D, Conv3D, ResolvesConvImpl

BN_MOMENTUM = 0.9  # flax convention: running = momentum * running + (1 - momentum) * batch
BN_EPSILON = 1e-5

# The reference's initialisation: N(0, sqrt(2 / n)), n = kernel volume * output channels.
conv_init = nn.initializers.variance_scaling(2.0, "fan_out", "normal")
# PyTorch's default for transposed convolutions (the reference leaves them untouched):
# kaiming_uniform(a=sqrt(5)) on the weight (cin, cout, k...) whose "fan_in" PyTorch takes as
# cout * kernel volume, i.e. U(-b, b) with b = 1 / sqrt(cout * kernel volume). In flax's layout
# (k..., cin, cout) that volume times cout is the "fan_out".
conv_transpose_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_out", "uniform")


class BatchNorm(nn.BatchNorm):
  """flax's BatchNorm (same variables) whose running variance takes PyTorch's unbiased update.

  groups > 1: in training the batch is that many consecutive groups (a stereo pair's views run
  as one batch), each normalised with its own statistics and averaged into the running ones in
  order, exactly as that many calls of the layer, one per group, would.
  """

  groups: int = 1

  @nn.compact
  def __call__(self, x: jax.Array, use_running_average: bool | None = None) -> jax.Array:
    """Normalises as flax does; in training, rescales the running-variance update by n/(n-1)."""
    train = not nn.merge_param("use_running_average", self.use_running_average,
                               use_running_average)
    if train and self.groups > 1 and (x.shape[0] % self.groups
                                      or self.axis not in (-1, x.ndim - 1)):
      raise ValueError(f"BatchNorm groups={self.groups} needs a batch divisible by it and "
                       f"features last, got shape {x.shape}")
    if not train or self.is_initializing():  # flax's own (it creates the same variables)
      return super().__call__(x, use_running_average=not train)
    if self.axis not in (-1, x.ndim - 1) or self.axis_name is not None:
      raise ValueError("sljax's BatchNorm normalises the last axis of one device's batch "
                       f"(a jitted step shards it), got axis {self.axis}, axis_name "
                       f"{self.axis_name}")
    c = x.shape[-1]
    stats_dtype = jnp.float32 if self.force_float32_reductions else self.param_dtype  # flax's
    ra_mean = self.variable("batch_stats", "mean", lambda s: jnp.zeros(s, stats_dtype), (c,))
    ra_var = self.variable("batch_stats", "var", lambda s: jnp.ones(s, stats_dtype), (c,))
    scale = self.param("scale", self.scale_init, (c,), self.param_dtype) if self.use_scale else None
    bias = self.param("bias", self.bias_init, (c,), self.param_dtype) if self.use_bias else None
    y, ra_mean.value, ra_var.value = _train_batch_norm(
        x, scale, bias, ra_mean.value, ra_var.value, groups=self.groups,
        momentum=self.momentum, epsilon=self.epsilon, dtype=self.dtype,
        param_dtype=self.param_dtype, fast_variance=self.use_fast_variance,
        float32_reductions=self.force_float32_reductions)
    return y


class _Params:
  """What flax's `_normalize` asks of its module: the scale and bias, already created."""

  def __init__(self, scale: jax.Array | None, bias: jax.Array | None):
    self.values = {"scale": scale, "bias": bias}

  def param(self, name: str, *_) -> jax.Array:
    """The named parameter (flax's initialiser, shape and dtype arguments are not needed)."""
    return self.values[name]


@functools.partial(jax.jit, static_argnames=("groups", "momentum", "epsilon", "dtype",
                                             "param_dtype", "fast_variance",
                                             "float32_reductions"))
def _train_batch_norm(x, scale, bias, ra_mean, ra_var, *, groups, momentum, epsilon, dtype,
                      param_dtype, fast_variance, float32_reductions):
  """(normalised x, running mean, running variance) of a BatchNorm in training: flax's
  statistics and normalisation (its functions) per group of the batch, the running averages
  updated once per group in order with PyTorch's unbiased variance.

  Jitted, so that a network's BatchNorms of one shape are traced and differentiated once, not
  once per layer: they were half of the twin's step tracing (issue 49); XLA inlines the call,
  so the program and its values are the same. What sljax builds (scale, bias, float32
  statistics) is differentiated by `_normalized`'s own gradient, two reductions per group."""
  xs = x.reshape((groups, x.shape[0] // groups) + x.shape[1:]) if groups > 1 else x
  axes = tuple(range(1 if groups > 1 else 0, xs.ndim - 1))
  if (scale is not None and bias is not None and dtype is None and float32_reductions
      and param_dtype == jnp.float32):
    y, mean, var = _normalized(xs, scale, bias, axes, epsilon, fast_variance)
  else:
    mean, var = normalization._compute_stats(  # [groups, C] or [C]
        xs, axes, dtype=dtype, use_fast_variance=fast_variance,
        force_float32_reductions=float32_reductions)
    y = normalization._normalize(
        _Params(scale, bias), xs, mean, var, axes, (xs.ndim - 1,), dtype, param_dtype, epsilon,
        scale is not None, bias is not None, None, None, float32_reductions)
  n = xs.size // (groups * x.shape[-1])
  for i in range(groups):
    m, v = (mean[i], var[i]) if groups > 1 else (mean, var)
    old = ra_var
    ra_mean = momentum * ra_mean + (1 - momentum) * m
    # flax's m * old + (1 - m) * biased, turned into PyTorch's unbiased average: the
    # difference matters where n is small (the SPP branches' pooled maps have n = batch).
    ra_var = unbiased_update(momentum * old + (1 - momentum) * v, old, momentum, n)
  return y.reshape(x.shape), ra_mean, ra_var


def _statistics_and_normalized(xs, scale, bias, axes, epsilon, fast_variance):
  """(normalised xs, mean, variance) over `axes` in float32, as flax computes them (its
  functions)."""
  mean, var = normalization._compute_stats(xs, axes, dtype=None,
                                           use_fast_variance=fast_variance,
                                           force_float32_reductions=True)
  y = normalization._normalize(_Params(scale, bias), xs, mean, var, axes, (xs.ndim - 1,), None,
                               jnp.float32, epsilon, True, True, None, None, True)
  return y, mean, var


# The same with a gradient of its own (`_normalized_bwd`).
_normalized = jax.custom_vjp(_statistics_and_normalized, nondiff_argnums=(3, 4, 5))


def _normalized_fwd(xs, scale, bias, axes, epsilon, fast_variance):
  y, mean, var = _statistics_and_normalized(xs, scale, bias, axes, epsilon, fast_variance)
  return (y, mean, var), (xs, scale, mean, var)


def _normalized_bwd(axes, epsilon, fast_variance, residuals, cotangents):
  """BatchNorm's gradient written out, with two reductions per group (the sums of dy and of
  dy * x_hat). Autodiff of the forward took three, and its YNNPACK reduction thunks each cost
  load time and a first-run set-up: with this the main job's step has 454 instead of 560 and
  a warm launch of it takes 0.91x the time (docs/benchmarks/first-run.md). Where fast variance's
  clamp at zero acts (a constant channel) autodiff drops the variance's term and this keeps it;
  x_hat is then ~0 there."""
  del fast_variance  # the same derivative either way
  xs, scale, mean, var = residuals
  dy, dmean, dvar = cotangents  # the statistics' own: zero unless a caller differentiates them
  n = math.prod(xs.shape[a] for a in axes)
  expand = lambda v: jnp.expand_dims(v, axes)
  xc = xs.astype(jnp.float32) - expand(mean)
  rstd = lax.rsqrt(expand(var) + epsilon)
  xhat = xc * rstd
  dy = dy.astype(jnp.float32)
  sdy, sdyx = jnp.sum(dy, axes), jnp.sum(dy * xhat, axes)  # [groups, C] or [C]
  dx = (scale * rstd) * (dy - expand(sdy) / n - xhat * (expand(sdyx) / n))
  dx = dx + expand(dmean) / n + expand(dvar) * (2.0 / n) * xc
  return dx.astype(xs.dtype), _over_groups(sdyx), _over_groups(sdy)


_normalized.defvjp(_normalized_fwd, _normalized_bwd)


def _over_groups(s: jax.Array) -> jax.Array:
  """[groups, C] summed to [C] by additions in order (a reduction would be a thunk of its
  own); [C] as it is."""
  if s.ndim == 1:
    return s
  total = s[0]
  for i in range(1, s.shape[0]):
    total = total + s[i]
  return total


def unbiased_update(new: jax.Array, old: jax.Array, momentum: float, n: int) -> jax.Array:
  """flax's running variance m * old + (1 - m) * biased turned into PyTorch's, which averages
  in the unbiased batch variance biased * n / (n - 1)."""
  return new + (new - momentum * old) / max(n - 1, 1)


def batch_norm(name: str | None = None, groups: int = 1) -> BatchNorm:
  """A BatchNorm with PyTorch's momentum, epsilon and running-variance update (groups: see
  BatchNorm)."""
  return BatchNorm(momentum=BN_MOMENTUM, epsilon=BN_EPSILON, groups=groups, name=name)


class ConvBN2D(ResolvesConvImpl, nn.Module):
  """Conv2d (no bias, PyTorch padding) followed by BatchNorm: the reference's `convbn`."""

  features: int
  kernel_size: int = 3
  strides: int = 1
  padding: int = 1
  dilation: int = 1
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D
  groups: int = 1  # BatchNorm's batch groups in training (the views of a pair in one batch)

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies conv then BN (batch statistics when train, running averages otherwise)."""
    p = self.padding
    x = Conv2D(self.features, (self.kernel_size, self.kernel_size),
               strides=(self.strides, self.strides), padding=((p, p), (p, p)),
               kernel_dilation=(self.dilation, self.dilation), use_bias=False,
               kernel_init=conv_init, impl=self.conv_impl, name="conv")(x)
    return batch_norm("bn", self.groups)(x, use_running_average=not train)


class ConvBN3D(ResolvesConvImpl, nn.Module):
  """Conv3d (no bias, PyTorch padding) followed by BatchNorm: the reference's `convbn_3d`."""

  features: int
  kernel_size: int = 3
  strides: int = 1
  padding: int = 1
  conv_impl: str | None = None  # an IMPLS name (sljax.kernels.impl); None: $SLJAX_CONV3D

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    """Applies conv then BN on NDHWC input."""
    x = Conv3D(self.features, (self.kernel_size,) * 3, strides=self.strides,
               padding=self.padding, use_bias=False, kernel_init=conv_init, impl=self.conv_impl,
               name="conv")(x)
    return batch_norm("bn")(x, use_running_average=not train)


class UpConv2x2(nn.Module):
  """nn.ConvTranspose(features, (2, 2), strides=(2, 2), padding="VALID"), same parameters.

  With stride = kernel size the output blocks do not overlap: output pixel (2i + a, 2j + c)
  is x[i, j] times the kernel tap (1 - a, 1 - c), one matrix product and a reshape. XLA:CPU
  runs the transposed convolution's kernel gradient as a slow generic convolution (40% of
  the UNet's training step at 256x256); as a product it is a matrix product too.
  """

  features: int
  kernel_init: nn.initializers.Initializer = nn.initializers.lecun_normal()
  bias_init: nn.initializers.Initializer = nn.initializers.zeros_init()

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Upsamples NHWC x by 2 in height and width."""
    kernel = self.param("kernel", self.kernel_init, (2, 2, x.shape[-1], self.features),
                        jnp.float32)
    bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
    dtype = jnp.result_type(x, kernel)
    b, h, w, _ = x.shape
    y = jnp.einsum("bhwi,acio->bhawco", x.astype(dtype), kernel[::-1, ::-1].astype(dtype))
    return y.reshape(b, 2 * h, 2 * w, self.features) + bias.astype(dtype)


@functools.lru_cache(maxsize=256)
def linear_resize_matrix(n_in: int, n_out: int, align_corners: bool) -> np.ndarray:
  """(n_out, n_in) matrix of PyTorch's 1D linear interpolation weights.

  align_corners=False: source = max((dst + 0.5) * n_in / n_out - 0.5, 0) (half-pixel centres);
  align_corners=True: source = dst * (n_in - 1) / (n_out - 1) (end samples coincide).
  """
  dst = np.arange(n_out, dtype=np.float64)
  if align_corners:
    scale = (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
    src = dst * scale
  else:
    src = np.maximum((dst + 0.5) * (n_in / n_out) - 0.5, 0.0)
  i0 = np.minimum(np.floor(src).astype(np.int64), n_in - 1)
  i1 = np.minimum(i0 + 1, n_in - 1)
  w1 = src - i0
  m = np.zeros((n_out, n_in), np.float64)
  np.add.at(m, (np.arange(n_out), i0), 1.0 - w1)
  np.add.at(m, (np.arange(n_out), i1), w1)
  return m.astype(np.float32)


@functools.lru_cache(maxsize=256)
def linear_resize_phases(n_in: int, n_out: int, align_corners: bool
                         ) -> tuple[tuple[int, float, float], ...] | None:
  """`linear_resize_matrix` as f = n_out / n_in phases, or None where it has no such form.

  Phase r gives output f*i + r = w0 * x[i + s] + w1 * x[i + s + 1] with x edge-extended by
  one sample on both sides; returns ((s, w0, w1), ...) for r = 0..f-1. This holds for an
  integer factor with align_corners=False (PyTorch's clamping at the ends is the edge
  extension) and is verified against the matrix, row by row.
  """
  if align_corners or n_out % n_in or n_in < 2:
    return None
  f = n_out // n_in
  m = linear_resize_matrix(n_in, n_out, False).astype(np.float64)
  mid = n_in // 2
  phases = []
  for r in range(f):
    row = m[f * mid + r]
    cols = np.flatnonzero(row)
    s = int(cols[0]) - mid if len(cols) else 0
    if len(cols) == 1 and row[cols[0]] == 1.0:
      phases.append((s, 1.0, 0.0))
    elif len(cols) == 2 and cols[1] == cols[0] + 1:
      phases.append((s, float(row[cols[0]]), float(row[cols[1]])))
    else:
      return None
  ext = np.concatenate([[0], np.arange(n_in), [n_in - 1]])  # edge extension by one sample
  want = np.zeros_like(m)
  for r, (s, w0, w1) in enumerate(phases):
    if s < -1 or s > 0:
      return None
    for i in range(n_in):
      want[f * i + r, ext[i + s + 1]] += w0
      want[f * i + r, ext[i + s + 2]] += w1
  return tuple(phases) if np.allclose(want, m, rtol=0, atol=1e-6) else None


def resize_linear(x: jax.Array, sizes: Sequence[int], axes: Sequence[int],
                  align_corners: bool = False) -> jax.Array:
  """Separable (bi/tri)linear resize of `axes` to `sizes`, PyTorch `interpolate` semantics.

  Each axis is a small dense matrix product (exact, differentiable, fast on CPU); axes are
  processed in the given order, so put the cheapest (smallest growth) first.
  """
  for size, axis in zip(sizes, axes):
    axis = axis % x.ndim
    n_in = x.shape[axis]
    if n_in == size:
      continue
    m = jnp.asarray(linear_resize_matrix(n_in, int(size), bool(align_corners)), x.dtype)
    x = jnp.moveaxis(jnp.tensordot(x, m, axes=((axis,), (1,))), -1, axis)
  return x
