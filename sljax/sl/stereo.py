"""Both views of a rectified structured-light capture -> pattern bits, projector codes and
left-right checked disparity: the one path that `sljax decode` and `sljax import-captures` take.

Decoding. Each view is decoded on its own (sljax.sl.decode); codes that the projector cannot
show (a column >= its width, when the width is not a power of two) are unknown.

Matching. The code maps are matched along the rectified scanlines (sljax.sl.match, left-right
checked) on the coarsest b column bits, b chosen so that a code's stripe is at least
min_stripe_px wide in the cameras: a projector about as dense as the cameras (1920 columns seen
by 2048 pixels) gives stripes of one or two pixels for the finest bit, whose pixels are almost
all on a blurred stripe edge, so that many codes have no confidently decoded pixel left to
match. The patterns written (sl0, sl1) keep every bit. Pixels on a stripe boundary (exactly one
uncertain bit, whose two readings are neighbouring codes: the one bit a Gray code changes
there) are matched as boundary pixels (see sljax.sl.match).

Rows. When the capture also holds row patterns, the projector row of each pixel is decoded too,
and a match whose two pixels see different projector rows (by more than row_tolerance) is
unknown: a point is lit by one projector pixel, whichever camera sees it, so a row mismatch is
a false match (interreflection, a wrongly decided bit). Rows are used for nothing else.
"""

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from sljax.errors import require
from sljax.sl import codes
from sljax.sl.decode import DecodeConfig, Decoded, decode_captures
from sljax.sl.match import disparity_from_codes, lr_check_disparities


@dataclasses.dataclass(frozen=True)
class MatchConfig:
  """Matching of decoded codes (see sljax.sl.match).

  bits: column bits matched, coarsest first (None: the most whose stripes are at least
    min_stripe_px wide in the cameras, see match_bits).
  min_stripe_px: the narrowest stripe (camera pixels per matched code) bits=None allows.
  lr_tolerance: px a disparity may differ from the other view's at the matched pixel.
  max_gap: unknown pixels that may separate two pixels of one code run on a row.
  edges: match the pixels on a stripe boundary too (see boundary_codes).
  edge_tolerance: px the two runs' disparities at a boundary pixel may differ by.
  subpixel: place stripe boundaries where the changing bit's contrast crosses zero (see
    code_bounds) rather than between whole pixels.
  row_tolerance: projector rows the two pixels of a match may differ by (with row patterns;
    1: the rounding of the matched pixel and a row boundary between the two pixel centres).
  """
  bits: int | None = None
  min_stripe_px: float = 2.5
  lr_tolerance: float = 1.0
  max_gap: int = 2
  edges: bool = True
  edge_tolerance: float = 1.0
  subpixel: bool = True
  row_tolerance: float = 1.0


@dataclasses.dataclass
class StereoDecoded:
  """Decoded views and, once matched, disparities (inf unknown) and the bits matched."""
  left: Decoded
  right: Decoded
  code: str
  projector: tuple[int | None, int | None] = (None, None)
  rows: tuple[np.ndarray, np.ndarray] | None = None  # projector row per pixel, NaN unknown
  raw: tuple[Mapping[str, np.ndarray], Mapping[str, np.ndarray]] | None = None  # the captures
  disp0: np.ndarray | None = None
  disp1: np.ndarray | None = None
  bits: int | None = None  # column bits the matching used
  row_rejected: int = 0    # left pixels whose match saw another projector row
  row_checked: int = 0     # left matches the row check could judge (both rows known)


def _limit(column: np.ndarray, count: int | None) -> np.ndarray:
  """Codes outside 0..count-1 (no projector column or row shows them) become NaN."""
  if count is None:
    return column
  return np.where(column < count, column, np.float32(np.nan)).astype(np.float32)


def decode_views(raw0: Mapping[str, np.ndarray], raw1: Mapping[str, np.ndarray], code: str,
                 config: DecodeConfig = DecodeConfig(), *,
                 projector: tuple[int | None, int | None] = (None, None),
                 rows: tuple[Mapping[str, np.ndarray], Mapping[str, np.ndarray]] | None = None,
                 where: tuple[str, str] = ("raw0", "raw1")) -> StereoDecoded:
  """Decodes both views' column patterns (keys white, black, p000..., i000...).

  projector: (width, height); codes at or beyond them are unknown (None: any code). rows: the
  two views' row captures under the same keys (p000 = coarsest row bit), for the row check.
  """
  views = [decode_captures(raw, code, None, config, where=w) for raw, w in zip((raw0, raw1), where)]
  require(views[0].bits.shape == views[1].bits.shape,
          f"{where[1]}: {views[1].bits.shape[-1]} patterns of {views[1].bits.shape[:2]}, "
          f"{where[0]} has {views[0].bits.shape[-1]} of {views[0].bits.shape[:2]}")
  for v in views:
    v.column = _limit(v.column, projector[0])
  out = StereoDecoded(left=views[0], right=views[1], code=code, projector=tuple(projector),
                      raw=(raw0, raw1))
  if rows is not None:
    out.rows = tuple(_limit(decode_captures(raw, code, None, config, where=f"{w} rows").column,
                            projector[1]) for raw, w in zip(rows, where))
  return out


