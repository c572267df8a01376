"""Column codes of a structured-light projector: plain binary and Gray code, MSB first.

A projector of width W shows t = num_bits(W) stripe patterns. Pattern k (k = 0..t-1, the
paper's n = k + 1) is bit t-1-k of the code of each projector column, so pattern k has
2^(k+1) stripes for the plain binary code (the paper's virtual set) and the coarsest pattern
comes first. 1 = lit, 0 = dark. The Gray code g = c XOR (c >> 1) changes one bit between
neighbouring columns (the medical set).

encode/decode work on NumPy or jax.numpy arrays (argument xp) and loop over the t bits only.
"""

from types import ModuleType
from typing import Any

import numpy as np

from sljax.errors import require

CODES = ("binary", "gray")


def _check_code(code: str) -> str:
  require(code in CODES, f"unknown structured-light code {code!r}; expected one of {CODES}")
  return code


def num_bits(width: int) -> int:
  """Number of patterns needed to give each of `width` projector columns its own code."""
  require(int(width) >= 1, f"projector width must be >= 1, got {width}")
  return max(1, (int(width) - 1).bit_length())  # ceil(log2(width)), at least one pattern


def encode(columns: Any, code: str, t: int, xp: ModuleType = np) -> Any:
  """Code bits of integer columns: (...,) -> (..., t) uint8, MSB (coarsest pattern) first.

  Columns are taken modulo 2^t (only the t least significant bits are encoded).
  """
  _check_code(code)
  # The bits come from int32 shifts: t > 31 (or a float t) gives garbage, not an error.
  require(isinstance(t, (int, np.integer)) and 1 <= t <= 31,
          f"number of patterns t must be an integer in 1..31, got {t!r}")
  c = xp.asarray(columns).astype(xp.int32)
  if code == "gray":
    c = c ^ (c >> 1)
  shifts = xp.arange(t - 1, -1, -1, dtype=xp.int32)  # MSB first
  return ((c[..., None] >> shifts) & 1).astype(xp.uint8)


def decode(bits: Any, code: str, xp: ModuleType = np) -> Any:
  """Inverse of encode: (..., t) bits (0/1, any numeric dtype) -> (...,) int32 columns."""
  _check_code(code)
  b = xp.asarray(bits)  # each bit plane becomes int32 on its own (no full-size copy)
  require(b.ndim >= 1 and 1 <= b.shape[-1] <= 31,
          f"code bits must be (..., t) with t in 1..31, got shape {b.shape}")
  t = b.shape[-1]
  # One pass per bit over (...,) planes: a cumsum or weighted sum along a short last axis of a
  # large array is many times slower (per-element inner loops).
  value = xp.zeros(b.shape[:-1], xp.int32)
  bit = xp.zeros(b.shape[:-1], xp.int32)
  for k in range(t):
    # Binary bit k is the XOR of Gray bits 0..k.
    plane = b[..., k].astype(xp.int32)
    bit = (bit ^ plane) if code == "gray" else plane
    value = (value << 1) | bit
  return value


def pattern_columns(width: int, t: int | None = None) -> np.ndarray:
  """Code value of each projector column: its index, or its stripe index when t < num_bits.

  With fewer patterns than num_bits(width), only the t coarsest patterns are shown, so each
  code covers 2^(num_bits - t) neighbouring columns.
  """
  nb = num_bits(width)
  t = nb if t is None else int(t)
  require(1 <= t <= nb,
          f"t = {t} patterns for a projector of width {width}: expected 1..{nb}")
  return np.arange(width, dtype=np.int64) >> (nb - t)


def patterns(code: str, width: int, t: int | None = None) -> np.ndarray:
  """The t projected patterns, (t, width) uint8 0/1, coarsest first; t defaults to num_bits."""
  _check_code(code)
  cols = pattern_columns(width, t)
  t = num_bits(width) if t is None else int(t)
  return np.ascontiguousarray(encode(cols, code, t).T)


def inverse(pattern: Any) -> Any:
  """The inverse pattern(s): 1 - pattern, same dtype."""
  return 1 - pattern


def patterns_with_inverses(code: str, width: int, t: int | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
  """(patterns, inverses), each (t, width) uint8 0/1."""
  p = patterns(code, width, t)
  return p, inverse(p)


__all__ = ["CODES", "num_bits", "encode", "decode", "pattern_columns", "patterns", "inverse",
           "patterns_with_inverses"]
