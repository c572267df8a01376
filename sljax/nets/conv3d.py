"""3D convolution and transposed convolution (NDHWC) with a fast exact CPU path.

Parameters are exactly those of `flax.linen.Conv` / `flax.linen.ConvTranspose`:
{"kernel": (kd, kh, kw, cin, cout)[, "bias": (cout,)]}. Padding follows PyTorch: an int p
pads p on both sides of every spatial dimension.

Why two paths. XLA:CPU's 3D convolution is slow (tens of GFLOP/s on 2 cores, and its
stride-2 and transposed gradients take seconds at PSMNet's sizes), while its 2D convolution
is close to PyTorch's conv3d. On CPU ("auto" -> "fast"):
* `fold_conv3d`: a kd x kh x kw conv is the sum over the kd depth taps of 2D convs of the
  depth-shifted input with depth folded into the batch (exact; strides and any padding).
* `phase_conv_transpose3d`: a stride-s transposed conv is s^3 output phases, each a stride-1
  conv of the undilated input; they share one `fold_conv3d` with s^3 * cout outputs and are
  interleaved, so the zeros of the dilated input are never multiplied.
Alternatives measured at PSMNet's 1/4-resolution shapes (B=1, D=24, H=W=64, C=32/64) and
rejected: im2col + one matmul (the 27-fold patch copy costs more than it saves: 3-4x slower
than the fold), folding depth and height (1D convs, slower), concatenating the depth taps
on channels (one 2D conv with 3*cin inputs: same speed or slower, 3x memory). On GPU/TPU
("auto" -> "lax") the plain `lax.conv_general_dilated` is used. Select with the module's
`impl` argument or $SLJAX_CONV3D = auto | lax | fast (read when a function is traced).
Gradients come from autodiff through these formulations (tests compare them with lax's).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

Initializer = Callable[..., jax.Array]
PaddingLike = str | int | Sequence[int] | Sequence[tuple[int, int]]

_DIMS = ("NDHWC", "DHWIO", "NDHWC")

# "auto" (fast path on CPU, lax elsewhere), "lax" or "fast"; overridable per module.
_ENV_IMPL = "SLJAX_CONV3D"


def _triple(v: int | Sequence[int]) -> tuple[int, int, int]:
  if isinstance(v, int):
    return (v, v, v)
  v = tuple(int(x) for x in v)
  if len(v) != 3:
    raise ValueError(f"expected 3 values, got {v}")
  return v


def resolve_padding(padding: PaddingLike | None, kernel_size: Sequence[int]
                    ) -> tuple[tuple[int, int], ...] | str:
  """Turns int / per-dim ints / pairs / 'SAME' / 'VALID' / None (k//2) into lax padding."""
  if padding is None:
    return tuple((k // 2, k // 2) for k in kernel_size)
  if isinstance(padding, str):
    return padding.upper()
  if isinstance(padding, int):
    return tuple((padding, padding) for _ in kernel_size)
  out = []
  for p in padding:
    if isinstance(p, int):
      out.append((p, p))
    else:
      lo, hi = p
      out.append((int(lo), int(hi)))
  if len(out) != len(kernel_size):
    raise ValueError(f"padding {padding} does not match kernel size {kernel_size}")
  return tuple(out)


def transpose_padding(kernel_size: Sequence[int], padding: int | Sequence[int],
                      output_padding: int | Sequence[int]) -> tuple[tuple[int, int], ...]:
  """lax padding of the dilated input that reproduces PyTorch ConvTranspose semantics.

  PyTorch's ConvTranspose(k, s, p, op) equals a stride-1 convolution of the input dilated
  by s (s - 1 zeros between samples) padded by (k - 1 - p) before and (k - 1 - p + op)
  after, with the PyTorch kernel flipped spatially. Output size: (n - 1) s - 2 p + k + op.
  """
  p, op = _triple(padding), _triple(output_padding)
  return tuple((k - 1 - pi, k - 1 - pi + oi) for k, pi, oi in zip(kernel_size, p, op))


def conv_impl(impl: str | None = None) -> str:
  """Chooses 'lax' or 'fast': explicit argument, else $SLJAX_CONV3D, else by backend."""
  choice = impl or os.environ.get(_ENV_IMPL, "auto")
  if choice not in ("auto", "lax", "fast"):
    raise ValueError(f"conv impl must be auto, lax or fast, got {choice!r}")
  if choice == "auto":
    return "fast" if jax.default_backend() == "cpu" else "lax"
  return choice


def lax_conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int],
               padding, lhs_dilation: Sequence[int] = (1, 1, 1)) -> jax.Array:
  """The plain XLA 3D convolution (reference and GPU/TPU path)."""
  return lax.conv_general_dilated(
      x, kernel, window_strides=tuple(strides), padding=padding,
      lhs_dilation=tuple(lhs_dilation), dimension_numbers=_DIMS)


def _explicit_padding(padding, x_shape: Sequence[int], kernel_size: Sequence[int],
                      strides: Sequence[int]) -> tuple[tuple[int, int], ...]:
  """Resolves 'SAME' / 'VALID' to explicit (lo, hi) pairs like lax does."""
  if isinstance(padding, str):
    return tuple(lax.padtype_to_pads(tuple(x_shape[1:4]), tuple(kernel_size), tuple(strides),
                                     padding))
  return tuple((int(lo), int(hi)) for lo, hi in padding)


def _conv2d(x: jax.Array, kernel: jax.Array, strides: Sequence[int], padding) -> jax.Array:
  return lax.conv_general_dilated(x, kernel, tuple(strides), tuple(padding),
                                  dimension_numbers=("NHWC", "HWIO", "NHWC"))


def fold_conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int], padding) -> jax.Array:
  """Exact 3D conv as a sum over depth taps of 2D convs with depth folded into the batch.

  y[:, z] = sum_a conv2d(x_padded[:, s*z + a], kernel[a]). XLA:CPU runs 2D convolutions
  several times faster than 3D ones (and their gradients, notably for stride 2), so this
  is the CPU path; slicing the depth of NDHWC data is contiguous, so the folding is cheap.
  """
  n, _, _, _, c = x.shape
  kd = kernel.shape[0]
  sd = strides[0]
  pad = _explicit_padding(padding, x.shape, kernel.shape[:3], strides)
  # Negative padding crops; lax.pad handles both signs.
  xp = lax.pad(x, jnp.zeros((), x.dtype), ((0, 0, 0), (*pad[0], 0), (0, 0, 0), (0, 0, 0),
                                            (0, 0, 0)))
  dp = xp.shape[1]
  do = (dp - kd) // sd + 1
  y = None
  for a in range(kd):
    xa = lax.slice_in_dim(xp, a, a + sd * (do - 1) + 1, sd, axis=1)
    ya = _conv2d(xa.reshape((n * do,) + xa.shape[2:]), kernel[a], strides[1:], pad[1:])
    y = ya if y is None else y + ya
  return y.reshape((n, do) + y.shape[1:])


