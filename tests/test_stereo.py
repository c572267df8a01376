"""sljax.sl.stereo and the matcher's boundary pixels and sub-pixel bounds, against hand-computed
cases and naive per-pixel loops."""

import numpy as np
import pytest

from sljax.sl import codes
from sljax.sl.decode import DecodeConfig, Decoded
from sljax.sl.match import disparity_from_codes
from sljax.sl.stereo import (MatchConfig, StereoDecoded, code_bounds, coarse_codes, column_rate,
                             decode_views, match_bits, match_views)

NAN = np.nan


def _affine_d(x, run_l, run_r):
  """Hand formula: d = x - (c_r + (x - c_l) w_r / w_l) for runs given as [start, end]."""
  cl, wl = (run_l[0] + run_l[1]) / 2, run_l[1] - run_l[0]
  cr, wr = (run_r[0] + run_r[1]) / 2, run_r[1] - run_r[0]
  return x - (cr + (x - cl) * wr / wl)


def test_sub_pixel_bounds_set_the_runs_extents():
  """Left: code 5 at x = 2..4, 6 at 5..7, their boundary at 4.7; right: 5 at 0..2, 6 at 3..5,
  boundary at 2.2. Without bounds a run covers whole pixels."""
  left = np.array([[NAN, NAN, 5, 5, 5, 6, 6, 6, NAN, NAN]])
  right = np.array([[5, 5, 5, 6, 6, 6, NAN, NAN, NAN, NAN]])
  bl, br = np.full(left.shape, NAN), np.full(left.shape, NAN)
  bl[0, 4], br[0, 2] = 4.7, 2.2
  d0, d1 = disparity_from_codes(left, right, lr_check=False, bounds=(bl, br))
  runs_l = {5: (1.5, 4.7), 6: (4.7, 7.5)}
  runs_r = {5: (-0.5, 2.2), 6: (2.2, 5.5)}
  for x in range(2, 8):
    c = int(left[0, x])
    assert d0[0, x] == pytest.approx(_affine_d(x, runs_l[c], runs_r[c]), abs=1e-5), x
  for x in range(0, 6):  # the right view: d1(x) = (c_l + (x - c_r) w_l / w_r) - x
    c = int(right[0, x])
    assert d1[0, x] == pytest.approx(-_affine_d(x, runs_r[c], runs_l[c]), abs=1e-5), x
  plain, _ = disparity_from_codes(left, right, lr_check=False)
  np.testing.assert_allclose(plain[0, 2:8], [2, 2, 2, 2, 2, 2])  # whole pixels: shift 2


def test_boundary_pixels_take_the_mean_of_both_runs():
  """A boundary pixel between codes 5 and 6 (x = 4) is in neither run and gets the mean of the
  two runs' mappings; where they disagree by more than edge_tolerance it stays unknown."""
  left = np.array([[NAN, 5, 5, 5, NAN, 6, 6, 6, NAN, NAN]])
  right = np.array([[5, 5, 5, 6, 6, 6, NAN, NAN, NAN, NAN]])
  edges = (np.where(np.arange(10) == 4, 5.0, NAN)[None], np.full((1, 10), NAN))
  d0, _ = disparity_from_codes(left, right, lr_check=False, edges=edges, edge_tolerance=2.0)
  want = 0.5 * (_affine_d(4, (0.5, 3.5), (-0.5, 2.5)) + _affine_d(4, (4.5, 7.5), (2.5, 5.5)))
  assert d0[0, 4] == pytest.approx(want, abs=1e-5)
  d0, _ = disparity_from_codes(left, right, lr_check=False, edges=edges, edge_tolerance=0.1)
  assert np.isinf(d0[0, 4])  # the two mappings differ by 1 px here
  d0, _ = disparity_from_codes(left, right, lr_check=False)
  assert np.isinf(d0[0, 4])  # without edges: unknown, as before


