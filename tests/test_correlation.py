"""sljax.corr.correlation against a naive float64 loop of the paper's formula (eq. 4-5)."""

import numpy as np
import pytest

from sljax.corr import correlation as corr
from sljax.corr import rows
from sljax.errors import SljaxError


def naive_volume(a, b, u, w, sign=-1):
  """cc[s, y, x] = sum over the w x w window at (x, y) of a(x', y') . b(x' + sign * s, y').

  Literal loops; every read outside the image (window or shifted pixel) contributes 0.
  sign = -1 is the left-referenced formula; sign = +1 matches the right view against the left.
  """
  a = np.nan_to_num(np.asarray(a, np.float64))
  b = np.nan_to_num(np.asarray(b, np.float64))
  h, wd, _ = a.shape
  r = w // 2
  cc = np.zeros((u + 1, h, wd))
  for s in range(u + 1):
    for y in range(h):
      for x in range(wd):
        total = 0.0
        for yy in range(y - r, y + r + 1):
          for xx in range(x - r, x + r + 1):
            xs = xx + sign * s
            if 0 <= yy < h and 0 <= xx < wd and 0 <= xs < wd:
              total += float(np.dot(a[yy, xx], b[yy, xs]))
        cc[s, y, x] = total
  return cc


def naive_zncc(a, b, u, w):
  """Zero-mean normalised cc over the window and all patterns, zero-padded, float64 loops."""
  a = np.asarray(a, np.float64)
  b = np.asarray(b, np.float64)
  h, wd, t = a.shape
  r = w // 2
  n = w * w * t
  out = np.zeros((u + 1, h, wd))
  for s in range(u + 1):
    for y in range(h):
      for x in range(wd):
        wa = np.zeros((w, w, t))
        wb = np.zeros((w, w, t))
        for i, yy in enumerate(range(y - r, y + r + 1)):
          for j, xx in enumerate(range(x - r, x + r + 1)):
            if 0 <= yy < h and 0 <= xx < wd:
              wa[i, j] = a[yy, xx]
              if xx - s >= 0:
                wb[i, j] = b[yy, xx - s]
        cov = (wa * wb).sum() - wa.sum() * wb.sum() / n
        va = (wa * wa).sum() - wa.sum() ** 2 / n
        vb = (wb * wb).sum() - wb.sum() ** 2 / n
        den = np.sqrt(max(va, 0.0) * max(vb, 0.0))
        out[s, y, x] = cov / den if den > 1e-9 else 0.0
  return out


def binary(rng, shape):
  return (rng.random(shape) < 0.5).astype(np.float32)


# (H, W, t, u, window): odd widths, t = 8 and 9, windows and shifts larger than the image.
CASES = [(7, 11, 8, 4, 3), (9, 13, 9, 6, 5), (6, 9, 8, 10, 17), (5, 7, 9, 0, 1)]


@pytest.mark.parametrize("case", CASES)
def test_binary_equals_naive_loop_exactly(case):
  h, w, t, u, win = case
  rng = np.random.default_rng(sum(case))
  pl, pr = binary(rng, (h, w, t)), binary(rng, (h, w, t))
  ref = naive_volume(pl, pr, u, win)
  disp, peak = corr.sl_disparity(pl, pr, u, win)
  assert disp.dtype == np.float32 and disp.shape == (h, w)
  np.testing.assert_array_equal(disp, np.argmax(ref, axis=0))  # first maximum = smallest s
  np.testing.assert_array_equal(peak, ref.max(axis=0))
  if win == 3:  # small windows on random bits do produce ties, so the tie rule is exercised
    assert (ref == ref.max(axis=0)).sum(axis=0).max() > 1