def _phase_selection(k: int, s: int, lo: int) -> tuple[np.ndarray, int]:
  """0/1 matrix S[e, a, t]: output phase a reads input offset e + emin through kernel tap t.

  For the stride-s dilated input padded by lo, output o = s*i + a reads dilated position
  o + t - lo, a real sample only when (a + t - lo) % s == 0, namely input i + (a + t - lo) / s.
  """
  pairs = [(a, t, (a + t - lo) // s) for a in range(s) for t in range(k) if (a + t - lo) % s == 0]
  offsets = [e for _, _, e in pairs]
  emin, emax = min(offsets), max(offsets)
  sel = np.zeros((emax - emin + 1, s, k), np.float32)
  for a, t, e in pairs:
    sel[e - emin, a, t] = 1.0
  return sel, emin


def phase_conv_transpose3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int],
                           padding: Sequence[tuple[int, int]]) -> jax.Array:
  """Exact stride-s transposed conv via sub-pixel (phase) decomposition.

  Equal to conv of the s-dilated input padded by `padding` with `kernel` (unflipped), but
  never multiplies the inserted zeros: each of the s^3 output phases is a stride-1 conv of
  the undilated input; all phases share one conv with s^3*cout output channels whose kernel
  (over the union of input offsets) is gathered from `kernel` by 0/1 selection, then the
  phases are interleaved (pixel shuffle) and the output cropped to its exact size.
  """
  n, cout = x.shape[0], kernel.shape[4]
  sels, pads, lq, lengths = [], [], [], []
  for dim in range(3):
    k, s, (lo, hi), size = kernel.shape[dim], strides[dim], padding[dim], x.shape[1 + dim]
    length = (size - 1) * s + 1 + lo + hi - k + 1
    sel, emin = _phase_selection(k, s, lo)
    q = -(-length // s)
    m = sel.shape[0]
    # Phase output i reads inputs i + emin .. i + emin + m - 1 (zero outside the input).
    pads.append((-emin, q - 1 + emin + m - 1 - (size - 1)))
    sels.append(jnp.asarray(sel, kernel.dtype))
    lq.append(q)
    lengths.append(length)
  comb = jnp.einsum("dat,hbu,wcv,tuvio->dhwiabco", *sels, kernel)
  comb = comb.reshape(comb.shape[:4] + (-1,))
  y = fold_conv3d(x, comb, (1, 1, 1), tuple(pads))
  sd, sh, sw = strides
  y = y.reshape(n, lq[0], lq[1], lq[2], sd, sh, sw, cout)
  y = y.transpose(0, 1, 4, 2, 5, 3, 6, 7).reshape(n, lq[0] * sd, lq[1] * sh, lq[2] * sw, cout)
  return y[:, :lengths[0], :lengths[1], :lengths[2]]


def conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int] = (1, 1, 1),
           padding=((1, 1),) * 3, impl: str | None = None) -> jax.Array:
  """NDHWC 3D convolution, numerically equal to lax.conv_general_dilated."""
  if conv_impl(impl) == "lax":
    return lax_conv3d(x, kernel, strides, padding)
  return fold_conv3d(x, kernel, tuple(strides), padding)


