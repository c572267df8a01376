import numpy as np
import pytest

from sljax.errors import SljaxError
from sljax.sl.match import disparity_from_codes

NAN = np.nan


def _rows(*rows):
  return np.array(rows, dtype=np.float32)


def _naive_disparity(col_a, col_b, sign):
  """Reference: loops over rows and codes; affine run mapping, split runs unknown (max_gap 0)."""
  h, w = col_a.shape
  out = np.full((h, w), np.inf)
  for y in range(h):
    for x in range(w):
      c = col_a[y, x]
      if not np.isfinite(c):
        continue
      xa = [i for i in range(w) if col_a[y, i] == c]
      xb = [i for i in range(w) if col_b[y, i] == c]
      if not xb:
        continue
      # A run is contiguous when its pixels form one block without holes.
      if xa[-1] - xa[0] + 1 != len(xa) or xb[-1] - xb[0] + 1 != len(xb):
        continue
      ca, cb = (xa[0] + xa[-1]) / 2, (xb[0] + xb[-1]) / 2
      wa, wb = len(xa), len(xb)
      out[y, x] = sign * (x - (cb + (x - ca) * wb / wa))
  return out


def test_equal_width_runs_give_exact_integer_disparities():
  left = _rows([NAN, NAN, 0, 0, 0, 1, 1, 1, 2, 2, 2, NAN],
               [5, 5, 6, 6, 7, 7, NAN, NAN, NAN, NAN, NAN, NAN])
  right = _rows([0, 0, 0, 1, 1, 1, 2, 2, 2, NAN, NAN, NAN],
                [NAN, NAN, NAN, 5, 5, 6, 6, 7, 7, NAN, NAN, NAN])
  d0, d1 = disparity_from_codes(left, right)
  e0 = _rows([np.inf, np.inf, 2, 2, 2, 2, 2, 2, 2, 2, 2, np.inf],
             [-3, -3, -3, -3, -3, -3] + [np.inf] * 6)
  # Negative disparities are allowed without max_disp; the second row is consistent anyway.
  np.testing.assert_array_equal(d0, e0)
  e1 = _rows([2, 2, 2, 2, 2, 2, 2, 2, 2] + [np.inf] * 3,
             [np.inf] * 3 + [-3] * 6 + [np.inf] * 3)
  np.testing.assert_array_equal(d1, e1)
  assert d0.dtype == np.float32 and d1.dtype == np.float32
  # max_disp = 10 removes the negative row.
  d0, _ = disparity_from_codes(left, right, max_disp=10)
  assert np.isinf(d0[1]).all() and (d0[0, 2:11] == 2).all()


def test_slanted_runs_use_affine_mapping():
  # Code 3 covers 4 left pixels and 2 right pixels: the surface is strongly slanted.
  left = _rows([NAN] * 10 + [3, 3, 3, 3] + [NAN] * 6)
  right = _rows([NAN] * 5 + [3, 3] + [NAN] * 13)
  d0, d1 = disparity_from_codes(left, right, lr_check=False)
  # Left pixel x covers [x - .5, x + .5]; run [9.5, 13.5] maps onto [4.5, 6.5] affinely.
  for x in range(10, 14):
    xr = 4.5 + (x - 9.5) * 0.5
    assert d0[0, x] == pytest.approx(x - xr)
  for x in (5, 6):
    xl = 9.5 + (x - 4.5) * 2.0
    assert d1[0, x] == pytest.approx(xl - x)


