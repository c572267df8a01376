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

A pixel on the boundary between the stripes of codes c and c + 1 (a Gray code changes one bit
there, which the camera sees half lit: an uncertain bit) has no code of its own; given as an
edge pixel it takes the mean of the two runs' mappings, which agree on a smooth surface.
"""

import numpy as np

from sljax.errors import require


def _view_runs(col: np.ndarray, offset: int, n_codes: int, max_gap: int,
               bounds: np.ndarray | None = None):
  """(pixel ys, xs, keys) and (unique keys, extent start, extent end, split) of one code map
  (bounds: see disparity_from_codes)."""
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
  # Continuous extents: a run of pixels x_min..x_max covers [x_min - 0.5, x_max + 0.5], unless
  # the position of a boundary with a neighbouring code is known more precisely.
  lo = sx[starts].astype(np.float64) - 0.5
  hi = sx[ends].astype(np.float64) + 0.5
  if bounds is not None:
    row = sy[starts]
    left = bounds[row, np.maximum(sx[starts] - 1, 0)]
    right = bounds[row, sx[ends]]
    lo = np.where(np.isfinite(left) & (sx[starts] >= 1), left, lo)
    hi = np.where(np.isfinite(right), right, hi)
  return (ys, xs, keys), (sk[starts], lo, hi, split)


def _affine(ys, xs, keys, runs_a, runs_b, sign: float) -> tuple[np.ndarray, np.ndarray]:
  """(disparity, matched) of view a's pixels (ys, xs) mapped through the runs of their keys."""
  uk_a, min_a, max_a, split_a = runs_a
  uk_b, min_b, max_b, split_b = runs_b
  if keys.size == 0 or uk_a.size == 0 or uk_b.size == 0:
    return np.zeros(keys.size), np.zeros(keys.size, bool)
  ia = np.clip(np.searchsorted(uk_a, keys), 0, uk_a.size - 1)
  ib = np.clip(np.searchsorted(uk_b, keys), 0, uk_b.size - 1)
  ok = (uk_a[ia] == keys) & (uk_b[ib] == keys) & ~split_a[ia] & ~split_b[ib]
  ca = 0.5 * (min_a[ia] + max_a[ia])
  cb = 0.5 * (min_b[ib] + max_b[ib])
  wa = max_a[ia] - min_a[ia]
  wb = max_b[ib] - min_b[ib]
  ok &= (wa > 0) & (wb > 0)
  x_other = cb + (xs - ca) * (wb / wa)
  return sign * (xs - x_other), ok


def _disparity(pix, runs_a, runs_b, sign: float, shape) -> np.ndarray:
  """Disparity of view a's pixels from the runs of both views (sign +1 left, -1 right)."""
  ys, xs, keys = pix
  out = np.full(shape, np.inf, np.float32)
  d, ok = _affine(ys, xs, keys, runs_a, runs_b, sign)
  out[ys[ok], xs[ok]] = d[ok].astype(np.float32)
  return out


