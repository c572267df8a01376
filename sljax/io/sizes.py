"""Image sizes, parsed and checked in one place: N means N x N, HxW is height x width."""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Integral

from sljax.errors import SljaxError


def as_size(size: int | Sequence[int] | None, what: str = "size") -> tuple[int, int] | None:
  """None -> None; N -> (N, N); (H, W) -> (H, W); SljaxError unless both are positive ints."""
  if size is None:
    return None
  try:
    h, w = (size, size) if isinstance(size, Integral) else size
    h, w = int(h), int(w)
  except (TypeError, ValueError):
    raise SljaxError(f"{what} {size!r}: expected N or (height, width)") from None
  if h <= 0 or w <= 0:
    raise SljaxError(f"{what} {size!r}: height and width must be positive")
  return h, w


def parse_size(text: str, what: str = "--size", square: bool = True) -> tuple[int, int]:
  """'256' -> (256, 256) (when square); '96x128' -> (96, 128); SljaxError naming `what` else."""
  try:
    parts = [int(p) for p in str(text).lower().split("x")]
  except ValueError:
    parts = []
  if len(parts) not in ((1, 2) if square else (2,)):
    expected = "N or HEIGHTxWIDTH" if square else "HEIGHTxWIDTH"
    raise SljaxError(f"{what} {text!r}: expected {expected} in pixels, e.g. 96x128")
  h, w = parts * 2 if len(parts) == 1 else parts
  if h <= 0 or w <= 0:
    raise SljaxError(f"{what} {text!r}: height and width must be positive")
  return h, w