def column_rate(columns: tuple[np.ndarray, ...], step: int = 16) -> float:
  """Median projector columns per camera pixel along the rows (NaN when nothing is decoded):
  from code differences over `step` pixels (long enough that whole codes measure fractions of a
  column per pixel to 1/step), where both ends are decoded and no depth edge lies between (a
  difference above 4 columns per pixel)."""
  rates = []
  for col in columns:
    diff = np.abs(col[:, step:] - col[:, :-step]) / step
    rates.append(diff[np.isfinite(diff) & (diff <= 4.0)])
  found = np.concatenate(rates)
  return float(np.median(found)) if found.size else float("nan")


def match_bits(decoded: StereoDecoded, match: MatchConfig) -> int:
  """The column bits to match: match.bits, or the most whose codes' stripes are at least
  match.min_stripe_px wide (a code of the coarsest b of n bits spans 2^(n - b) columns)."""
  n = decoded.left.bits.shape[-1]
  if match.bits is not None:
    require(1 <= match.bits <= n, f"match bits {match.bits}: the capture has {n} column bits")
    return int(match.bits)
  rate = column_rate((decoded.left.column, decoded.right.column))
  if not np.isfinite(rate) or rate <= 0:
    return n
  drop = max(0, math.ceil(math.log2(match.min_stripe_px * rate) - 1e-9))
  return max(1, n - drop)