def reference_volume(a, b, u, w):
  """The formula vectorised over pixels in float64: per shift, the channel-summed product of the
  left view and the right view shifted by s (zeros where x - s < 0), then the w x w window sum
  as w * w explicit shifted adds of a zero-padded map (no doubling tree, no matrix product)."""
  a = np.nan_to_num(np.asarray(a, np.float64))
  b = np.nan_to_num(np.asarray(b, np.float64))
  h, wd, _ = a.shape
  r = w // 2
  cc = np.zeros((u + 1, h, wd))
  for s in range(u + 1):
    shifted = np.zeros_like(b)
    shifted[:, s:] = b[:, :wd - s] if s < wd else 0.0
    prod = np.pad((a * shifted).sum(axis=2), r)
    for dy in range(w):
      for dx in range(w):
        cc[s] += prod[dy:dy + h, dx:dx + wd]
  return cc


def test_reference_volume_is_the_naive_loop():
  rng = np.random.default_rng(21)
  a, b = rng.random((6, 9, 3)), rng.random((6, 9, 3))
  np.testing.assert_allclose(reference_volume(a, b, 4, 5), naive_volume(a, b, 4, 5), rtol=1e-12)


# Larger odd sizes for the row path: several blocks of _COLS columns (W + window - 1 > 64),
# several row bands (band_rows below the height, one band shorter than the window), t = 8 and 9,
# the paper's window 17 and shifts past the image's left edge.
ROW_CASES = [(41, 83, 9, 29, 17, 7), (37, 75, 8, 35, 9, 16), (23, 131, 9, 40, 17, 10),
             (19, 67, 8, 70, 5, 1000)]


@pytest.mark.parametrize("case", ROW_CASES)
def test_row_path_equals_formula_on_odd_sizes(case):
  h, w, t, u, win, band_rows = case
  rng = np.random.default_rng(sum(case))
  pl, pr = binary(rng, (h, w, t)), binary(rng, (h, w, t))
  ref = reference_volume(pl, pr, u, win)
  disp, peak, _ = rows.rows_disparity(pl, pr, u, win, False, False, band_rows=band_rows)
  np.testing.assert_array_equal(disp, np.argmax(ref, axis=0))
  np.testing.assert_array_equal(peak, ref.max(axis=0))
  public = corr.sl_disparity(pl, pr, u, win)  # default bands and threads
  np.testing.assert_array_equal(public[0], disp)
  np.testing.assert_array_equal(public[1], peak)
  np.testing.assert_array_equal(corr.cost_volume(pl, pr, u, win), ref.astype(np.float32))
  # Probabilities: float32 sums of float32 products, within a few ulps of the float64 formula.
  qa = rng.random((h, w, t), dtype=np.float32)
  qb = rng.random((h, w, t), dtype=np.float32)
  ref = reference_volume(qa, qb, u, win)
  disp, peak, _ = rows.rows_disparity(qa, qb, u, win, False, False, band_rows=band_rows)
  np.testing.assert_allclose(peak, ref.max(axis=0), rtol=2e-6)
  top2 = np.sort(ref, axis=0)[-2:]
  clear = (top2[1] - top2[0]) > 1e-4 * top2[1]
  assert clear.mean() > 0.9
  np.testing.assert_array_equal(disp[clear], np.argmax(ref, axis=0)[clear])


def test_probabilities_close_to_float64_loop():
  rng = np.random.default_rng(3)
  pl = rng.random((8, 13, 9)).astype(np.float32)
  pr = rng.random((8, 13, 9)).astype(np.float32)
  ref = naive_volume(pl, pr, 5, 5)
  disp, peak = corr.sl_disparity(pl, pr, 5, 5)
  np.testing.assert_allclose(peak, ref.max(axis=0), rtol=2e-6)
  top2 = np.sort(ref, axis=0)[-2:]
  clear = (top2[1] - top2[0]) > 1e-4 * top2[1]  # float32 may only reorder near-ties
  assert clear.mean() > 0.9
  np.testing.assert_array_equal(disp[clear], np.argmax(ref, axis=0)[clear])


