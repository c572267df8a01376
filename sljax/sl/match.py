"""Stereo from decoded structured-light codes: equal codes on a rectified scanline match.

Each projector code lights a stripe that a camera sees as a run of pixels on every row (wider
or narrower than the projector column, depending on depth and slant). For each (row, code)
the run's extent [x_min, x_max] is found in the left and in the right view; its centre is
c = (x_min + x_max) / 2 and its width w = x_max - x_min + 1 (midpoints are insensitive to
unknown pixels inside the run, unlike means).

Disparity (left pixel x, code run centres c_l, c_r and widths w_l, w_r):

    d(x) = x - (c_r + (x - c_l) * w_r / w_l)

i.e. the run is mapped affinely from the left onto the right view. This is exact for a
locally planar surface, whose left-to-right mapping x -> x - d(x) is affine, and reduces to
d = c_l - c_r at the run centre (and for runs of equal width). The right view is treated
symmetrically: a right pixel x has disparity d1(x) = (c_l + (x - c_r) * w_l / w_r) - x
(left pixel x + d1 matches it, Middlebury disp1 convention).

A code that appears on one row in separate places (occlusion, or both sides of a projector
shadow) cannot be matched reliably, so it is unknown: two consecutive pixels of one code on a
row belong to different runs when another valid code lies between them or more than
`max_gap` unknown pixels separate them. Unknown disparity is inf.
"""

import numpy as np

from sljax.errors import require


def _view_runs(col: np.ndarray, offset: int, n_codes: int, max_gap: int):
  """(pixel ys, xs, keys) and (unique keys, x_min, x_max, split) of one code map."""
  valid = np.isfinite(col)
  ys, xs = np.nonzero(valid)
  code = np.rint(col[ys, xs]).astype(np.int64) - offset
  keys = ys.astype(np.int64) * n_codes + code
  if keys.size == 0:
    empty = np.zeros(0, np.float64)
    return (ys, xs, keys), (keys, empty, empty, np.zeros(0, bool))
  # Stable sort by key keeps the row-major (x increasing) order inside every (row, code).
  order = np.argsort(keys, kind="stable")
  sk, sx, sy = keys[order], xs[order], ys[order]
  starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
  ends = np.r_[starts[1:], sk.size] - 1
  # Consecutive same-code pixels: a break if other valid pixels or a wide unknown gap lie between.
  same = sk[1:] == sk[:-1]
  cum = np.cumsum(valid, axis=1)  # valid pixels in [0, x] of each row
  x0, x1, yy = sx[:-1], sx[1:], sy[:-1]
  between_valid = cum[yy, np.maximum(x1 - 1, 0)] - cum[yy, x0]
  gap = x1 - x0 - 1
  brk = same & ((between_valid > 0) | (gap > max_gap))
  brk_cum = np.r_[0, np.cumsum(brk)]
  split = (brk_cum[ends] - brk_cum[starts]) > 0
  return (ys, xs, keys), (sk[starts], sx[starts].astype(np.float64),
                          sx[ends].astype(np.float64), split)


def _disparity(pix, runs_a, runs_b, sign: float, shape) -> np.ndarray:
  """Disparity of view a's pixels from the runs of both views (sign +1 left, -1 right)."""
  ys, xs, keys = pix
  uk_a, min_a, max_a, split_a = runs_a
  uk_b, min_b, max_b, split_b = runs_b
  out = np.full(shape, np.inf, np.float32)
  if keys.size == 0 or uk_b.size == 0:
    return out
  ia = np.searchsorted(uk_a, keys)
  ib = np.clip(np.searchsorted(uk_b, keys), 0, uk_b.size - 1)
  ok = (uk_b[ib] == keys) & ~split_a[ia] & ~split_b[ib]
  ca = 0.5 * (min_a[ia] + max_a[ia])
  cb = 0.5 * (min_b[ib] + max_b[ib])
  wa = max_a[ia] - min_a[ia] + 1.0
  wb = max_b[ib] - min_b[ib] + 1.0
  x_other = cb + (xs - ca) * (wb / wa)
  d = sign * (xs - x_other)
  out[ys[ok], xs[ok]] = d[ok].astype(np.float32)
  return out


def _lr_consistent(d_a: np.ndarray, d_b: np.ndarray, sign: float, tol: float) -> np.ndarray:
  """Mask of view a's pixels whose disparity agrees with view b at the matched pixel."""
  h, w = d_a.shape
  finite = np.isfinite(d_a)
  xs = np.arange(w, dtype=np.float64)[None, :]
  xb = np.rint(xs - sign * np.where(finite, d_a, 0.0)).astype(np.int64)
  inside = finite & (xb >= 0) & (xb < w)
  rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
  back = d_b[rows, np.clip(xb, 0, w - 1)]
  both = inside & np.isfinite(back)
  return both & (np.abs(np.where(both, d_a, 0.0) - np.where(both, back, 0.0)) <= tol)


def disparity_from_codes(col0: np.ndarray, col1: np.ndarray, lr_check: bool = True,
                         max_disp: float | None = None, *, max_gap: int = 2,
                         lr_tolerance: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
  """Left and right disparity (float32 HxW, inf unknown) from decoded code maps (NaN unknown).

  Codes are compared after rounding to integers. With max_disp, disparities outside
  [0, max_disp] are unknown. lr_check marks pixels whose disparity differs by more than
  lr_tolerance from the other view's disparity at the matched pixel (nearest) as unknown.
  """
  col0 = np.asarray(col0, np.float64)
  col1 = np.asarray(col1, np.float64)
  require(col0.ndim == 2 and col0.shape == col1.shape,
          f"code maps must be HxW of one shape, got {col0.shape} and {col1.shape}")
  require(max_gap >= 0, f"max_gap must be >= 0, got {max_gap}")
  finite = np.concatenate([col0[np.isfinite(col0)], col1[np.isfinite(col1)]])
  if finite.size == 0:
    inf = np.full(col0.shape, np.inf, np.float32)
    return inf, inf.copy()
  lo, hi = int(np.rint(finite.min())), int(np.rint(finite.max()))
  n_codes = hi - lo + 1
  pix0, runs0 = _view_runs(col0, lo, n_codes, max_gap)
  pix1, runs1 = _view_runs(col1, lo, n_codes, max_gap)
  d0 = _disparity(pix0, runs0, runs1, 1.0, col0.shape)
  d1 = _disparity(pix1, runs1, runs0, -1.0, col0.shape)
  if max_disp is not None:
    for d in (d0, d1):
      d[(d < 0) | (d > max_disp)] = np.inf
  if lr_check:
    ok0 = _lr_consistent(d0, d1, 1.0, lr_tolerance)
    ok1 = _lr_consistent(d1, d0, -1.0, lr_tolerance)
    d0 = np.where(ok0, d0, np.float32(np.inf))
    d1 = np.where(ok1, d1, np.float32(np.inf))
  return d0.astype(np.float32), d1.astype(np.float32)
