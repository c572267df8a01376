"""The row path of the plain cross-correlation (NumPy on the host, rows split over CPU threads).

Per image row the products summed over patterns for every left column and shift are a band of
a small matrix product; the window is a separable box filter (a doubling tree along x, van Herk /
Gil-Werman blocks along y). The formulation, its exactness and the rules it follows (zero
padding, ties to the smallest shift) are described in `sljax.corr.correlation`, which calls
`rows_disparity` and `lr_checked` for `sl_disparity` with plain cc.
"""

import concurrent.futures
import os

import numpy as np

LR_TOLERANCE = 1.0  # px: left-right check passes when |d_l(x) - d_r(x - d_l(x))| <= this
_COLS = 64  # left columns per block of the per-row matrix product (u + _COLS right columns each)
BAND_ROWS = 256  # output rows per thread task; each task recomputes window - 1 rows above it


def cpu_threads() -> int:
  """CPU threads available to this process."""
  try:
    return max(1, len(os.sched_getaffinity(0)))
  except AttributeError:  # not Linux
    return max(1, os.cpu_count() or 1)


def _box_rows(p: np.ndarray, n: int, levels: list[np.ndarray], out: np.ndarray) -> None:
  """out = sums of n consecutive rows of p (valid: len(p) - n + 1 rows), as a doubling tree.

  levels[k] holds the sums of 2^(k+1) rows; each output is a fixed-order sum of at most
  log2(n) + 1 level values (no running sum, so rounding never accumulates along the row).
  """
  sums = [p]
  while 2 ** len(sums) <= n:
    prev, m = sums[-1], 2 ** (len(sums) - 1)
    length = len(prev) - m
    dst = levels[len(sums) - 1][:length]
    np.add(prev[:length], prev[m:m + length], out=dst)
    sums.append(dst)
  parts, offset = [], 0
  for k in range(len(sums) - 1, -1, -1):
    if n & (1 << k):
      parts.append(sums[k][offset:offset + len(out)])
      offset += 1 << k
  if len(parts) == 1:
    np.copyto(out, parts[0])
    return
  np.add(parts[0], parts[1], out=out)
  for part in parts[2:]:
    np.add(out, part, out=out)