def test_tie_takes_smallest_shift_and_nan_reads_zero():
  pl = np.zeros((3, 12, 8), np.float32)
  pr = np.zeros((3, 12, 8), np.float32)
  pl[1, 8, :] = 1
  pr[1, 6, :] = 1  # shift 2
  pr[1, 3, :] = 1  # shift 5, same score
  pr[0, :, :] = np.nan  # unknown patterns contribute nothing
  disp, peak = corr.sl_disparity(pl, pr, 6, 3)
  assert disp[1, 8] == 2 and peak[1, 8] == 8
  assert disp[1, 0] == 0 and peak[1, 0] == 0  # all-zero scores tie at every shift -> 0
  # without the nearer copy the farther one wins
  pr[1, 6, :] = 0
  disp, _ = corr.sl_disparity(pl, pr, 6, 3)
  assert disp[1, 8] == 5


def test_default_max_disp_is_quarter_width():
  assert corr.default_max_disp(256) == 64 and corr.default_max_disp(1280) == 320
  assert corr.default_max_disp(13) == 3


@pytest.fixture(scope="module")
def pair():
  rng = np.random.default_rng(7)
  return binary(rng, (8, 13, 8)), binary(rng, (8, 13, 8))


@pytest.mark.parametrize("kind", ["binary", "prob"])
def test_bounded_path_equals_direct_path(kind, pair):
  rng = np.random.default_rng(11)
  pl, pr = pair if kind == "binary" else (rng.random((8, 13, 8), dtype=np.float32),
                                          rng.random((8, 13, 8), dtype=np.float32))
  u = 7
  vol = corr.cost_volume(pl, pr, u, 5)
  assert vol.shape == (u + 1, 8, 13)
  direct = corr.sl_disparity(pl, pr, u, 5, block=u + 1)
  np.testing.assert_array_equal(direct[0], np.argmax(vol, axis=0))
  np.testing.assert_array_equal(direct[1], vol.max(axis=0))
  for block in (1, 3):  # 3 does not divide u + 1: the last block is partly past u
    bounded = corr.sl_disparity(pl, pr, u, 5, block=block)
    np.testing.assert_array_equal(bounded[0], direct[0])
    np.testing.assert_array_equal(bounded[1], direct[1])


def test_choose_block_respects_budget():
  assert corr.choose_block(1, 8, 13, 7) == 8
  per_shift = corr.choose_block(1, 1024, 1280, 320, budget=1)
  assert per_shift == 1
  assert corr.choose_block(4, 256, 256, 64, budget=64 * 2**20) <= corr.choose_block(
      1, 256, 256, 64, budget=64 * 2**20)


def test_batched_equals_per_image():
  rng = np.random.default_rng(5)
  pl = rng.random((3, 7, 11, 8), dtype=np.float32)
  pr = rng.random((3, 7, 11, 8), dtype=np.float32)
  disp, peak = corr.sl_disparity(pl, pr, 4, 3, block=2)
  assert disp.shape == (3, 7, 11)
  for i in range(3):
    d, p = corr.sl_disparity(pl[i], pr[i], 4, 3, block=2)
    np.testing.assert_array_equal(disp[i], d)
    np.testing.assert_array_equal(peak[i], p)


