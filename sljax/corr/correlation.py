"""Disparity from structured-light patterns by windowed cross-correlation along epipolar lines.

For a left pixel k = (x, y) and a shift s in [0, u]:

  cc(k, s) = sum_{(x', y') in W_k} sum_{c < t} P_l(x', y', c) * P_r(x' - s, y', c)

where W_k is the window x window square centred on k, and disparity(k) = argmax_s cc(k, s).

Rules (the paper leaves them open; these are ours, and every path below follows them):
  * Zero padding: any read outside the image is 0, both a shifted right pixel (x' - s < 0) and a
    window pixel outside the image (x' or y' outside [0, W) x [0, H)).
  * Ties: the smallest shift wins (first maximum in s).
  * Non-finite inputs (NaN = unknown pattern) are read as 0: they add nothing to any sum.
  * u (max_disp) defaults to floor(0.25 * W), the paper's 25% of the image width.

Two formulations compute the same cc.

Row path (plain cc, the default; NumPy on the host, rows split over CPU threads). Per image row
y', the products summed over patterns for every left column x and shift s are a band of the
small matrix product P_l(y') P_r(y')^T (W x t times t x W): it is computed in blocks of
`_COLS` left columns against the u + _COLS right columns they can reach, and the band is read
out of each block by a strided view (no gather), giving a W x (u + 1) map with s contiguous.
The window is a separable box filter: along x a tree of log2(window) shifted adds per row, along
y the van Herk / Gil-Werman scheme over blocks of `window` rows (each output row is one suffix
sum of a block plus one prefix sum of the next, each of at most `window` terms), so nothing is
a running sum over the image and no rounding drifts; cc is never held for more than 2 * window
rows. Every cc entry is a float32 sum of float32 products: exact for 0/1 patterns (integers
below 2^24), and within a few float32 ulps of the float64 formula for probabilities.

Shift-major path (JAX, jit; used for `normalized=True` and kept as the reference the benchmark
compares against): per shift, the channel-summed product map is box-filtered with a separable
filter built by window doubling, and the argmax is a running maximum in a `lax.scan` over
blocks of shifts; memory is bounded by the block size, chosen from a memory budget unless given.
"""

import concurrent.futures
import functools
import math

import jax
import jax.numpy as jnp
from jax import lax
import numpy as np

from sljax.corr import rows
from sljax.corr.rows import BAND_ROWS, LR_TOLERANCE
from sljax.errors import require

PAPER_WINDOW = 17  # window side in pixels (paper section 3.2)
PAPER_DISP_FRACTION = 0.25  # u = floor(0.25 * width)
MEMORY_BUDGET = 8 * 2**20  # bytes of correlation maps alive at once when block is None; small
# blocks keep the maps in cache and were measured fastest on CPU (see benchmarks/bench_corr.py)
_EPS = 1e-12


def default_max_disp(width: int) -> int:
  """The paper's search range: u = floor(0.25 * width)."""
  require(width >= 1, f"image width must be >= 1, got {width!r}")  # else a negative range
  return int(math.floor(PAPER_DISP_FRACTION * width))


def _box_1d(a: jax.Array, window: int, axis: int) -> jax.Array:
  """Zero-padded centred box sum along axis, as a tree of log2(window) shifted adds."""
  n = a.shape[axis]
  r = window // 2
  pad = [(0, 0)] * a.ndim
  pad[axis] = (r, r)
  a = jnp.pad(a, pad)

  def take(x, start, length):
    return lax.slice_in_dim(x, start, start + length, axis=axis)

  # sums[k][i] = sum of 2**k consecutive padded values starting at i. The barrier stops XLA from
  # fusing the levels into one loop that recomputes each level 2**k times (measured ~3x slower).
  sums = [a]
  while 2 ** len(sums) <= window:
    prev, m = sums[-1], 2 ** (len(sums) - 1)
    length = prev.shape[axis] - m
    sums.append(lax.optimization_barrier(take(prev, 0, length) + take(prev, m, length)))
  out, offset = None, 0
  for k in range(len(sums) - 1, -1, -1):
    if window & (1 << k):
      part = take(sums[k], offset, n)
      out = part if out is None else out + part
      offset += 1 << k
  return out


