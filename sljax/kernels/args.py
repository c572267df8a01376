"""The one argument normaliser: ints or sequences to tuples, PyTorch padding to lax pairs."""

from __future__ import annotations

from collections.abc import Sequence

from jax import lax

PaddingLike = str | int | Sequence[int] | Sequence[tuple[int, int]]
Pairs = tuple[tuple[int, int], ...]


def ntuple(v: int | Sequence[int], n: int) -> tuple[int, ...]:
  """An int repeated n times, or a sequence of n ints as a tuple."""
  if isinstance(v, int):
    return (v,) * n
  v = tuple(int(x) for x in v)
  if len(v) != n:
    raise ValueError(f"expected {n} values, got {v}")
  return v


def pairs(padding: Sequence[tuple[int, int]]) -> Pairs:
  """Explicit (lo, hi) padding pairs as a tuple of int pairs (hashable: a static argument)."""
  return tuple((int(lo), int(hi)) for lo, hi in padding)


def resolve_padding(padding: PaddingLike | None, kernel_size: Sequence[int]) -> Pairs | str:
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


def explicit_padding(padding: str | Sequence[tuple[int, int]], spatial: Sequence[int],
                     kernel_size: Sequence[int], strides: Sequence[int],
                     dilation: Sequence[int] | None = None) -> Pairs:
  """'SAME' / 'VALID' resolved to the (lo, hi) pairs lax uses; pairs passed through."""
  if not isinstance(padding, str):
    return pairs(padding)
  dilation = dilation or (1,) * len(kernel_size)
  eff = [(k - 1) * d + 1 for k, d in zip(kernel_size, dilation)]
  return pairs(lax.padtype_to_pads(tuple(spatial), eff, tuple(strides), padding))


def transpose_padding(kernel_size: Sequence[int], padding: int | Sequence[int],
                      output_padding: int | Sequence[int]) -> Pairs:
  """lax padding of the dilated input that reproduces PyTorch ConvTranspose semantics.

  PyTorch's ConvTranspose(k, s, p, op) equals a stride-1 convolution of the input dilated
  by s (s - 1 zeros between samples) padded by (k - 1 - p) before and (k - 1 - p + op)
  after, with the PyTorch kernel flipped spatially. Output size: (n - 1) s - 2 p + k + op.
  """
  n = len(kernel_size)
  p, op = ntuple(padding, n), ntuple(output_padding, n)
  return tuple((k - 1 - pi, k - 1 - pi + oi) for k, pi, oi in zip(kernel_size, p, op))