def _naive_coarse(bits, shadow, code, keep, count):
  """Per-pixel loop: (code of the kept bits or NaN, lower code of a boundary pixel or NaN)."""
  h, w, n = bits.shape
  column, boundary = np.full((h, w), NAN), np.full((h, w), NAN)
  limit = None if count is None else int(np.ceil(count / 2 ** (n - keep)))
  for y in range(h):
    for x in range(w):
      b = bits[y, x, :keep]
      unknown = [k for k in range(keep) if np.isnan(b[k])]

      def value(fill):
        v = [int(fill) if np.isnan(t) else int(t) for t in b]
        if code == "gray":  # binary bit k = XOR of Gray bits 0..k
          v = [int(np.bitwise_xor.reduce(v[:k + 1])) for k in range(keep)]
        return int("".join(map(str, v)), 2)

      if not unknown and (limit is None or value(0) < limit):
        column[y, x] = value(0)
      if len(unknown) == 1 and not shadow[y, x]:
        lo, hi = sorted((value(0), value(1)))
        if hi - lo == 1 and (limit is None or hi < limit):
          boundary[y, x] = lo
  return column, boundary


@pytest.mark.parametrize("code", ["gray", "binary"])
def test_coarse_codes_against_a_naive_loop(code):
  rng = np.random.default_rng(1)
  bits = rng.integers(0, 2, (9, 11, 6)).astype(np.float32)
  bits[rng.random(bits.shape) < 0.12] = NAN
  shadow = rng.random((9, 11)) < 0.1
  view = Decoded(bits=bits, column=np.full((9, 11), NAN), shadow=shadow,
                 uncertain=np.isnan(bits))
  for keep, count in ((6, None), (4, 13), (6, 50)):
    got = coarse_codes(view, code, keep, count)
    want = _naive_coarse(bits, shadow, code, keep, count)
    for g, w_ in zip(got, want):
      np.testing.assert_array_equal(np.nan_to_num(g, nan=-1), np.nan_to_num(w_, nan=-1))


def _captures(signed):
  """Captures of one 8-pixel row and a 2-bit Gray code: bit k's contrast (pattern - inverse) /
  (white - black) is signed[k] at each pixel; white 0.9, black 0.1."""
  white, black = np.full((1, 8), 0.9), np.full((1, 8), 0.1)
  raw = {"white": white, "black": black}
  for k, s in enumerate(signed):
    raw[f"p{k:03d}"] = 0.5 + 0.4 * s[None]
    raw[f"i{k:03d}"] = 0.5 - 0.4 * s[None]
  return raw


def test_code_bounds_interpolate_the_changing_bit():
  """The boundary between codes 1 and 2 (Gray 01 -> 11: bit 0 changes)
  lies where bit 0's contrast crosses zero, between two pixels or across a boundary pixel."""
  x = np.arange(8, dtype=float)
  s0 = np.clip(0.3 * (x - 3.4), -1, 1)  # bit 0 crosses zero at x = 3.4
  s1 = np.ones(8)                       # bit 1 lit everywhere
  raw = _captures([s0, s1])
  column = np.array([[1, 1, 1, 1, 2, 2, 2, 2]], float)  # Gray 01 at x <= 3, 11 beyond
  got = code_bounds(raw, column, np.full((1, 8), NAN), "gray", 2)
  assert got[0, 3] == pytest.approx(3.4) and np.isnan(got[0, [0, 1, 2, 4, 5, 6, 7]]).all()
  # A boundary pixel at x = 3 (lower code 1): the zero lies between x = 3 and 4.
  column[0, 3] = NAN
  boundary = np.where(x == 3, 1.0, NAN)[None]
  got = code_bounds(raw, column, boundary, "gray", 2)
  assert got[0, 2] == pytest.approx(3.4) and got[0, 3] == pytest.approx(3.4)
  # Codes 0 and 1 differ in bit 1 (Gray 00 -> 01): its contrast is used, not bit 0's.
  s1 = np.clip(0.25 * (x - 4.6), -1, 1)
  column = np.array([[2, 2, 2, 2, 2, 3, 3, 3]], float)  # Gray 11 -> 10: bit 1 changes
  got = code_bounds(_captures([np.ones(8), -s1]), column, np.full((1, 8), NAN), "gray", 2)
  assert got[0, 4] == pytest.approx(4.6)


