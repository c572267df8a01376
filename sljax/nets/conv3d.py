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

import functools
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


def _conv2d(x: jax.Array, kernel: jax.Array, strides: Sequence[int], padding,
            dilation: Sequence[int] = (1, 1)) -> jax.Array:
  return lax.conv_general_dilated(x, kernel, tuple(strides), tuple(padding),
                                  rhs_dilation=tuple(dilation),
                                  dimension_numbers=("NHWC", "HWIO", "NHWC"))


# Output planes are computed in blocks whose input holds about this many values (512 KiB of
# float32, an L2 cache): XLA:CPU's 2D convolutions and, above all, their kernel gradients
# run several times faster on such blocks than on a whole folded volume at once (measured
# at PSMNet's shapes with benchmarks/bench_nets.py --part micro). One (batch, depth) plane
# is the smallest block; blocks run in a loop, so the program stays small.
BLOCK_VALUES = 1 << 17


def _block_shape(n: int, count: int, plane_values: int) -> tuple[int, int]:
  """(batch, plane) counts per block: whole ranges of several batch items, or plane chunks.

  Both divide their totals, so that every block has the same shape.
  """
  per = max(1, BLOCK_VALUES // max(1, plane_values))
  if per >= count:
    return max(d for d in range(1, n + 1) if n % d == 0 and d * count <= per), count
  return 1, max(d for d in range(1, per + 1) if count % d == 0)


def _blocked(n: int, count: int, plane_values: int, body: Callable, init):
  """Runs body(n0, z0, nb, tz, carry) over all blocks (a loop when there are several)."""
  if count == 0:
    return init
  if not isinstance(n, int):  # a symbolic batch (jax.export): one block of everything
    return body(0, 0, n, count, init)
  nb, tz = _block_shape(n, count, plane_values)
  zblocks = count // tz
  total = (n // nb) * zblocks
  if total == 1:
    return body(0, 0, nb, tz, init)
  return lax.fori_loop(0, total, lambda i, c: body((i // zblocks) * nb, (i % zblocks) * tz,
                                                   nb, tz, c), init)


def _depth_plan(depth: int, kd: int, sd: int, padding: tuple[int, int]):
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


def _tap_planes(x: jax.Array, n0, z0, nb: int, tz: int, kd: int, sd: int,
                lo: int) -> list[jax.Array]:
  """Input planes sd*z + a - lo of the interior block z0 .. z0 + tz - 1, [nb * tz, H, W, C]."""
  if tz == 1:
    return [lax.dynamic_slice(x, (n0, sd * z0 + a - lo, 0, 0, 0), (nb, 1) + x.shape[2:]
                              ).reshape((nb,) + x.shape[2:]) for a in range(kd)]
  size = (nb, sd * (tz - 1) + kd) + x.shape[2:]
  xin = lax.dynamic_slice(x, (n0, sd * z0 - lo, 0, 0, 0), size)
  return [lax.slice_in_dim(xin, a, a + sd * (tz - 1) + 1, sd, axis=1).reshape((nb * tz,) + size[2:])
          for a in range(kd)]


def _fold_forward(x: jax.Array, kernel: jax.Array, strides: tuple[int, int, int],
                  padding: tuple[tuple[int, int], ...]) -> jax.Array:
  n, depth = x.shape[:2]
  kd, sd, lo = kernel.shape[0], strides[0], padding[0][0]
  do, first, count, edges = _depth_plan(depth, kd, sd, padding[0])

  def conv(xa, a):
    return _conv2d(xa, kernel[a], strides[1:], padding[1:])

  out_hw = [(x.shape[2 + i] + sum(padding[1 + i]) - kernel.shape[1 + i]) // strides[1 + i] + 1
            for i in range(2)]
  out = jnp.zeros((n, do, *out_hw, kernel.shape[4]), x.dtype)
  for z, taps in edges:
    y = sum((conv(x[:, sd * z + a - lo], a) for a in taps), jnp.zeros_like(out[:, 0]))
    out = out.at[:, z].set(y)

  def body(n0, z0, nb, tz, out):
    y = None
    for a, xa in enumerate(_tap_planes(x, n0, first + z0, nb, tz, kd, sd, lo)):
      ya = conv(xa, a)
      y = ya if y is None else y + ya
    return lax.dynamic_update_slice(out, y.reshape((nb, tz) + y.shape[1:]),
                                    (n0, first + z0, 0, 0, 0))

  return _blocked(n, count, int(np.prod(x.shape[2:])), body, out)


def _conv2d_kernel_grad(x: jax.Array, dy: jax.Array, kernel_size: Sequence[int],
                        strides: Sequence[int], padding,
                        dilation: Sequence[int] = (1, 1)) -> jax.Array:
  """dL/dk of conv2d(x, k) for output gradient dy, as one plain NHWC convolution.

  k[i, j, c, o] = sum_{b,y,x} x_pad[b, s*y + d*i, s*x + d*j, c] dy[b, y, x, o]: a convolution
  of x (channels as the batch, batch as the channels) with dy dilated by s as its kernel and
  output stride d. XLA builds the same, but written out it stays a library convolution
  inside loops (XLA leaves its own form to a slow generic kernel there).
  """
  xt = jnp.transpose(x, (3, 1, 2, 0))
  dt = jnp.transpose(dy, (1, 2, 0, 3))
  pads = [(lo, (k - 1) * d + s * (o - 1) + 1 - size - lo) for k, s, d, o, size, (lo, _) in
          zip(kernel_size, strides, dilation, dy.shape[1:3], x.shape[1:3], padding)]
  g = lax.conv_general_dilated(xt, dt, tuple(dilation), pads, rhs_dilation=tuple(strides),
                               dimension_numbers=("NHWC", "HWIO", "NHWC"))
  return jnp.transpose(g, (1, 2, 0, 3))


def _input_grad_padding(kernel_shape, strides, padding, x_shape, y_shape):
  """Padding of the s-dilated output gradient whose conv with the flipped kernel is dL/dx."""
  pads = []
  for i in range(3):
    k, s, lo = kernel_shape[i], strides[i], padding[i][0]
    lo_t = k - 1 - lo
    pads.append((lo_t, x_shape[1 + i] - (y_shape[1 + i] - 1) * s - 1 - lo_t + k - 1))
  return tuple(pads)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _fold(x, kernel, strides, padding):
  return _fold_forward(x, kernel, strides, padding)


def _fold_fwd(x, kernel, strides, padding):
  return _fold_forward(x, kernel, strides, padding), (x, kernel)


def _fold_bwd(strides, padding, res, dy):
  x, kernel = res
  # dL/dx: the transposed convolution, i.e. a convolution of the stride-dilated dy with the
  # flipped kernel (in/out swapped); stride 1 is another folded conv, stride s the phases.
  flipped = jnp.flip(kernel, (0, 1, 2)).swapaxes(3, 4)
  pads = _input_grad_padding(kernel.shape, strides, padding, x.shape, dy.shape)
  if strides == (1, 1, 1):
    dx = _fold(dy, flipped, strides, pads)
  else:
    dx = phase_conv_transpose3d(dy, flipped, strides, pads)
  return dx, _fold_kernel_grad(x, dy, kernel.shape, strides, padding)


_fold.defvjp(_fold_fwd, _fold_bwd)


def _fold_kernel_grad(x: jax.Array, dy: jax.Array, kernel_shape: Sequence[int],
                      strides: tuple[int, int, int], padding) -> jax.Array:
  """dL/dkernel of the folded conv: per depth tap, blocked 2D kernel gradients, summed."""
  n, depth = x.shape[:2]
  kd, sd, lo = kernel_shape[0], strides[0], padding[0][0]
  _, first, count, edges = _depth_plan(depth, kd, sd, padding[0])

  def grad(xa, dya):
    return _conv2d_kernel_grad(xa, dya, kernel_shape[1:3], strides[1:], padding[1:])

  dk = [jnp.zeros(tuple(kernel_shape[1:]), dy.dtype) for _ in range(kd)]
  for z, taps in edges:
    for a in taps:
      dk[a] = dk[a] + grad(x[:, sd * z + a - lo], dy[:, z])

  def body(n0, z0, nb, tz, dk):
    dyb = lax.dynamic_slice(dy, (n0, first + z0, 0, 0, 0), (nb, tz) + dy.shape[2:])
    dyb = dyb.reshape((nb * tz,) + dy.shape[2:])
    return tuple(g + grad(xa, dyb)
                 for g, xa in zip(dk, _tap_planes(x, n0, first + z0, nb, tz, kd, sd, lo)))

  return jnp.stack(_blocked(n, count, int(np.prod(x.shape[2:])), body, tuple(dk)))


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


def fold_conv3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int], padding) -> jax.Array:
  """Exact 3D conv as a sum over depth taps of 2D convs with depth folded into the batch.

  y[:, z] = sum_a conv2d(x_padded[:, s*z + a], kernel[a]), computed over blocks of output
  planes (`BLOCK_VALUES`). XLA:CPU runs 2D convolutions several times faster than 3D ones,
  and both on small blocks. The gradient is written out (custom VJP) so that it reuses the
  same machinery: dL/dx is a folded convolution (or phases, for strides), dL/dkernel a sum
  of blocked 2D kernel gradients.
  """
  strides = tuple(int(v) for v in strides)
  pad = _explicit_padding(padding, x.shape, kernel.shape[:3], strides)
  if strides == (1, 1, 1) and np.prod(kernel.shape[:3]) * kernel.shape[4] <= kernel.shape[3]:
    return tap_products_conv3d(x, kernel, pad)
  return _fold(x, kernel, strides, pad)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4))
