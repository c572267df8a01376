"""Raw structured-light captures -> per-pixel pattern bits and projector column.

A capture set for one camera holds 'white' and 'black' (projector fully on / off), the
patterns 'p000'..'p{t-1}' (coarsest first) and optionally their inverses 'i000'... . A bit is
lit when the pattern is brighter than its inverse (robust to albedo and ambient light), or,
without inverses, brighter than the per-pixel mean of white and black. A pixel whose
white - black contrast is small is not reached by the projector (shadow) and is unknown; a bit
whose two compared values are too close is uncertain and unknown.
"""

import dataclasses
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from sljax.errors import SljaxError, require
from sljax.io.images import unit_image
from sljax.sl import codes


@dataclasses.dataclass(frozen=True)
class DecodeConfig:
  """Decoding thresholds on intensities in [0, 1] (defaults expressed in 8-bit grey levels).

  shadow_threshold: pixels with white - black below it are projector shadow (10 grey levels:
    well above 8-bit sensor noise, well below the contrast of a lit matte surface).
  bit_threshold: a bit whose |pattern - inverse| (or |pattern - (white + black) / 2|) is
    below it is uncertain (6 grey levels: about 2 sigma of the difference of two captures with
    a noise of 2 grey levels, a real camera at moderate gain; catches pixels on a stripe edge).
    Chosen on rendered captures of an unrectified rig degraded by defocus, indirect light,
    noise and overexposure (tests/test_captures.py), where 4 levels lost more pixels to
    wrongly decided bits and 10 more to uncertain ones.
  """
  shadow_threshold: float = 10.0 / 255.0
  bit_threshold: float = 6.0 / 255.0


@dataclasses.dataclass
class Decoded:
  """Decoding result of one camera; unknown entries are NaN."""
  bits: np.ndarray       # HxWxt float32 0/1, NaN where shadow or uncertain
  column: np.ndarray     # HxW float32 decoded code value, NaN if any bit is unknown
  shadow: np.ndarray     # HxW bool
  uncertain: np.ndarray  # HxWxt bool


_PATTERN_KEY = re.compile(r"^([pi])(\d{3})$")


def count_patterns(raw: dict[str, np.ndarray], where: str = "raw captures") -> int:
  """Number of patterns t in a capture dict; SljaxError names a missing key."""
  indices = {}
  for key in raw:
    m = _PATTERN_KEY.match(key)
    if m:
      indices.setdefault(m.group(1), set()).add(int(m.group(2)))
  ps = indices.get("p", set())
  if not ps:
    odd = sorted((k for k in raw if re.fullmatch(r"[pi]\d+", k) and not _PATTERN_KEY.match(k)),
                 key=lambda k: (k[0] != "p", k))
    hint = (f"; found {', '.join(odd[:3])}{', ...' if len(odd) > 3 else ''}: a capture's "
            "number takes exactly three digits" if odd else
            "; only inverse captures (i000, ...)" if indices.get("i") else "")
    raise SljaxError(f"{where}: no pattern captures (expected p000, p001, ...){hint}")
  t = max(ps) + 1
  for k in range(t):
    require(k in ps, f"{where}: missing pattern capture p{k:03d}")
  return t


def has_inverses(raw: dict[str, np.ndarray]) -> bool:
  """Whether a capture dict holds inverse captures (i000, ...)."""
  return any(_PATTERN_KEY.match(k) and k.startswith("i") for k in raw)


def column_from_bits(bits: np.ndarray, code: str, threshold: float = 0.5) -> np.ndarray:
  """HxWxt pattern values (1 lit, 0 dark, NaN unknown; or probabilities) -> HxW float32 code.

  A value >= threshold is a lit bit; a pixel with any NaN bit decodes to NaN.
  """
  b = np.asarray(bits, np.float32)
  known = ~np.isnan(b).any(axis=-1)
  column = codes.decode(b >= threshold, code).astype(np.float32)  # NaN >= threshold is False
  column[~known] = np.nan
  return column


def _capture(value: Any, key: str, where: str) -> np.ndarray:
  """One capture as float32 in [0, 1], NaN = unknown; uint8 / uint16 are scaled (the thresholds
  are in [0, 1])."""
  return unit_image(value, f"{where}: capture '{key}'", allow_nan=True)


def decode_captures(raw: dict[str, np.ndarray], code: str, t: int | None = None,
                    config: DecodeConfig = DecodeConfig(), where: str = "raw captures"
                    ) -> Decoded:
  """Classifies every pattern bit and decodes the projector column of every pixel.

  raw: HxW captures keyed 'white', 'black', 'p000'... and optionally 'i000'..., float in
  [0, 1] or uint8 / uint16 (divided by 255 / 65535); t defaults to the number of pattern
  captures. `where` names the capture set in error messages (e.g. the scene folder). A NaN
  capture pixel makes its bits unknown.
  """
  codes._check_code(code)
  require(isinstance(raw, Mapping), f"{where}: raw captures must be a dict of HxW images "
          f"keyed 'white', 'black', 'p000', ..., got {type(raw).__name__}")
  for key in ("white", "black"):
    require(key in raw, f"{where}: missing capture '{key}'")
  n = count_patterns(raw, where)
  require(t is None or (isinstance(t, (int, np.integer)) and t >= 1),
          f"{where}: number of patterns t must be a positive integer, got {t!r}")
  t = n if t is None else int(t)
  for k in range(t):
    require(f"p{k:03d}" in raw, f"{where}: missing pattern capture p{k:03d}")
  inv = has_inverses(raw)
  if inv:
    for k in range(t):
      require(f"i{k:03d}" in raw, f"{where}: missing inverse capture i{k:03d}")

  keys = ["white", "black"] + [f"p{k:03d}" for k in range(t)] + (
      [f"i{k:03d}" for k in range(t)] if inv else [])
  cap = {key: _capture(raw[key], key, where) for key in keys}
  white, black = cap["white"], cap["black"]
  require(white.ndim == 2, f"{where}: captures must be HxW grey images, got white {white.shape}")
  shape = white.shape
  for key in keys[1:]:
    require(cap[key].shape == shape,
            f"{where}: capture '{key}' has shape {cap[key].shape}, 'white' has {shape}")

  # Written as "not above the threshold" so that a NaN capture pixel is shadow / uncertain
  # (unknown) rather than a confident dark bit.
  shadow = ~((white - black) >= config.shadow_threshold)
  mean = None if inv else (white + black) * 0.5
  bits = np.empty(shape + (t,), np.float32)
  uncertain = np.empty(shape + (t,), bool)
  for k in range(t):  # one bit at a time: no stacks of all the captures
    diff = cap[f"p{k:03d}"] - (cap[f"i{k:03d}"] if inv else mean)
    uncertain[..., k] = ~(np.abs(diff) >= config.bit_threshold)
    bits[..., k] = np.where(uncertain[..., k] | shadow, np.float32(np.nan),
                            (diff > 0).astype(np.float32))
  column = column_from_bits(bits, code)
  return Decoded(bits=bits, column=column, shadow=shadow, uncertain=uncertain)