def test_match_bits_rule():
  """The most bits whose stripes stay at least min_stripe_px wide: a code of the coarsest b of
  n bits spans 2^(n - b) projector columns, 2^(n - b) / rate pixels."""
  rng = np.random.default_rng(0)
  for rate, n, min_px, want in ((0.6, 8, 2.5, 7), (0.3, 8, 2.5, 8), (1.5, 9, 2.5, 7),
                                (0.6, 8, 1.0, 8), (3.0, 8, 2.5, 5)):
    ramp = np.floor(rate * np.arange(200))[None].repeat(4, 0) + rng.integers(0, 1, (4, 1))
    view = Decoded(bits=np.zeros((4, 200, n), np.float32), column=ramp.astype(np.float32),
                   shadow=np.zeros((4, 200), bool), uncertain=np.zeros((4, 200, n), bool))
    dec = StereoDecoded(left=view, right=view, code="gray")
    assert column_rate((ramp,)) == pytest.approx(rate, abs=1 / 16)
    assert match_bits(dec, MatchConfig(min_stripe_px=min_px)) == want, (rate, n, min_px)
    assert match_bits(dec, MatchConfig(bits=3)) == 3


def test_row_check_refuses_matches_that_see_another_projector_row():
  """One image pair with identical columns (disparity 0); the right view's projector rows are
  shifted by 3 on the right half: those matches are refused, in both views."""
  w, h = 64, 8
  cols = codes.patterns("gray", w)  # (6, 64)
  rows_p = codes.patterns("gray", h)  # (3, 8)
  white, black = np.full((h, w), 0.9), np.full((h, w), 0.1)

  def capture(planes):
    raw = {"white": white, "black": black}
    for k, plane in enumerate(planes):
      raw[f"p{k:03d}"] = black + 0.8 * plane
      raw[f"i{k:03d}"] = black + 0.8 * (1 - plane)
    return raw

  col_raw = capture([np.broadcast_to(c[None], (h, w)) for c in cols])
  row_left = capture([np.broadcast_to(r[:, None], (h, w)) for r in rows_p])
  shifted = np.roll(rows_p, 3, axis=1)  # another row per pixel
  row_right = capture([np.where(np.arange(w)[None] < 32, r[:, None], s[:, None])
                       for r, s in zip(rows_p, shifted)])
  dec = decode_views(col_raw, col_raw, "gray", projector=(w, h), rows=(row_left, row_right))
  match_views(dec, MatchConfig(row_tolerance=1.0))
  assert np.isfinite(dec.disp0[:, :32]).all() and np.isinf(dec.disp0[:, 32:]).all()
  assert np.isinf(dec.disp1[:, 32:]).all() and dec.row_rejected == h * 32
  assert dec.row_checked == h * w  # every left match, both rows known
  np.testing.assert_array_equal(dec.disp0[:, :32], 0)
  match_views(dec, MatchConfig(row_tolerance=8.0))
  assert np.isfinite(dec.disp0).all() and dec.row_rejected == 0 and dec.row_checked == h * w


def test_codes_beyond_the_projector_are_unknown():
  """A 12-column projector shows codes 0..11; a pixel decoding to 13 (impossible) is unknown."""
  bits = codes.encode(np.array([[3, 11, 13, 12]]), "gray", 4).astype(np.float32)
  ones = np.ones((1, 4))
  raw = {"white": ones * 0.9, "black": ones * 0.1}
  for k in range(4):
    raw[f"p{k:03d}"] = 0.1 + 0.8 * bits[..., k]
    raw[f"i{k:03d}"] = 0.9 - 0.8 * bits[..., k]
  dec = decode_views(raw, raw, "gray", DecodeConfig(), projector=(12, None))
  np.testing.assert_array_equal(np.nan_to_num(dec.left.column, nan=-1), [[3, 11, -1, -1]])