def coarse_codes(view: Decoded, code: str, bits: int, count: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
  """(codes, boundary codes) of the coarsest `bits` bits of a decoded view.

  codes: HxW float32, NaN where a bit is unknown. Boundary codes: the lower code c of the pixels
  that lie on the boundary between the stripes of codes c and c + 1 (NaN elsewhere): lit pixels
  with exactly one unknown bit whose two readings are neighbouring codes (the one bit a Gray
  code changes there, half lit in the camera). count: codes of the projector's width (None:
  all).
  """
  b = view.bits[..., :bits]
  unknown = np.isnan(b)
  n_unknown = unknown.sum(axis=-1)
  low = codes.decode(b > 0.5, code)  # unknown bits read 0 (NaN > 0.5 is False) ...
  high = codes.decode(~(b <= 0.5), code)  # ... and 1
  # Codes of fewer bits cover 2^(n - bits) columns each: the projector's last code is
  # ceil(count / 2^(n - bits)) - 1.
  limit = None if count is None else -(-count // 2 ** (view.bits.shape[-1] - bits))
  column = np.where(n_unknown == 0, low, np.nan).astype(np.float32)
  edge = (n_unknown == 1) & ~view.shadow & (np.abs(low - high) == 1)
  boundary = np.where(edge, np.minimum(low, high), np.nan).astype(np.float32)
  if limit is not None:
    column = _limit(column, limit)
    boundary = np.where(np.maximum(low, high) < limit, boundary, np.nan).astype(np.float32)
  return column, boundary


def _changing_bit(lower: np.ndarray, code: str, bits: int) -> np.ndarray:
  """Index (coarsest first) of the one bit that differs between the codes lower and lower + 1
  of `bits` bits; -1 where more than one differs (the binary code's carries)."""
  pair = codes.encode(np.stack([lower, lower + 1], -1), code, bits).astype(np.int32)
  changed = pair[..., 0, :] != pair[..., 1, :]
  return np.where(changed.sum(-1) == 1, np.argmax(changed, -1), -1)


def _contrast(raw: Mapping[str, np.ndarray], bit: np.ndarray, ys: np.ndarray, xs: np.ndarray
              ) -> np.ndarray:
  """(pattern - inverse) / (white - black) of the given bits at the given pixels (pattern minus
  the mean of white and black without inverses): a bit's signed contrast, free of albedo."""
  out = np.zeros(ys.size, np.float64)
  white = np.asarray(raw["white"])[ys, xs].astype(np.float64)
  black = np.asarray(raw["black"])[ys, xs].astype(np.float64)
  for k in np.unique(bit):
    at = bit == k
    p = np.asarray(raw[f"p{k:03d}"])[ys[at], xs[at]].astype(np.float64)
    inverse = raw.get(f"i{k:03d}")
    ref = (np.asarray(inverse)[ys[at], xs[at]].astype(np.float64) if inverse is not None
           else 0.5 * (white[at] + black[at]))
    out[at] = (p - ref) / np.maximum(white[at] - black[at], 1e-9)
  return out


def _crossing(s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
  """Where the line through (0, s0), (1, s1) crosses zero, clipped to [0, 1]."""
  den = s0 - s1
  return np.clip(np.where(np.abs(den) > 1e-12, s0 / np.where(den == 0, 1, den), 0.5), 0.0, 1.0)


def code_bounds(raw: Mapping[str, np.ndarray], column: np.ndarray, boundary: np.ndarray,
                code: str, bits: int) -> np.ndarray:
  """HxW sub-pixel x of the boundary between a pixel's code and the neighbouring code on its
  right, on the last pixel of a stripe and on a boundary pixel (NaN elsewhere).

  Between neighbouring codes one bit changes; the boundary is where that bit's signed contrast
  (sljax.sl.match's bounds) crosses zero, interpolated linearly between the two pixels of
  opposite sign: x and x + 1, or, across a boundary pixel, the pair on either side of it.
  """
  h, w = column.shape
  out = np.full((h, w), np.nan, np.float64)
  # Two neighbouring codes side by side.
  a, b = column[:, :-1], column[:, 1:]
  ys, xs = np.nonzero(np.isfinite(a) & np.isfinite(b) & (np.abs(a - b) == 1))
  if ys.size:
    k = _changing_bit(np.minimum(a[ys, xs], b[ys, xs]).astype(np.int64), code, bits)
    ok = k >= 0
    ys, xs, k = ys[ok], xs[ok], k[ok]
    out[ys, xs] = xs + _crossing(_contrast(raw, k, ys, xs), _contrast(raw, k, ys, xs + 1))
  # Two neighbouring codes with a boundary pixel between them.
  a, e, b = column[:, :-2], boundary[:, 1:-1], column[:, 2:]
  ys, xs = np.nonzero(np.isfinite(a) & np.isfinite(b) & (np.abs(a - b) == 1)
                      & (e == np.minimum(a, b)))
  if ys.size:
    k = _changing_bit(e[ys, xs].astype(np.int64), code, bits)
    ok = k >= 0
    ys, xs, k = ys[ok], xs[ok], k[ok]
    s = [_contrast(raw, k, ys, xs + i) for i in range(3)]
    first = np.sign(s[0]) != np.sign(s[1])  # the zero lies between x and x + 1
    x = np.where(first, xs + _crossing(s[0], s[1]), xs + 1 + _crossing(s[1], s[2]))
    out[ys, xs] = x
    out[ys, xs + 1] = x
  return out


def _row_mismatch(d: np.ndarray, rows_a: np.ndarray, rows_b: np.ndarray, sign: float,
                  tolerance: float) -> tuple[np.ndarray, np.ndarray]:
  """(mismatched, checked): pixels of view a whose matched pixel in view b (nearest) sees
  another projector row, and those where both rows are known (a row unknown in either view
  does not count against the match)."""
  h, w = d.shape
  finite = np.isfinite(d)
  xb = np.rint(np.arange(w)[None, :] - sign * np.where(finite, d, 0.0)).astype(np.int64)
  inside = finite & (xb >= 0) & (xb < w)
  other = rows_b[np.arange(h)[:, None], np.clip(xb, 0, w - 1)]
  both = inside & np.isfinite(rows_a) & np.isfinite(other)
  return both & (np.abs(np.where(both, rows_a - other, 0.0)) > tolerance), both


def match_views(decoded: StereoDecoded, match: MatchConfig = MatchConfig()) -> StereoDecoded:
  """Sets decoded.disp0 and disp1 (left-right checked disparity from the coarsest match bits of
  the two views, less the matches the row check refuses) and decoded.bits; returns decoded."""
  bits = match_bits(decoded, match)
  maps = [coarse_codes(v, decoded.code, bits, decoded.projector[0])
          for v in (decoded.left, decoded.right)]
  bounds = None
  if match.subpixel and decoded.raw is not None:
    bounds = tuple(code_bounds(raw, column, edge, decoded.code, bits)
                   for raw, (column, edge) in zip(decoded.raw, maps))
  d0, d1 = disparity_from_codes(maps[0][0], maps[1][0], lr_check=True, max_gap=match.max_gap,
                                lr_tolerance=match.lr_tolerance,
                                edges=(maps[0][1], maps[1][1]) if match.edges else None,
                                edge_tolerance=match.edge_tolerance, bounds=bounds)
  if decoded.rows is not None:
    bad0, checked0 = _row_mismatch(d0, decoded.rows[0], decoded.rows[1], 1.0,
                                   match.row_tolerance)
    bad1, _ = _row_mismatch(d1, decoded.rows[1], decoded.rows[0], -1.0, match.row_tolerance)
    decoded.row_rejected, decoded.row_checked = int(bad0.sum()), int(checked0.sum())
    d0 = np.where(bad0, np.float32(np.inf), d0)
    d1 = np.where(bad1, np.float32(np.inf), d1)
    # A pixel whose partner was refused is no longer confirmed by the other view.
    d0, d1 = lr_check_disparities(d0, d1, match.lr_tolerance)
  decoded.disp0, decoded.disp1, decoded.bits = d0, d1, bits
  return decoded


def decode_stereo(raw0: Mapping[str, np.ndarray], raw1: Mapping[str, np.ndarray], code: str,
                  config: DecodeConfig = DecodeConfig(), *,
                  projector: tuple[int | None, int | None] = (None, None),
                  rows: tuple[Mapping[str, np.ndarray], Mapping[str, np.ndarray]] | None = None,
                  match: MatchConfig = MatchConfig(),
                  where: tuple[str, str] = ("raw0", "raw1")) -> StereoDecoded:
  """decode_views then match_views: patterns, codes and disparity of both views."""
  return match_views(decode_views(raw0, raw1, code, config, projector=projector, rows=rows,
                                  where=where), match)