def test_subpixel_and_confidence_match_naive(pair):
  pl, pr = pair
  u, win = 6, 5
  ref = naive_volume(pl, pr, u, win)
  d0 = np.argmax(ref, axis=0)
  c0 = ref.max(axis=0)
  disp, peak, conf = corr.sl_disparity(pl, pr, u, win, subpixel=True, confidence=True, block=3)
  hh, ww = np.meshgrid(np.arange(8), np.arange(13), indexing="ij")
  cm = np.where(d0 > 0, ref[np.maximum(d0 - 1, 0), hh, ww], 0)
  cp = np.where(d0 < u, ref[np.minimum(d0 + 1, u), hh, ww], 0)
  curv = cm - 2 * c0 + cp
  inside = (d0 > 0) & (d0 < u) & (curv < 0)
  expect = d0 + np.where(inside, np.clip(0.5 * (cm - cp) / np.where(inside, curv, -1), -.5, .5), 0)
  np.testing.assert_allclose(disp, expect, atol=1e-6)
  np.testing.assert_array_equal(peak, c0)
  s = np.arange(u + 1)[:, None, None]
  c2 = np.where(np.abs(s - d0) > 1, ref, -np.inf).max(axis=0)
  expect_conf = np.where(c0 > 0, 1 - c2 / np.where(c0 > 0, c0, 1), 0)
  np.testing.assert_allclose(conf, np.clip(expect_conf, 0, 1), atol=1e-6)
  assert np.any(disp != np.round(disp))  # the refinement does move some pixels


def test_lr_check_matches_naive(pair):
  pl, pr = pair
  u, win = 5, 3
  d_l = np.argmax(naive_volume(pl, pr, u, win), axis=0)
  d_r = np.argmax(naive_volume(pr, pl, u, win, sign=+1), axis=0)
  disp, _ = corr.sl_disparity(pl, pr, u, win, lr_check=True)
  x = np.arange(13)[None, :]
  xr = x - d_l
  ok = (xr >= 0) & (np.abs(d_l - np.take_along_axis(d_r, np.clip(xr, 0, 12), axis=1)) <= 1)
  np.testing.assert_array_equal(disp, np.where(ok, d_l, np.inf).astype(np.float32))
  assert 0 < np.isinf(disp).mean() < 1


def test_normalized_matches_naive_zncc():
  rng = np.random.default_rng(9)
  pl = rng.random((6, 11, 8), dtype=np.float32)
  pr = rng.random((6, 11, 8), dtype=np.float32)
  ref = naive_zncc(pl, pr, 4, 3)
  disp, peak = corr.sl_disparity(pl, pr, 4, 3, normalized=True)
  np.testing.assert_allclose(peak, ref.max(axis=0), atol=2e-5)
  top2 = np.sort(ref, axis=0)[-2:]
  clear = (top2[1] - top2[0]) > 1e-3
  np.testing.assert_array_equal(disp[clear], np.argmax(ref, axis=0)[clear])
  assert np.all(np.abs(peak) <= 1 + 1e-5)


def test_ground_truth_patterns_of_synthetic_scene_give_its_disparity():
  from sljax.render.synthetic import SynthConfig, render_scene
  scene = render_scene(0, 0, SynthConfig(size=128, domain="tissue"))
  disp, _ = corr.sl_disparity(scene.sl0, scene.sl1, window=17)
  assert disp.shape == scene.disp0.shape
  # Valid: known ground truth, seen by both cameras, lit by the projector. The finest patterns
  # alias on steep surfaces and are NaN there (read as 0 by the correlation), so projector
  # shadow is judged on the coarsest pattern, which is known wherever any light falls.
  valid = np.isfinite(scene.disp0) & ~scene.occ0 & ~np.isnan(scene.sl0[..., 0])
  assert valid.mean() > 0.5
  assert (np.abs(disp - scene.disp0)[valid] <= 1).mean() >= 0.95


@pytest.mark.parametrize("kwargs, match", [
    ({"p_right": np.zeros((4, 6, 3))}, "same shape"),
    ({"window": 4}, "odd"),
    ({"max_disp": -1}, "max_disp"),
    ({"block": 0}, "block"),
])
def test_bad_input_raises_clear_error(kwargs, match):
  args = {"p_left": np.zeros((4, 5, 3)), "p_right": np.zeros((4, 5, 3))}
  args.update(kwargs)
  with pytest.raises(SljaxError, match=match):
    corr.sl_disparity(**args)
  with pytest.raises(SljaxError, match="HxWxt"):
    corr.sl_disparity(np.zeros((4, 5)), np.zeros((4, 5)))
