"""What the fast paths share: plain 2D convolutions, their kernel gradient, and blocking."""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Callable, Iterator, Sequence

import jax
import jax.numpy as jnp
from jax import lax

from sljax.runtime import choices

DIMS_2D = ("NHWC", "HWIO", "NHWC")

# Output planes are computed in blocks whose input holds about this many values (512 KiB of
# float32, an L2 cache): XLA:CPU's 2D convolutions and, above all, their kernel gradients
# run several times faster on such blocks than on a whole folded volume at once (measured
# at PSMNet's shapes with benchmarks/bench_nets.py --part micro). One (batch, depth) plane
# is the smallest block; blocks run in a loop, so the program stays small. The default of
# every `block_values` argument.
BLOCK_VALUES = 1 << 17

# The blocks of the kernel gradients (fold_kernel_grad, conv2d's), where a program sets them.
# Which size is fastest depends on the library XLA hands the convolutions to, i.e. on the
# compiler options (sljax.runtime.choices.grad_blocks_for): with YNNPACK's fusions off, PSMNet's
# kernel gradients ran 1.4-2x faster in 1 Mi-value blocks than in 128 Ki ones (Zen 5, Zen 4, an
# Intel Xeon), while YNNPACK's were slower in them. Blocking never changes a value beyond
# float rounding (the sums' order), so this only selects the speed of a trace.
_GRAD_BLOCKS: contextvars.ContextVar[int | None] = contextvars.ContextVar("grad_blocks",
                                                                         default=None)


@contextlib.contextmanager
def grad_blocks(values: int | None) -> Iterator[None]:
  """Layers traced inside take kernel-gradient blocks of `values` input values (None: each
  layer's own); a layer's forward fixes its backward's blocks (a static argument of its jitted
  kernel), so a gradient taken inside has them."""
  token = _GRAD_BLOCKS.set(None if values is None else int(values))
  try:
    yield
  finally:
    _GRAD_BLOCKS.reset(token)


def grad_block_values(block_values: int) -> int:
  """The kernel-gradient block size of a layer traced now: the enclosing `grad_blocks`; else
  the layer's own `block_values` where it chose one; else this machine's for XLA's default
  compiler options (`context_free_blocks`, off the CPU the default `BLOCK_VALUES`)."""
  values = _GRAD_BLOCKS.get()
  if values is not None:
    return values
  if block_values != BLOCK_VALUES:
    return block_values
  machine = context_free_blocks()
  return block_values if machine is None else machine


@functools.cache
def context_free_blocks() -> int | None:
  """The blocks a gradient traced outside any `grad_blocks` takes: those of this CPU kind for a
  program compiled with XLA's default options (a plain `jax.jit(jax.grad(loss))`), as training
  would take them (sljax.runtime.choices.grad_blocks_for: `sljax tune`'s measurement, else the
  rule by fusions); None off the CPU. Read once per process."""
  return choices.grad_blocks_for(choices.DEFAULT)


def plain_conv2d(x: jax.Array, kernel: jax.Array, strides: Sequence[int], padding,
                 dilation: Sequence[int] = (1, 1)) -> jax.Array:
  """XLA's NHWC 2D convolution (the unit every fast path is made of)."""
  return lax.conv_general_dilated(x, kernel, tuple(strides), tuple(padding),
                                  rhs_dilation=tuple(dilation), dimension_numbers=DIMS_2D)


def conv2d_kernel_grad(x: jax.Array, dy: jax.Array, kernel_size: Sequence[int],
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
                               dimension_numbers=DIMS_2D)
  return jnp.transpose(g, (1, 2, 0, 3))


def block_shape(n: int, count: int, plane_values: int, block_values: int) -> tuple[int, int]:
  """(batch, plane) counts per block: whole ranges of several batch items, or plane chunks.

  Both divide their totals, so that every block has the same shape.
  """
  per = max(1, block_values // max(1, plane_values))
  if per >= count:
    return max(d for d in range(1, n + 1) if n % d == 0 and d * count <= per), count
  return 1, max(d for d in range(1, per + 1) if count % d == 0)


def blocked(n: int, count: int, plane_values: int, block_values: int, body: Callable, init):
  """Runs body(n0, z0, nb, tz, carry) over all blocks (a loop when there are several)."""
  if count == 0:
    return init
  if not isinstance(n, int):  # a symbolic batch (jax.export): one block of everything
    return body(0, 0, n, count, init)
  nb, tz = block_shape(n, count, plane_values, block_values)
  zblocks = count // tz
  total = (n // nb) * zblocks
  if total == 1:
    return body(0, 0, nb, tz, init)
  return lax.fori_loop(0, total, lambda i, c: body((i // zblocks) * nb, (i % zblocks) * tz,
                                                   nb, tz, c), init)