def box_filter(a: jax.Array, window: int) -> jax.Array:
  """Zero-padded centred window x window box sum over the last two axes (H, W)."""
  return _box_1d(_box_1d(a, window, a.ndim - 2), window, a.ndim - 1)


def _shifted(pr_pad: jax.Array, s: jax.Array, u: int, width: int) -> jax.Array:
  """Right view read at x - s (zeros left of the image) from a copy padded with u left zeros."""
  return lax.dynamic_slice_in_dim(pr_pad, u - s, width, axis=pr_pad.ndim - 1)


def _channel_dot(a: jax.Array, b: jax.Array) -> jax.Array:
  """sum_c a[c] * b[c] for t x H x W inputs, accumulated in channel order.

  Written as a chain of adds over the (few) channels: XLA CPU's reduce over a leading axis fused
  with a dynamic slice was measured ~15x slower than this elementwise form.
  """
  out = a[0] * b[0]
  for c in range(1, a.shape[0]):
    out = out + a[c] * b[c]
  return out


def _make_cc(pl: jax.Array, pr: jax.Array, u: int, window: int, normalized: bool):
  """Returns cc(s) -> HxW correlation map for one shift; pl, pr are t x H x W."""
  t, _, width = pl.shape
  pr_pad = jnp.pad(pr, ((0, 0), (0, 0), (u, 0)))
  if not normalized:
    def cc(s):
      return box_filter(_channel_dot(pl, _shifted(pr_pad, s, u, width)), window)
    return cc

  # Zero-mean normalised correlation over the window and all patterns jointly; padded zeros count
  # as samples (n = window^2 * t everywhere), consistent with the zero-padding rule.
  n = float(window * window * t)
  sum_l = box_filter(jnp.sum(pl, axis=0), window)
  var_l = box_filter(jnp.sum(pl * pl, axis=0), window) - sum_l * sum_l / n
  r1_pad = jnp.pad(jnp.sum(pr, axis=0), ((0, 0), (u, 0)))
  r2_pad = jnp.pad(jnp.sum(pr * pr, axis=0), ((0, 0), (u, 0)))

  def ncc(s):
    prod = box_filter(_channel_dot(pl, _shifted(pr_pad, s, u, width)), window)
    sum_r = box_filter(_shifted(r1_pad, s, u, width), window)
    var_r = box_filter(_shifted(r2_pad, s, u, width), window) - sum_r * sum_r / n
    cov = prod - sum_l * sum_r / n
    denom = jnp.sqrt(jnp.maximum(var_l, 0.0) * jnp.maximum(var_r, 0.0))
    return jnp.where(denom > _EPS, cov / jnp.maximum(denom, _EPS), 0.0)
  return ncc