def _conv2d_blocked(x, kernel, strides, padding, dilation):
  return _conv2d(x, kernel, strides, padding, dilation)


def _conv2d_blocked_fwd(x, kernel, strides, padding, dilation):
  return _conv2d(x, kernel, strides, padding, dilation), (x, kernel)


def _conv2d_blocked_bwd(strides, padding, dilation, res, dy):
  x, kernel = res
  dx = jax.vjp(lambda x: _conv2d(x, kernel, strides, padding, dilation), x)[1](dy)[0]
  # dL/dkernel over blocks of output rows (and whole images when they are small).
  n, ho = dy.shape[:2]
  kh, sh, dh = kernel.shape[0], strides[0], dilation[0]
  zero = jnp.zeros((), x.dtype)
  xp = lax.pad(x, zero, ((0, 0, 0), (*padding[0], 0), (*padding[1], 0), (0, 0, 0)))
  row_values = xp.shape[2] * xp.shape[3]
  _, rows = _block_shape(n, ho, row_values)
  hb = -(-ho // rows) * rows
  need = sh * (hb - 1) + (kh - 1) * dh + 1
  xp = lax.pad(xp, zero, ((0, 0, 0), (0, max(0, need - xp.shape[1]), 0), (0, 0, 0), (0, 0, 0)))
  dyp = lax.pad(dy, zero, ((0, 0, 0), (0, hb - ho, 0), (0, 0, 0), (0, 0, 0)))

  def body(n0, r0, nb, rows, dk):
    xin = lax.dynamic_slice(xp, (n0, sh * r0, 0, 0),
                            (nb, sh * (rows - 1) + (kh - 1) * dh + 1) + xp.shape[2:])
    dyb = lax.dynamic_slice(dyp, (n0, r0, 0, 0), (nb, rows) + dy.shape[2:])
    return dk + _conv2d_kernel_grad(xin, dyb, kernel.shape[:2], strides, ((0, 0), (0, 0)),
                                    dilation)

  dk = _blocked(n, ho, row_values, body, jnp.zeros(kernel.shape, kernel.dtype))
  return dx, dk



_conv2d_blocked.defvjp(_conv2d_blocked_fwd, _conv2d_blocked_bwd)


def conv2d(x: jax.Array, kernel: jax.Array, strides: Sequence[int] = (1, 1), padding=((1, 1),) * 2,
           dilation: Sequence[int] = (1, 1), impl: str | None = None) -> jax.Array:
  """NHWC 2D convolution equal to lax.conv_general_dilated; on CPU its kernel gradient is blocked.

  The forward pass and dL/dx are XLA's own; dL/dkernel is summed over blocks of output rows
  (`BLOCK_VALUES`), which XLA:CPU computes 1.3-1.6x faster than in one piece at PSMNet's
  feature-extraction shapes.
  """
  strides, dilation = tuple(int(v) for v in strides), tuple(int(v) for v in dilation)
  if isinstance(padding, str):
    eff = [(k - 1) * d + 1 for k, d in zip(kernel.shape[:2], dilation)]
    padding = lax.padtype_to_pads(x.shape[1:3], eff, strides, padding)
  padding = tuple((int(lo), int(hi)) for lo, hi in padding)
  if conv_impl(impl) == "lax":
    return _conv2d(x, kernel, strides, padding, dilation)
  return _conv2d_blocked(x, kernel, strides, padding, dilation)


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


def _phase_forward(x, kernel, strides, padding):
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



@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _phase(x, kernel, strides, padding):
  return _phase_forward(x, kernel, strides, padding)


def _phase_fwd(x, kernel, strides, padding):
  return _phase_forward(x, kernel, strides, padding), (x, kernel)


def _phase_bwd(strides, padding, res, dy):
  # The transposed conv is the adjoint of the stride-s conv with the flipped, in/out-swapped
  # kernel w; so dL/dx is that strided (folded) conv of dy and dL/dw its kernel gradient
  # with dy as input and x as output gradient, both cheaper than differentiating the phases.
  x, kernel = res
  w = jnp.flip(kernel, (0, 1, 2)).swapaxes(3, 4)
  pads = []
  for i in range(3):
    k, s, lo = kernel.shape[i], strides[i], padding[i][0]
    front = k - 1 - lo
    pads.append((front, s * (x.shape[1 + i] - 1) + k - front - dy.shape[1 + i]))
  pads = tuple(pads)
  dx = _fold(dy, w, strides, pads)
  dw = _fold_kernel_grad(dy, x, w.shape, strides, pads)
  return dx, jnp.flip(dw, (0, 1, 2)).swapaxes(3, 4)


_phase.defvjp(_phase_fwd, _phase_bwd)


def phase_conv_transpose3d(x: jax.Array, kernel: jax.Array, strides: Sequence[int],
                           padding: Sequence[tuple[int, int]]) -> jax.Array:
  """Exact stride-s transposed conv via sub-pixel (phase) decomposition.

  Equal to conv of the s-dilated input padded by `padding` with `kernel` (unflipped), but
  never multiplies the inserted zeros: each of the s^3 output phases is a stride-1 conv of
  the undilated input; all phases share one conv with s^3*cout output channels whose kernel
  (over the union of input offsets) is gathered from `kernel` by 0/1 selection, then the
  phases are interleaved (pixel shuffle) and the output cropped to its exact size.
  """
  strides = tuple(int(v) for v in strides)
  padding = tuple((int(lo), int(hi)) for lo, hi in padding)
  return _phase(x, kernel, strides, padding)


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


class Conv2D(nn.Module):
  """Drop-in for a 2D nn.Conv on NHWC input (same params): XLA's convolution, blocked kernel grad."""

  features: int
  kernel_size: Sequence[int] = (3, 3)
  strides: int | Sequence[int] = (1, 1)
  padding: PaddingLike = "SAME"
  kernel_dilation: int | Sequence[int] = (1, 1)
  use_bias: bool = True
  kernel_init: Initializer = nn.initializers.lecun_normal()
  bias_init: Initializer = nn.initializers.zeros_init()
  dtype: Any = None  # computation dtype; None: that of the input and kernel (as nn.Conv)
  impl: str | None = None

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Applies the convolution to x (N, H, W, C)."""
    ks = tuple(self.kernel_size)
    pair = lambda v: (v, v) if isinstance(v, int) else tuple(v)
    kernel = self.param("kernel", self.kernel_init, ks + (x.shape[-1], self.features), jnp.float32)
    pad = self.padding if isinstance(self.padding, str) else resolve_padding(self.padding, ks)
    dtype = self.dtype or jnp.result_type(x, kernel)
    y = conv2d(x.astype(dtype), kernel.astype(dtype), pair(self.strides), pad,
               pair(self.kernel_dilation), self.impl)
    if self.use_bias:
      bias = self.param("bias", self.bias_init, (self.features,), jnp.float32)
      y = y + bias.astype(dtype)
    return y