def _edge_disparity(edges: np.ndarray, offset: int, n_codes: int, runs_a, runs_b, sign: float,
                    tolerance: float, out: np.ndarray) -> None:
  """Writes into out the disparity of view a's boundary pixels (edges: the lower code c of the
  boundary between codes c and c + 1, NaN elsewhere): the mean of both runs' mappings, where
  both runs are matched and agree within tolerance."""
  ys, xs = np.nonzero(np.isfinite(edges))
  lo = np.rint(edges[ys, xs]).astype(np.int64) - offset
  inside = (lo >= 0) & (lo + 1 < n_codes)
  ys, xs, lo = ys[inside], xs[inside], lo[inside]
  base = ys.astype(np.int64) * n_codes
  d_lo, ok_lo = _affine(ys, xs, base + lo, runs_a, runs_b, sign)
  d_hi, ok_hi = _affine(ys, xs, base + lo + 1, runs_a, runs_b, sign)
  ok = ok_lo & ok_hi & (np.abs(d_lo - d_hi) <= tolerance)
  out[ys[ok], xs[ok]] = (0.5 * (d_lo + d_hi))[ok].astype(np.float32)


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
                         lr_tolerance: float = 1.0,
                         edges: tuple[np.ndarray, np.ndarray] | None = None,
                         edge_tolerance: float = 1.0,
                         bounds: tuple[np.ndarray, np.ndarray] | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
  """Left and right disparity (float32 HxW, inf unknown) from decoded code maps (NaN unknown).

  Codes are compared after rounding to integers. With max_disp, disparities outside
  [0, max_disp] are unknown. lr_check marks pixels whose disparity differs by more than
  lr_tolerance from the other view's disparity at the matched pixel (nearest) as unknown.
  edges: per view, pixels known to lie on the boundary between codes c and c + 1 (the value c,
  NaN elsewhere; NaN in col0 / col1): they take no part in the runs and get the mean of the two
  runs' disparities where both runs are matched and agree within edge_tolerance.
  bounds: per view, HxW sub-pixel x of the boundary between a pixel's code and the neighbouring
  code to its right (on the last pixel of a run and on a boundary pixel; NaN elsewhere): a run
  then spans [boundary on its left, boundary on its right] instead of whole pixels.
  """
  col0 = np.asarray(col0, np.float64)
  col1 = np.asarray(col1, np.float64)
  require(col0.ndim == 2 and col0.shape == col1.shape,
          f"code maps must be HxW of one shape, got {col0.shape} and {col1.shape}")
  require(max_gap >= 0, f"max_gap must be >= 0, got {max_gap}")
  if edges is not None:
    edges = tuple(np.asarray(e, np.float64) for e in edges)
    require(all(e.shape == col0.shape for e in edges),
            f"edge maps must have the code maps' shape {col0.shape}")
  finite = np.concatenate([col0[np.isfinite(col0)], col1[np.isfinite(col1)]])
  if finite.size == 0:
    inf = np.full(col0.shape, np.inf, np.float32)
    return inf, inf.copy()
  lo, hi = int(np.rint(finite.min())), int(np.rint(finite.max()))
  n_codes = hi - lo + 1
  b0, b1 = (None, None) if bounds is None else (np.asarray(b, np.float64) for b in bounds)
  pix0, runs0 = _view_runs(col0, lo, n_codes, max_gap, b0)
  pix1, runs1 = _view_runs(col1, lo, n_codes, max_gap, b1)
  d0 = _disparity(pix0, runs0, runs1, 1.0, col0.shape)
  d1 = _disparity(pix1, runs1, runs0, -1.0, col0.shape)
  if edges is not None:
    _edge_disparity(edges[0], lo, n_codes, runs0, runs1, 1.0, edge_tolerance, d0)
    _edge_disparity(edges[1], lo, n_codes, runs1, runs0, -1.0, edge_tolerance, d1)
  if max_disp is not None:
    for d in (d0, d1):
      d[(d < 0) | (d > max_disp)] = np.inf
  if lr_check:
    d0, d1 = lr_check_disparities(d0, d1, lr_tolerance)
  return d0.astype(np.float32), d1.astype(np.float32)


def lr_check_disparities(d0: np.ndarray, d1: np.ndarray, tolerance: float = 1.0
                         ) -> tuple[np.ndarray, np.ndarray]:
  """Both views' disparities with pixels that disagree with the other view (by more than
  tolerance at the matched pixel, or whose match is unknown) set to inf."""
  ok0 = _lr_consistent(d0, d1, 1.0, tolerance)
  ok1 = _lr_consistent(d1, d0, -1.0, tolerance)
  return (np.where(ok0, d0, np.float32(np.inf)).astype(np.float32),
          np.where(ok1, d1, np.float32(np.inf)).astype(np.float32))