def _blocks(cc, u: int, block: int):
  """Number of blocks and b -> (shifts of block b, their maps); shifts past u are clamped."""
  nblocks = -(-(u + 1) // block)

  def block_maps(b):
    shifts = b * block + jnp.arange(block, dtype=jnp.int32)
    # lax.map, not vmap: a vmapped dynamic slice becomes a gather, measured ~40x slower on CPU.
    maps = lax.map(cc, jnp.minimum(shifts, u))
    return shifts, maps
  return nblocks, block_maps


def _argmax_pass(cc, shape_hw, u: int, block: int):
  """Running max over blocks of shifts; ties keep the smallest shift."""
  nblocks, block_maps = _blocks(cc, u, block)

  def step(carry, b):
    best, arg = carry
    shifts, maps = block_maps(b)
    maps = jnp.where((shifts <= u)[:, None, None], maps, -jnp.inf)
    m = jnp.max(maps, axis=0)
    a = b * block + jnp.argmax(maps, axis=0).astype(jnp.int32)
    better = m > best  # strict: an equal later shift never replaces an earlier one
    return (jnp.where(better, m, best), jnp.where(better, a, arg)), None

  init = (jnp.full(shape_hw, -jnp.inf, jnp.float32), jnp.zeros(shape_hw, jnp.int32))
  (best, arg), _ = lax.scan(step, init, jnp.arange(nblocks))
  return best, arg


def _neighbour_pass(cc, arg, u: int, block: int):
  """cc at arg - 1 and arg + 1, and the best cc at shifts further than 1 from arg."""
  nblocks, block_maps = _blocks(cc, u, block)

  def step(carry, b):
    left, right, second = carry
    shifts, maps = block_maps(b)
    s = shifts[:, None, None]
    ok = s <= u
    left = left + jnp.sum(jnp.where(ok & (s == arg - 1), maps, 0.0), axis=0)
    right = right + jnp.sum(jnp.where(ok & (s == arg + 1), maps, 0.0), axis=0)
    far = ok & (jnp.abs(s - arg) > 1)
    second = jnp.maximum(second, jnp.max(jnp.where(far, maps, -jnp.inf), axis=0))
    return (left, right, second), None

  zeros = jnp.zeros(arg.shape, jnp.float32)
  init = (zeros, zeros, jnp.full(arg.shape, -jnp.inf, jnp.float32))
  (left, right, second), _ = lax.scan(step, init, jnp.arange(nblocks))
  return left, right, second


def _one_direction(pl, pr, u, window, normalized, subpixel, confidence, block):
  """Left-referenced disparity, peak and optional confidence for t x H x W inputs."""
  cc = _make_cc(pl, pr, u, window, normalized)
  peak, arg = _argmax_pass(cc, pl.shape[1:], u, block)
  disp = arg.astype(jnp.float32)
  conf = None
  if subpixel or confidence:
    left, right, second = _neighbour_pass(cc, arg, u, block)
    if subpixel:
      curv = left - 2.0 * peak + right
      inside = (arg > 0) & (arg < u) & (curv < 0)
      offset = jnp.where(inside, 0.5 * (left - right) / jnp.where(inside, curv, -1.0), 0.0)
      disp = disp + jnp.clip(offset, -0.5, 0.5)
    if confidence:
      if normalized:
        conf = 0.5 * (peak - second)
      else:
        conf = jnp.where(peak > 0, 1.0 - second / jnp.where(peak > 0, peak, 1.0), 0.0)
      conf = jnp.where(jnp.isfinite(second), jnp.clip(conf, 0.0, 1.0), 1.0)
  return disp, peak, conf


def _single(pl, pr, *, u, window, subpixel, normalized, lr_check, confidence, block):
  """All outputs for one HxWxt pair."""
  pl = jnp.moveaxis(jnp.nan_to_num(pl, nan=0.0, posinf=0.0, neginf=0.0), -1, 0)
  pr = jnp.moveaxis(jnp.nan_to_num(pr, nan=0.0, posinf=0.0, neginf=0.0), -1, 0)
  disp, peak, conf = _one_direction(pl, pr, u, window, normalized, subpixel, confidence, block)
  if lr_check:
    # Right-referenced matching is left-referenced matching of the mirrored pair (right as left).
    disp_r, _, _ = _one_direction(pr[..., ::-1], pl[..., ::-1], u, window, normalized, subpixel,
                                  False, block)
    disp_r = disp_r[..., ::-1]
    width = disp.shape[-1]
    x = jnp.arange(width, dtype=jnp.float32)
    xr = jnp.round(x - disp).astype(jnp.int32)
    inside = (xr >= 0) & (xr < width)
    d_r = jnp.take_along_axis(disp_r, jnp.clip(xr, 0, width - 1), axis=-1)
    ok = inside & (jnp.abs(disp - d_r) <= LR_TOLERANCE)
    disp = jnp.where(ok, disp, jnp.inf)
  out = {"disparity": disp, "peak": peak}
  if confidence:
    out["confidence"] = conf
  return out


@functools.partial(jax.jit, static_argnames=("u", "window", "subpixel", "normalized", "lr_check",
                                             "confidence", "block"))
def _batched(pl, pr, **static):
  return jax.vmap(functools.partial(_single, **static))(pl, pr)


def _bytes_per_shift(height: int, width: int, window: int, normalized: bool) -> int:
  """Rough bytes of temporaries one shift's map needs inside a block (product + box-filter sums)."""
  maps = 12 if normalized else 5
  return 4 * maps * (height + window) * (width + window)


def choose_block(batch: int, height: int, width: int, max_disp: int, window: int = PAPER_WINDOW,
                 normalized: bool = False, budget: int = MEMORY_BUDGET) -> int:
  """Shifts per scan step so that one block of maps over the batch fits in budget bytes."""
  for key, v in (("batch", batch), ("height", height), ("width", width), ("window", window),
                 ("budget", budget)):
    require(isinstance(v, (int, np.integer)) and v >= 1,
            f"choose_block: {key} must be a positive integer, got {v!r}")
  require(isinstance(max_disp, (int, np.integer)) and max_disp >= 0,
          f"choose_block: max_disp must be a non-negative integer, got {max_disp!r}")
  per_shift = batch * _bytes_per_shift(height, width, window, normalized)
  return int(max(1, min(max_disp + 1, budget // per_shift)))


def _host_pair(p_left, p_right, name: str) -> tuple[np.ndarray, np.ndarray, bool]:
  """float32 BxHxWxt host copies with non-finite values read as 0, and whether input was single."""
  out = []
  for x, which in ((p_left, "p_left"), (p_right, "p_right")):
    try:
      a = np.asarray(x)
    except ValueError:  # a ragged nested list
      a = np.empty((), object)
    # Strings, None, ragged lists or complex values: name the type, not numpy's cast error.
    require(a.dtype.kind in "biuf", f"{name}: {which} must be a real-valued array (HxWxt "
            f"patterns), got {type(x).__name__} of dtype {a.dtype}")
    a = a.astype(np.float32)
    require(a.ndim in (3, 4), f"{name}: {which} must be HxWxt or BxHxWxt, got shape {a.shape}")
    out.append(np.nan_to_num(a[None] if a.ndim == 3 else a, nan=0.0, posinf=0.0, neginf=0.0))
  pl, pr = out
  require(pl.shape == pr.shape,
          f"{name}: p_left {pl.shape} and p_right {pr.shape} must have the same shape")
  return pl, pr, np.ndim(p_left) == 3


def _check_window_u(name: str, window, max_disp, width: int) -> int:
  require(isinstance(window, (int, np.integer)) and window >= 1 and window % 2 == 1,
          f"{name}: window must be a positive odd integer, got {window!r}")
  u = default_max_disp(width) if max_disp is None else max_disp
  require(isinstance(u, (int, np.integer)) and u >= 0,
          f"{name}: max_disp must be a non-negative integer, got {max_disp!r}")
  return int(u)


# ---- Validation and the public API (the row path is sljax.corr.rows) ------------------------------------------------------------------------------


def sl_disparity(p_left, p_right, max_disp: int | None = None, window: int = PAPER_WINDOW, *,
                 subpixel: bool = False, normalized: bool = False, lr_check: bool = False,
                 confidence: bool = False, block: int | None = None):
  """Left-referenced disparity of a pattern pair by windowed cross-correlation (paper eq. 4-5).

  Args:
    p_left, p_right: patterns or pattern probabilities, HxWxt or BxHxWxt (1 lit, 0 dark; NaN and
      other non-finite values are read as 0).
    max_disp: u, the largest shift searched (shifts 0..u); default floor(0.25 * W).
    window: odd side of the square correlation window (paper: 17).
    subpixel: refine by the vertex of the parabola through cc at d - 1, d, d + 1 (only where
      0 < d < u and the parabola is concave; offset clipped to [-0.5, 0.5]).
    normalized: zero-mean normalised cross-correlation, the mean and variance taken jointly over
      the window and all patterns (padded zeros count as samples; a flat window gives 0).
    lr_check: also match right-to-left and set pixels whose disparities disagree by more than
      LR_TOLERANCE px to inf.
    confidence: also return a per-pixel match confidence in [0, 1], higher is surer. Plain cc:
      1 - c2 / c1 (peak ratio), normalised cc: (c1 - c2) / 2 (margin), where c1 is the peak and
      c2 the best cc at shifts further than 1 px from the winning one (1 if there is none).
    block: shifts per scan step of the shift-major path (normalized cc; bounded memory); None
      chooses it from MEMORY_BUDGET. Every block size gives identical results. The row path
      (plain cc) streams rows and holds at most 2 * window rows of cc per thread.

  Returns:
    (disparity, peak) or, with confidence, (disparity, peak, confidence): float32 numpy arrays
    HxW (or BxHxW). peak is cc at the integer winning shift. Ties go to the smallest shift;
    reads outside the image are 0 (see the module docstring).
  """
  pl, pr, single = _host_pair(p_left, p_right, "sl_disparity")
  b, h, w, t = pl.shape
  require(t >= 1 and h >= 1 and w >= 1, f"sl_disparity: empty input of shape {pl.shape}")
  u = _check_window_u("sl_disparity", window, max_disp, w)
  require(block is None or (isinstance(block, (int, np.integer)) and block >= 1),
          f"sl_disparity: block must be a positive integer, got {block!r}")
  if normalized:
    res = _shift_major(pl, pr, u, int(window), subpixel=bool(subpixel), normalized=True,
                       lr_check=bool(lr_check), confidence=bool(confidence), block=block)
  else:
    # One image at a time over threads (bands of rows), or, for batches of images with fewer
    # bands than threads, one image per thread.
    per_image = b > 1 and -(-h // BAND_ROWS) < rows.cpu_threads()

    def one(i):
      disp, peak, conf = rows.rows_disparity(pl[i], pr[i], u, int(window), bool(subpixel),
                                         bool(confidence), workers=1 if per_image else None)
      if lr_check:
        disp = rows.lr_checked(pl[i], pr[i], disp, u, int(window), bool(subpixel),
                           1 if per_image else None)
      return (disp, peak, conf) if confidence else (disp, peak)
    if per_image:
      with concurrent.futures.ThreadPoolExecutor(rows.cpu_threads()) as pool:
        outs = list(pool.map(one, range(b)))
    else:
      outs = [one(i) for i in range(b)]
    res = tuple(np.stack(parts) for parts in zip(*outs))
  return tuple(r[0] for r in res) if single else res


def _shift_major(pl, pr, u: int, window: int, *, subpixel: bool = False, normalized: bool = False,
                 lr_check: bool = False, confidence: bool = False, block: int | None = None):
  """The shift-major JAX formulation on BxHxWxt float32 arrays; numpy outputs as sl_disparity."""
  b, h, w, _ = pl.shape
  if block is None:
    block = choose_block(b, h, w, u, window, normalized)
  block = int(min(block, u + 1))
  out = _batched(jnp.asarray(pl), jnp.asarray(pr), u=u, window=window, subpixel=subpixel,
                 normalized=normalized, lr_check=lr_check, confidence=confidence, block=block)
  keys = ("disparity", "peak", "confidence") if confidence else ("disparity", "peak")
  return tuple(np.asarray(out[k]) for k in keys)


@functools.partial(jax.jit, static_argnames=("u", "window", "normalized"))
def _volume(pl, pr, *, u, window, normalized):
  def one(a, b):
    a = jnp.moveaxis(jnp.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0), -1, 0)
    b = jnp.moveaxis(jnp.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0), -1, 0)
    return lax.map(_make_cc(a, b, u, window, normalized), jnp.arange(u + 1, dtype=jnp.int32))
  return jax.vmap(one)(pl, pr)


def cost_volume(p_left, p_right, max_disp: int | None = None, window: int = PAPER_WINDOW, *,
                normalized: bool = False) -> np.ndarray:
  """The full correlation volume cc, (u+1)xHxW (or Bx(u+1)xHxW); for small inputs only.

  Computed by the same path as sl_disparity (bit-identical values): the row path for plain cc,
  the shift-major path for normalized cc.
  """
  pl, pr, single = _host_pair(p_left, p_right, "cost_volume")
  b, h, w, t = pl.shape
  # As sl_disparity: an empty input would fail inside the thread pool or JAX.
  require(t >= 1 and h >= 1 and w >= 1, f"cost_volume: empty input of shape {pl.shape}")
  u = _check_window_u("cost_volume", window, max_disp, w)
  if normalized:
    vol = np.asarray(_volume(jnp.asarray(pl), jnp.asarray(pr), u=u, window=int(window),
                             normalized=True))
  else:
    vol = np.empty((b, u + 1, h, w), np.float32)
    for i in range(b):
      def emit(y, cc, i=i):
        vol[i, :, y] = cc.T
      rows.run_rows(pl[i], pr[i], u, int(window), emit)
  return vol[0] if single else vol