class _RowProducts:
  """Per-row x-boxed correlation maps of one image pair (HxWxt float32, NaN already 0)."""

  def __init__(self, pl: np.ndarray, pr: np.ndarray, u: int, window: int):
    h, w, t = pl.shape
    r = window // 2
    self.h, self.w, self.t, self.u, self.window, self.r = h, w, t, u, window, r
    self.wp = w + 2 * r  # x-box input: r zero columns on each side
    self.nb = -(-self.wp // _COLS)
    self.m = _COLS + u  # right columns one block of left columns reaches
    span = (self.nb - 1) * _COLS + self.m
    # Left: column j holds x = j - r. Right, reversed: row position q holds x = span - 1 - q - u
    # - r, so block b (left columns b*_COLS...) meets right positions starting at
    # (nb - 1 - b) * _COLS, increasing with the shift: one strided view serves every block.
    self.left = np.zeros((h, self.nb * _COLS, t), np.float32)
    self.left[:, r:r + w] = pl
    right = np.zeros((h, span, t), np.float32)
    right[:, u + r:u + r + w] = pr
    self.right = np.ascontiguousarray(right[:, ::-1])

  def workspace(self) -> dict[str, np.ndarray]:
    """Buffers one thread reuses for every row."""
    u1, rows = self.u + 1, self.nb * _COLS
    nlev = max(1, self.window.bit_length() - 1)
    return {"g": np.empty((self.nb, _COLS, self.m), np.float32),
            "p": np.empty((rows, u1), np.float32),
            "levels": [np.empty((rows, u1), np.float32) for _ in range(nlev)]}

  def x_boxed(self, y: int, ws: dict[str, np.ndarray], out: np.ndarray) -> None:
    """out (W x (u+1)) = sum over the window's columns of the products of row y, per shift."""
    nb, m, t, u1 = self.nb, self.m, self.t, self.u + 1
    row = self.right[y]
    # Block b (reversed order below) against right positions [(nb-1-b)*_COLS, ... + m).
    win = np.lib.stride_tricks.as_strided(row, shape=(nb, m, t),
                                          strides=(_COLS * row.strides[0],) + row.strides)
    lb = self.left[y].reshape(nb, _COLS, t)[::-1]
    g = ws["g"]
    np.matmul(lb, win.transpose(0, 2, 1), out=g)  # g[b', i, q] = left(i) . right position q
    # Shift s of left column i sits at q = _COLS - 1 - i + s: the band is the flat view with
    # row stride m - 1 starting at _COLS - 1.
    flat = g.reshape(nb, _COLS * m)
    band = np.lib.stride_tricks.as_strided(flat[:, _COLS - 1:], shape=(nb, _COLS, u1),
                                           strides=(flat.strides[0], (m - 1) * 4, 4))
    p = ws["p"]
    np.copyto(p.reshape(nb, _COLS, u1)[::-1], band)
    _box_rows(p[:self.wp], self.window, ws["levels"], out)

  def band(self, y0: int, y1: int, emit) -> None:
    """Calls emit(y, cc) for y in [y0, y1), cc the W x (u+1) float32 correlation of row y.

    Van Herk / Gil-Werman along y: padded rows a (original row a - r) are taken in blocks of
    `window` starting at y0; output y0 + q*window + k = suffix of block q from k + prefix of
    block q + 1 up to k - 1.
    """
    n, w, u1 = self.window, self.w, self.u + 1
    ws = self.workspace()
    cur = np.empty((n, w, u1), np.float32)
    prev = np.zeros((n, w, u1), np.float32)
    prefix = np.empty((w, u1), np.float32)
    out = np.empty((w, u1), np.float32)
    last = y1 + n - 2  # the last padded row any output of this band reads
    for q in range(-(-(y1 - y0) // n) + 1):
      for k in range(n):
        a = y0 + q * n + k
        y_src = a - self.r
        if a <= last and 0 <= y_src < self.h:
          self.x_boxed(y_src, ws, cur[k])
        else:
          cur[k].fill(0.0)
        y = y0 + (q - 1) * n + k
        if q > 0 and y < y1:
          if k == 0:
            emit(y, prev[0])
          else:
            np.add(prev[k], prefix, out=out)
            emit(y, out)
        if k == 0:
          np.copyto(prefix, cur[0])
        else:
          np.add(prefix, cur[k], out=prefix)
      for k in range(n - 2, -1, -1):  # suffix sums of this block, for the next one's outputs
        np.add(cur[k], cur[k + 1], out=cur[k])
      cur, prev = prev, cur


def run_rows(pl: np.ndarray, pr: np.ndarray, u: int, window: int, emit,
              band_rows: int = BAND_ROWS, workers: int | None = None) -> None:
  """emit(y, cc_row) for every row of one HxWxt pair, bands of rows spread over threads."""
  rows = _RowProducts(pl, pr, u, window)
  h = pl.shape[0]
  bands = [(y, min(h, y + band_rows)) for y in range(0, h, band_rows)]
  workers = min(len(bands), workers or cpu_threads())
  if workers == 1:
    for y0, y1 in bands:
      rows.band(y0, y1, emit)
    return
  with concurrent.futures.ThreadPoolExecutor(workers) as pool:  # NumPy releases the GIL
    for f in [pool.submit(rows.band, y0, y1, emit) for y0, y1 in bands]:
      f.result()


def _row_reduce(cc: np.ndarray, u: int, subpixel: bool, confidence: bool):
  """Integer argmax (first maximum), peak, and the optional refinement and confidence of a row."""
  arg = np.argmax(cc, axis=1)
  take = lambda s: np.take_along_axis(cc, s[:, None], axis=1)[:, 0]
  peak = take(arg)
  disp = arg.astype(np.float32)
  conf = None
  if subpixel or confidence:
    left = np.where(arg > 0, take(np.maximum(arg - 1, 0)), np.float32(0))
    right = np.where(arg < u, take(np.minimum(arg + 1, u)), np.float32(0))
    if subpixel:
      curv = left - np.float32(2) * peak + right
      inside = (arg > 0) & (arg < u) & (curv < 0)
      with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(inside, np.float32(0.5) * (left - right) / np.where(inside, curv, -1),
                          np.float32(0))
      disp = disp + np.clip(offset, -0.5, 0.5).astype(np.float32)
    if confidence:
      far = np.abs(np.arange(u + 1)[None, :] - arg[:, None]) > 1
      second = np.max(np.where(far, cc, -np.inf), axis=1, initial=-np.inf).astype(np.float32)
      with np.errstate(divide="ignore", invalid="ignore"):
        conf = np.where(peak > 0, np.float32(1) - second / np.where(peak > 0, peak, 1),
                        np.float32(0))
      conf = np.where(np.isfinite(second), np.clip(conf, 0, 1), np.float32(1)).astype(np.float32)
  return disp.astype(np.float32), peak.astype(np.float32), conf


def rows_disparity(pl: np.ndarray, pr: np.ndarray, u: int, window: int, subpixel: bool,
                    confidence: bool, band_rows: int = BAND_ROWS, workers: int | None = None):
  """Left-referenced (disparity, peak, confidence or None) of one HxWxt pair by the row path."""
  h, w, _ = pl.shape
  disp = np.empty((h, w), np.float32)
  peak = np.empty((h, w), np.float32)
  conf = np.empty((h, w), np.float32) if confidence else None

  def emit(y, cc):
    d, p, c = _row_reduce(cc, u, subpixel, confidence)
    disp[y], peak[y] = d, p
    if confidence:
      conf[y] = c
  run_rows(pl, pr, u, window, emit, band_rows, workers)
  return disp, peak, conf


def lr_checked(pl: np.ndarray, pr: np.ndarray, disp: np.ndarray, u: int, window: int,
                subpixel: bool, workers: int | None = None) -> np.ndarray:
  """disp with inf where right-to-left matching (the mirrored pair) disagrees by > LR_TOLERANCE."""
  disp_r, _, _ = rows_disparity(pr[:, ::-1], pl[:, ::-1], u, window, subpixel, False,
                                 workers=workers)
  disp_r = disp_r[:, ::-1]
  width = disp.shape[1]
  x = np.arange(width, dtype=np.float32)[None, :]
  xr = np.round(x - disp).astype(np.int64)
  inside = (xr >= 0) & (xr < width)
  d_r = np.take_along_axis(disp_r, np.clip(xr, 0, width - 1), axis=1)
  ok = inside & (np.abs(disp - d_r) <= LR_TOLERANCE)
  return np.where(ok, disp, np.float32(np.inf)).astype(np.float32)
