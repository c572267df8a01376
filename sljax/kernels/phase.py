"""Stride-s transposed 3D convolution by output phases (sub-pixel decomposition), no VJP here.

A stride-s transposed conv (a conv of the s-dilated input) is s^3 output phases, each a
stride-1 conv of the undilated input; they share one conv with s^3 * cout outputs whose
kernel is gathered from the original by 0/1 selection, and are interleaved, so the zeros of
the dilated input are never multiplied. `sljax.kernels.conv3d` runs the shared conv (folded)
and makes the whole a differentiable function.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def phase_selection(k: int, s: int, lo: int) -> tuple[np.ndarray, int]:
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


def phase_plan(x_shape: Sequence[int], kernel: jax.Array, strides: tuple[int, int, int],
               padding: tuple[tuple[int, int], ...]):
  """(kernel of the shared stride-1 conv, its padding, phase lengths, output lengths)."""
  sels, pads, lq, lengths = [], [], [], []
  for dim in range(3):
    k, s, (lo, hi), size = kernel.shape[dim], strides[dim], padding[dim], x_shape[1 + dim]
    length = (size - 1) * s + 1 + lo + hi - k + 1
    sel, emin = phase_selection(k, s, lo)
    q = -(-length // s)
    m = sel.shape[0]
    # Phase output i reads inputs i + emin .. i + emin + m - 1 (zero outside the input).
    pads.append((-emin, q - 1 + emin + m - 1 - (size - 1)))
    sels.append(jnp.asarray(sel, kernel.dtype))
    lq.append(q)
    lengths.append(length)
  comb = jnp.einsum("dat,hbu,wcv,tuvio->dhwiabco", *sels, kernel)
  return comb.reshape(comb.shape[:4] + (-1,)), tuple(pads), lq, lengths


def interleave_phases(y: jax.Array, strides: tuple[int, int, int], lq: Sequence[int],
                      lengths: Sequence[int]) -> jax.Array:
  """The shared conv's s^3 * cout channels as interleaved phases (pixel shuffle), cropped."""
  n, sd, sh, sw = y.shape[0], *strides
  cout = y.shape[-1] // (sd * sh * sw)
  y = y.reshape(n, lq[0], lq[1], lq[2], sd, sh, sw, cout)
  y = y.transpose(0, 1, 4, 2, 5, 3, 6, 7).reshape(n, lq[0] * sd, lq[1] * sh, lq[2] * sw, cout)
  return y[:, :lengths[0], :lengths[1], :lengths[2]]


def adjoint_padding(kernel_shape: Sequence[int], strides: tuple[int, int, int],
                    padding: tuple[tuple[int, int], ...], x_shape: Sequence[int],
                    y_shape: Sequence[int]) -> tuple[tuple[int, int], ...]:
  """Padding of the stride-s conv (flipped, in/out-swapped kernel) adjoint to the transposed one."""
  pads = []
  for i in range(3):
    k, s, lo = kernel_shape[i], strides[i], padding[i][0]
    front = k - 1 - lo
    pads.append((front, s * (x_shape[1 + i] - 1) + k - front - y_shape[1 + i]))
  return tuple(pads)
