"""Per-pixel uncertainty of predicted pattern probabilities and its relation to disparity error.

A sigmoid output p is least confident at 0.5: per pattern, uncertainty = 1 - 2 |p - 0.5|, in
[0, 1] (0 for p in {0, 1}, 1 for p = 0.5). A view's map is the mean over its t patterns; the
two-view map is the pixel-wise mean of the left and right maps at the same image coordinates
(no warping), as the paper shows both views side by side. The analysis relates it to the
disparity error with Pearson and Spearman correlation and a least-squares line (paper Fig. 4-5).
"""

import os

import numpy as np

from sljax.errors import require
from sljax.io import files
from sljax.io.pictures import Panel, new_figure, save_panels


def view_uncertainty(p: np.ndarray) -> np.ndarray:
  """Mean over patterns of 1 - 2|p - 0.5| for HxWxt (or BxHxWxt) probabilities; NaN skipped."""
  p = np.asarray(p, dtype=np.float32)
  require(p.ndim in (3, 4), f"pattern probabilities must be HxWxt or BxHxWxt, got shape {p.shape}")
  u = 1.0 - 2.0 * np.abs(p - 0.5)
  known = np.isfinite(u)
  count = known.sum(axis=-1)
  total = np.where(known, u, 0.0).sum(axis=-1)
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(count > 0, total / np.maximum(count, 1), np.nan).astype(np.float32)


def pattern_uncertainty(p_left: np.ndarray, p_right: np.ndarray | None = None) -> np.ndarray:
  """Uncertainty map HxW: the left view's, or the mean of both views' maps when p_right is given."""
  left = view_uncertainty(p_left)
  if p_right is None:
    return left
  right = view_uncertainty(p_right)
  require(left.shape == right.shape,
          f"p_left {np.shape(p_left)} and p_right {np.shape(p_right)} must have the same shape")
  return (0.5 * (left + right)).astype(np.float32)


def _ranks(x: np.ndarray) -> np.ndarray:
  """0-based ranks; tied values share the mean of the ranks they span."""
  _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
  first = np.cumsum(counts) - counts
  return (first + 0.5 * (counts - 1))[inverse].astype(np.float64)


def _pearson(x: np.ndarray, y: np.ndarray) -> float:
  x = x - x.mean()
  y = y - y.mean()
  denom = np.sqrt(np.dot(x, x) * np.dot(y, y))
  return float(np.dot(x, y) / denom) if denom > 0 else float("nan")


def analyse_uncertainty(uncertainty: np.ndarray, error: np.ndarray,
                        valid: np.ndarray | None = None) -> dict:
  """Pearson and Spearman correlation of uncertainty with error, and the least-squares line.

  Pixels count where valid (if given) holds and both values are finite. Returns dict(pearson,
  spearman, n, slope, intercept) with error ~ slope * uncertainty + intercept; correlations are
  NaN when fewer than 2 pixels count or either variable is constant.
  """
  u = np.asarray(uncertainty, dtype=np.float64)
  e = np.asarray(error, dtype=np.float64)
  require(u.shape == e.shape, f"uncertainty {u.shape} and error {e.shape} must have the same shape")
  keep = np.isfinite(u) & np.isfinite(e)
  if valid is not None:
    valid = np.asarray(valid, dtype=bool)
    require(valid.shape == u.shape, f"valid {valid.shape} must have the shape {u.shape}")
    keep &= valid
  u, e = u[keep], e[keep]
  n = int(u.size)
  out = {"pearson": float("nan"), "spearman": float("nan"), "n": n,
         "slope": float("nan"), "intercept": float("nan")}
  if n < 2:
    return out
  out["pearson"] = _pearson(u, e)
  out["spearman"] = _pearson(_ranks(u), _ranks(e))
  du = u - u.mean()
  var = np.dot(du, du)
  if var > 0:
    out["slope"] = float(np.dot(du, e - e.mean()) / var)
    out["intercept"] = float(e.mean() - out["slope"] * u.mean())
  return out


def _normalise(x: np.ndarray) -> np.ndarray:
  lo, hi = float(x.min()), float(x.max())
  return (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)


def plot_uncertainty_histogram(path: str | os.PathLike, uncertainty: np.ndarray, error: np.ndarray,
                               valid: np.ndarray | None = None, bins: int = 64) -> dict:
  """Writes a log-scaled 2D histogram of normalised uncertainty vs normalised error (jet colour
  map) with the least-squares line in red, as the paper's Fig. 5; returns the analysis of the
  normalised values."""
  u = np.asarray(uncertainty, dtype=np.float64)
  e = np.asarray(error, dtype=np.float64)
  require(u.shape == e.shape, f"uncertainty {u.shape} and error {e.shape} must have the same shape")
  keep = np.isfinite(u) & np.isfinite(e)
  if valid is not None:
    keep &= np.asarray(valid, dtype=bool)
  require(keep.sum() >= 2, f"{os.fspath(path)}: fewer than 2 valid pixels to plot")
  un, en = _normalise(u[keep]), _normalise(e[keep])
  stats = analyse_uncertainty(un, en)
  from matplotlib import colors as mcolors  # noqa: PLC0415  drawn only here (io.pictures.new_figure)
  fig = new_figure(figsize=(5.5, 4.5))
  ax = fig.subplots()
  counts, _, _ = np.histogram2d(un, en, bins=bins, range=((0, 1), (0, 1)))
  img = ax.imshow(np.ma.masked_equal(counts.T, 0), origin="lower", extent=(0, 1, 0, 1),
                  aspect="auto", cmap="jet",
                  norm=mcolors.LogNorm(vmin=1, vmax=max(counts.max(), 1)),
                  interpolation="nearest")
  fig.colorbar(img, ax=ax, label="pixels")
  if np.isfinite(stats["slope"]):
    x = np.array([0.0, 1.0])
    ax.plot(x, stats["slope"] * x + stats["intercept"], color="red", linewidth=2,
            label=f"fit: pearson {stats['pearson']:.3f}, spearman {stats['spearman']:.3f}")
    ax.legend(loc="upper left", fontsize=8)
  ax.set_xlim(0, 1)
  ax.set_ylim(0, 1)
  ax.set_xlabel("normalised uncertainty")
  ax.set_ylabel("normalised disparity error")
  fig.tight_layout()
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  files.save_figure(fig, path, dpi=100)  # whole or not at all
  return stats


def plot_uncertainty_maps(path: str | os.PathLike, error: np.ndarray, u_left: np.ndarray,
                          u_right: np.ndarray | None = None) -> None:
  """Writes disparity error, left uncertainty and right uncertainty side by side (paper Fig. 4)."""
  error = np.asarray(error, np.float32)
  finite = error[np.isfinite(error)]
  # A few gross mismatches would wash out the map; the scale stops at the 99th percentile.
  vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
  panels = [Panel("disparity error", error, cmap="inferno", vmin=0.0, vmax=max(vmax, 1e-6),
                  label="px"),
            Panel("left uncertainty", np.asarray(u_left, np.float32), cmap="inferno", vmin=0.0,
                  vmax=1.0)]
  if u_right is not None:
    panels.append(Panel("right uncertainty", np.asarray(u_right, np.float32), cmap="inferno",
                        vmin=0.0, vmax=1.0))
  save_panels(path, panels, ncols=len(panels))