def test_split_runs_are_unknown():
  # Code 4 appears twice on the right row, separated by code 9 (an occlusion).
  left = _rows([NAN, NAN, 4, 4, 5, 5, NAN, NAN, NAN, NAN])
  right = _rows([4, 9, 9, 4, 5, 5, NAN, NAN, NAN, NAN])
  d0, d1 = disparity_from_codes(left, right, lr_check=False)
  assert np.isinf(d0[0, 2:4]).all() and np.isinf(d1[0, [0, 3]]).all()
  np.testing.assert_array_equal(d0[0, 4:6], [0, 0])
  # Split by a wide unknown gap: unknown; by a small one: tolerated (centre from the extent).
  left = _rows([NAN, 4, 4, NAN, 4, 4, NAN, NAN, NAN, NAN, NAN, NAN])
  right = _rows([4, 4, NAN, 4, 4, NAN, NAN, NAN, NAN, NAN, NAN, NAN])
  d0, _ = disparity_from_codes(left, right, lr_check=False, max_gap=1)
  np.testing.assert_array_equal(d0[0, [1, 2, 4, 5]], [1, 1, 1, 1])
  d0, _ = disparity_from_codes(left, right, lr_check=False, max_gap=0)
  assert np.isinf(d0).all()


def test_codes_only_in_one_view_or_other_rows_are_unknown():
  left = _rows([1, 1, 2, 2], [NAN, NAN, NAN, NAN])
  right = _rows([NAN, NAN, NAN, NAN], [1, 1, 2, 2])  # same codes, wrong row
  d0, d1 = disparity_from_codes(left, right)
  assert np.isinf(d0).all() and np.isinf(d1).all()
  d0, d1 = disparity_from_codes(np.full((3, 4), NAN), np.full((3, 4), NAN))
  assert np.isinf(d0).all() and np.isinf(d1).all()


def test_left_right_check():
  # Code 7 is seen 1 px wide on the left and 5 px wide on the right: the affine map sends the
  # left pixel to the right run's centre (d = 2), but the right run's outer pixels map back
  # to left pixels without that disparity.
  left = _rows([NAN, NAN, NAN, NAN, NAN, 7, 8, 8, NAN, NAN])
  right = _rows([NAN, 7, 7, 7, 7, 7, 8, 8, NAN, NAN])
  d0_raw, d1_raw = disparity_from_codes(left, right, lr_check=False)
  d0, d1 = disparity_from_codes(left, right, lr_check=True)
  w = left.shape[1]
  for x in range(w):  # independent loop over pixels
    if np.isfinite(d0_raw[0, x]):
      xr = int(np.rint(x - d0_raw[0, x]))
      ok = 0 <= xr < w and np.isfinite(d1_raw[0, xr]) and abs(d0_raw[0, x] - d1_raw[0, xr]) <= 1
      assert np.isfinite(d0[0, x]) == ok
      if ok:
        assert d0[0, x] == d0_raw[0, x]
    if np.isfinite(d1_raw[0, x]):
      xl = int(np.rint(x + d1_raw[0, x]))
      ok = 0 <= xl < w and np.isfinite(d0_raw[0, xl]) and abs(d1_raw[0, x] - d0_raw[0, xl]) <= 1
      assert np.isfinite(d1[0, x]) == ok
  assert d0_raw[0, 5] == 2.0 and np.isfinite(d0[0, 5])  # maps onto the run centre, x = 3
  assert np.isinf(d1[0, 1]) and np.isinf(d1[0, 5])  # outer pixels of the wide run fail


def test_random_code_maps_against_naive_reference():
  rng = np.random.default_rng(0)
  for _ in range(5):
    # Monotone-ish code maps with random run lengths, holes and occasional repeats.
    h, w = 4, 30
    left = np.repeat(np.arange(w)[None], h, 0) // rng.integers(1, 4)
    right = np.roll(left, -rng.integers(0, 5), axis=1).astype(np.float32)
    left = left.astype(np.float32)
    for m in (left, right):
      m[rng.random(m.shape) < 0.1] = NAN
      m[rng.random(m.shape) < 0.05] = rng.integers(0, 10)
    d0, d1 = disparity_from_codes(left, right, lr_check=False, max_gap=0)
    np.testing.assert_allclose(d0, _naive_disparity(left, right, 1.0), rtol=0, atol=1e-5)
    np.testing.assert_allclose(d1, _naive_disparity(right, left, -1.0), rtol=0, atol=1e-5)


def test_shape_mismatch():
  with pytest.raises(SljaxError, match="shape"):
    disparity_from_codes(np.zeros((2, 3)), np.zeros((2, 4)))