def conv_transpose3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int] = (2, 2, 2),
                     padding=((1, 2),) * 3, impl: str | None = None) -> jax.Array:
  """Transposed 3D conv = conv of the s-dilated input (flax's unflipped kernel layout)."""
  strides = tuple(strides)
  if conv_impl(impl) == "lax":
    return lax_conv3d(x, kernel, (1, 1, 1), padding, lhs_dilation=strides)
  if isinstance(padding, str):
    raise ValueError(f"conv_transpose3d needs explicit (lo, hi) padding pairs, got {padding!r}")
  padding = tuple((int(lo), int(hi)) for lo, hi in padding)
  if strides == (1, 1, 1):
    return fold_conv3d(x, kernel, strides, padding)
  return phase_conv_transpose3d(x, kernel, strides, padding)


class Conv3D(nn.Module):
  """Drop-in for nn.Conv on NDHWC input (same params); PyTorch-style int padding."""

  features: int
  kernel_size: Sequence[int] = (3, 3, 3)
  strides: int | Sequence[int] = (1, 1, 1)
  padding: PaddingLike | None = None
  use_bias: bool = False
  kernel_init: Initializer = nn.initializers.lecun_normal()
  bias_init: Initializer = nn.initializers.zeros_init()
  dtype: Any = None  # computation dtype; None: that of the input and kernel (as nn.Conv)
  impl: str | None = None

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Applies the convolution to x (N, D, H, W, C)."""
    ks = _triple(self.kernel_size)
    cin = x.shape[-1]
    kernel = self.param("kernel", self.kernel_init, ks + (cin, self.features), jnp.float32)
    dtype = self.dtype or jnp.result_type(x, kernel)
    y = conv3d(x.astype(dtype), kernel.astype(dtype), _triple(self.strides),
               resolve_padding(self.padding, ks), self.impl)
    if self.use_bias:
      bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
      y = y + bias.astype(dtype)
    return y


class ConvTranspose3D(nn.Module):
  """PyTorch ConvTranspose3d(k, stride, padding, output_padding) semantics, nn.ConvTranspose params.

  The kernel has flax's layout (kd, kh, kw, cin, cout) and is applied without flipping to
  the stride-dilated input (flax `transpose_kernel=False`), so a PyTorch weight
  (cin, cout, kd, kh, kw) converts by flipping its three spatial axes and transposing to
  (kd, kh, kw, cin, cout). The defaults (k=3, s=2, p=1, op=1) double every spatial size,
  as PSMNet's hourglasses need; the lax padding is (k-1-p, k-1-p+op) = (1, 2).
  """

  features: int
  kernel_size: Sequence[int] = (3, 3, 3)
  strides: int | Sequence[int] = (2, 2, 2)
  padding: int | Sequence[int] = 1
  output_padding: int | Sequence[int] = 1
  use_bias: bool = False
  kernel_init: Initializer = nn.initializers.lecun_normal()
  bias_init: Initializer = nn.initializers.zeros_init()
  dtype: Any = None  # computation dtype; None: that of the input and kernel (as nn.Conv)
  impl: str | None = None

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Applies the transposed convolution to x (N, D, H, W, C)."""
    ks = _triple(self.kernel_size)
    cin = x.shape[-1]
    kernel = self.param("kernel", self.kernel_init, ks + (cin, self.features), jnp.float32)
    dtype = self.dtype or jnp.result_type(x, kernel)
    y = conv_transpose3d(x.astype(dtype), kernel.astype(dtype), _triple(self.strides),
                         transpose_padding(ks, self.padding, self.output_padding), self.impl)
    if self.use_bias:
      bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
      y = y + bias.astype(dtype)
    return y
