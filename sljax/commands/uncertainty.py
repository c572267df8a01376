"""`sljax uncertainty`: predicted-pattern uncertainty vs disparity error (paper Fig. 4-5)."""

import json
import os
from pathlib import Path

import numpy as np

from sljax.corr import correlation, uncertainty
from sljax.data.scene import load_scene
from sljax.errors import SljaxError, require
from sljax.io import files

HIST_PNG = "uncertainty_hist.png"
MAPS_PNG = "uncertainty_maps.png"
METRICS_JSON = "metrics.json"


def register(subparsers) -> None:
  """Adds the uncertainty subcommand."""
  p = subparsers.add_parser(
      "uncertainty",
      description="Reads predicted structured-light probabilities of both views (an .npz with "
      "arrays 'p_left' and 'p_right', HxWxt in [0, 1], and optionally 'disparity', HxW, "
      "left-referenced) and a ground-truth scene folder (disp0.pfm). Without 'disparity' the "
      "disparity is computed from the patterns by correlation. Per-pixel uncertainty is "
      "1 - 2|p - 0.5| averaged over patterns (and over both views for the analysis). Writes "
      f"{METRICS_JSON} (Pearson and Spearman correlation of uncertainty with absolute disparity "
      f"error, fitted line, MAE), {HIST_PNG} (log-scaled 2D histogram with the line of best "
      f"fit) and {MAPS_PNG} (error, left and right uncertainty).")
  p.add_argument("--pred", required=True, metavar="NPZ",
                 help="predictions: .npz with p_left, p_right (HxWxt) and optional disparity (HxW)")
  p.add_argument("--gt", required=True, metavar="SCENE",
                 help="ground-truth scene folder holding disp0.pfm (and mask0.png, if any)")
  p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
  p.add_argument("--overwrite", action="store_true",
                 help=f"replace {METRICS_JSON} and the pictures in an existing --out")
  p.add_argument("--search-range", "--max-disp", dest="search_range", type=int, default=None,
                 metavar="PX", help="correlation search range u when disparity is computed "
                 "(default 25%% of width; --max-disp is its former name)")
  p.add_argument("--window", type=int, default=17, help="correlation window side (default 17)")
  p.add_argument("--mask", action="store_true",
                 help="analyse only pixels inside the scene's mask0.png")
  p.set_defaults(func=run)


def _check_probabilities(path: Path, key: str, p: np.ndarray) -> None:
  """SljaxError unless p holds numbers in [0, 1] (NaN, an unknown pattern, allowed)."""
  require(p.dtype.kind in "fiub", f"{path}: '{key}' must be numeric, got dtype {p.dtype}")
  known = p[~np.isnan(p)] if p.dtype.kind == "f" else p
  # Logits or 0/255 pixels would give uncertainties outside [0, 1] and a meaningless analysis.
  if known.size and (known.min() < 0 or known.max() > 1):
    hint = "logits? apply a sigmoid" if known.min() < 0 else "8-bit values? divide by 255"
    raise SljaxError(f"{path}: '{key}' must hold probabilities in [0, 1], got values in "
                     f"[{known.min():g}, {known.max():g}] ({hint} first)")


def _load_pred(path: Path) -> dict:
  """Reads and checks the prediction .npz."""
  require(path.is_file(), f"{path}: prediction file not found")
  arrays = files.read_npz(path, "predictions")
  for key in ("p_left", "p_right"):
    require(key in arrays, f"{path}: array '{key}' missing (found {sorted(arrays)})")
    require(arrays[key].ndim == 3, f"{path}: '{key}' must be HxWxt, got shape {arrays[key].shape}")
    _check_probabilities(path, key, arrays[key])
  require(arrays["p_left"].shape == arrays["p_right"].shape,
          f"{path}: p_left {arrays['p_left'].shape} and p_right {arrays['p_right'].shape} differ")
  if "disparity" in arrays:
    require(arrays["disparity"].shape == arrays["p_left"].shape[:2],
            f"{path}: 'disparity' shape {arrays['disparity'].shape} is not "
            f"{arrays['p_left'].shape[:2]}")
  return arrays


def run(args) -> int:
  """Runs the analysis and writes the metrics and the two pictures."""
  require(args.window >= 1 and args.window % 2 == 1,
          f"--window must be a positive odd number, got {args.window}")
  require(args.search_range is None or args.search_range >= 0,
          f"--search-range must be >= 0, got {args.search_range}")
  out = Path(args.out)
  files.check_output_folder(out, args.overwrite)
  files.refuse_existing([out / n for n in (METRICS_JSON, HIST_PNG, MAPS_PNG)], args.overwrite)
  pred = _load_pred(Path(args.pred))
  parts = {"disp", "mask"} if args.mask else {"disp"}
  scene = load_scene(args.gt, parts=parts)
  p_left = pred["p_left"].astype(np.float32)
  p_right = pred["p_right"].astype(np.float32)
  require(scene.disp0.shape == p_left.shape[:2],
          f"{args.gt}: disp0.pfm is {scene.disp0.shape[1]}x{scene.disp0.shape[0]}, predictions "
          f"in {args.pred} are {p_left.shape[1]}x{p_left.shape[0]}")
  if "disparity" in pred:
    disparity = pred["disparity"].astype(np.float32)
    source = "npz"
  else:
    disparity, _ = correlation.sl_disparity(p_left, p_right, args.search_range, args.window)
    source = "correlation"

  u_left = uncertainty.view_uncertainty(p_left)
  u_right = uncertainty.view_uncertainty(p_right)
  u_both = uncertainty.pattern_uncertainty(p_left, p_right)
  error = np.abs(disparity - scene.disp0)
  valid = np.isfinite(error)
  if args.mask:
    valid &= scene.mask0
  require(valid.sum() >= 2,
          f"{args.gt}: fewer than 2 pixels with finite ground truth and prediction")

  stats = uncertainty.analyse_uncertainty(u_both, error, valid)
  stats_left = uncertainty.analyse_uncertainty(u_left, error, valid)
  os.makedirs(out, exist_ok=True)
  with files.replacing(out / HIST_PNG) as (tmp,):  # whole or not at all
    uncertainty.plot_uncertainty_histogram(tmp, u_both, error, valid)
  uncertainty.plot_uncertainty_maps(out / MAPS_PNG, np.where(valid, error, np.nan), u_left, u_right)
  metrics = {
      "pearson": stats["pearson"], "spearman": stats["spearman"], "n": stats["n"],
      "slope": stats["slope"], "intercept": stats["intercept"],
      "pearson_left": stats_left["pearson"], "spearman_left": stats_left["spearman"],
      "mae": float(error[valid].mean()), "disparity_source": source,
      "pred": os.fspath(args.pred), "gt": os.fspath(args.gt),
  }
  # Undefined correlations (constant input) are written as null, which strict JSON readers accept.
  metrics = {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
             for k, v in metrics.items()}
  files.write_text(out / METRICS_JSON, json.dumps(metrics, indent=2) + "\n")
  print(f"pearson {stats['pearson']:.4f}  spearman {stats['spearman']:.4f}  n {stats['n']}  "
        f"mae {metrics['mae']:.3f} px  -> {out}")
  return 0
