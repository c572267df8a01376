"""Disparity, depth and pattern metrics: one definition for training, the CLI and the tables.

Rules (SPEC section 5):
- A pixel is evaluated where the ground truth is finite and, if a region mask is given
  ("Seg"), the mask is nonzero. `n_pixels` counts these pixels.
- A non-finite prediction at an evaluated pixel (e.g. SGBM's 'no match') is an invalid
  prediction: it counts as bad in every bad-X and in D1 (its error is taken as infinite),
  it is left out of the error statistics that need a number (mae, rms, iqr, a90 and the
  depth statistics), and its share of the evaluated pixels is reported as `invalid_pred` (%).
- mae is the end-point error (EPE) of disparity; iqr = P75 - P25 and a90 = P90 of the
  absolute errors (np.percentile, linear interpolation); bad_X = % of pixels with error > X;
  d1 = % of pixels with error > 3 px and > 5% of the ground truth; rms = sqrt(mean(err^2)).
- Depth (mm, with a calibration): Z = f * B / (d + doffs) for truth and prediction. A predicted
  disparity near 0 (or below -doffs) is a depth near (or at) infinity, so one such pixel would
  decide the mean: predicted depth is capped at DEPTH_CAP_FACTOR x the scene's largest finite
  ground-truth depth over its evaluated pixels (a far plane past anything in the scene), and
  the share of depth-evaluated pixels whose prediction was capped is `depth_capped` (%). The
  depth statistics run over scored pixels (finite ground truth and finite predicted
  disparity) with a finite ground-truth depth (`depth_n_pixels`).
- Pooled results (a dataset) accumulate the per-pixel errors of all scenes and compute the
  statistics once, so large scenes weigh by their pixel count (no mean of means).
A statistic over zero pixels is NaN.
"""

from typing import Any

import numpy as np

from sljax.data.camera import Calib, depth_from_disparity
from sljax.errors import SljaxError

BAD_THRESHOLDS = (0.5, 1.0, 2.0, 3.0)
D1_PIXELS = 3.0
D1_RELATIVE = 0.05

# Keys in the order tables show them.
DISPARITY_KEYS = ("mae", "iqr", "rms", "a90", *(f"bad_{t:g}" for t in BAD_THRESHOLDS), "d1",
                  "invalid_pred", "n_pixels")
DEPTH_KEYS = ("depth_mae_mm", "depth_iqr_mm", "depth_capped", "depth_n_pixels")
# Predicted depth is capped at this multiple of the scene's largest ground-truth depth.
DEPTH_CAP_FACTOR = 2.0


def _as_2d_mask(mask: np.ndarray | None, shape: tuple[int, ...], what: str) -> np.ndarray:
  if mask is None:
    return np.ones(shape, dtype=bool)
  mask = np.asarray(mask)
  if mask.shape != shape:
    raise SljaxError(f"{what}: region mask has shape {mask.shape}, disparity has {shape}")
  return mask.astype(bool)


def _percentiles(values: np.ndarray, qs: tuple[float, ...]) -> list[float]:
  if values.size == 0:
    return [float("nan")] * len(qs)
  return [float(v) for v in np.percentile(values, qs)]


class DisparityAccumulator:
  """Pools disparity (and depth) errors over scenes; `result()` gives the metrics dict."""

  def __init__(self):
    self._errors: list[np.ndarray] = []
    self._depth_errors: list[np.ndarray] = []
    self._depth_capped = 0
    self.n_pixels = 0
    self.n_invalid = 0
    self._bad = {t: 0 for t in BAD_THRESHOLDS}
    self._d1 = 0
    self._has_depth = False

  def add(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
          calib: Calib | None = None, name: str = "prediction") -> None:
    """Adds one scene (or a batch of equally calibrated scenes); `name` is used in errors."""
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
      raise SljaxError(f"{name}: predicted disparity has shape {pred.shape}, "
                       f"ground truth has {gt.shape}")
    valid = np.isfinite(gt) & _as_2d_mask(mask, gt.shape, name)
    finite_pred = np.isfinite(pred)
    scored = valid & finite_pred
    err = np.abs(pred[scored] - gt[scored])
    g = gt[scored]
    n_valid = int(valid.sum())
    n_invalid = n_valid - int(scored.sum())
    self.n_pixels += n_valid
    self.n_invalid += n_invalid
    for t in BAD_THRESHOLDS:
      self._bad[t] += int((err > t).sum()) + n_invalid
    self._d1 += int(((err > D1_PIXELS) & (err > D1_RELATIVE * np.abs(g))).sum()) + n_invalid
    self._errors.append(err.astype(np.float32))
    if calib is not None:
      self._has_depth = True
      where = f"{name}: depth metrics"
      z_gt = depth_from_disparity(gt, calib, where).astype(np.float64)
      z_pred = depth_from_disparity(np.where(finite_pred, pred, np.inf), calib,
                                    where).astype(np.float64)
      both = scored & np.isfinite(z_gt)
      if both.any():
        cap = DEPTH_CAP_FACTOR * float(z_gt[valid & np.isfinite(z_gt)].max())
        capped = z_pred[both] > cap  # (inf: a predicted disparity <= -doffs)
        self._depth_capped += int(capped.sum())
        z = np.where(capped, cap, z_pred[both])
        self._depth_errors.append(np.abs(z - z_gt[both]).astype(np.float32))

  def result(self) -> dict[str, float]:
    """The metrics over everything added so far (NaN for statistics over zero pixels)."""
    err = (np.concatenate(self._errors).astype(np.float64) if self._errors
           else np.zeros(0, dtype=np.float64))
    n = self.n_pixels
    nan = float("nan")
    p25, p75, p90 = _percentiles(err, (25, 75, 90))
    out: dict[str, float] = {
        "mae": float(err.mean()) if err.size else nan,
        "iqr": p75 - p25,
        "rms": float(np.sqrt(np.mean(err * err))) if err.size else nan,
        "a90": p90,
    }
    for t in BAD_THRESHOLDS:
      out[f"bad_{t:g}"] = 100.0 * self._bad[t] / n if n else nan
    out["d1"] = 100.0 * self._d1 / n if n else nan
    out["invalid_pred"] = 100.0 * self.n_invalid / n if n else nan
    out["n_pixels"] = n
    if self._has_depth:
      derr = (np.concatenate(self._depth_errors).astype(np.float64) if self._depth_errors
              else np.zeros(0, dtype=np.float64))
      q25, q75 = _percentiles(derr, (25, 75))
      out["depth_mae_mm"] = float(derr.mean()) if derr.size else nan
      out["depth_iqr_mm"] = q75 - q25
      out["depth_capped"] = 100.0 * self._depth_capped / derr.size if derr.size else nan
      out["depth_n_pixels"] = int(derr.size)
    return out


def disparity_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
                      calib: Calib | None = None) -> dict[str, float]:
  """Disparity metrics of one prediction (see the module docstring for the rules)."""
  acc = DisparityAccumulator()
  acc.add(pred, gt, mask, calib)
  return acc.result()


def pooled_disparity_metrics(preds: list[np.ndarray], gts: list[np.ndarray],
                             masks: list[np.ndarray | None] | None = None,
                             calibs: list[Calib | None] | None = None) -> dict[str, float]:
  """Metrics pooled over the pixels of several scenes (not the mean of per-scene metrics)."""
  acc = DisparityAccumulator()
  masks = masks if masks is not None else [None] * len(preds)
  calibs = calibs if calibs is not None else [None] * len(preds)
  if not len(preds) == len(gts) == len(masks) == len(calibs):
    raise SljaxError(f"pooled metrics need as many ground truths ({len(gts)}), masks "
                     f"({len(masks)}) and calibrations ({len(calibs)}) as predictions "
                     f"({len(preds)})")
  for p, g, m, c in zip(preds, gts, masks, calibs):
    acc.add(p, g, m, c)
  return acc.result()


def pattern_counts(pred: np.ndarray, target: np.ndarray,
                   from_logits: bool = False) -> tuple[int, int]:
  """(correct, known) pattern pixels: lit where p > 0.5 (logit > 0); NaN target = unknown."""
  pred = np.asarray(pred, dtype=np.float32)
  target = np.asarray(target, dtype=np.float32)
  if pred.shape != target.shape:
    raise SljaxError(f"predicted patterns have shape {pred.shape}, ground truth has {target.shape}")
  known = np.isfinite(target)
  lit = pred > (0.0 if from_logits else 0.5)
  correct = known & (lit == (target > 0.5))
  return int(correct.sum()), int(known.sum())


def pattern_accuracy(pred: np.ndarray, target: np.ndarray, from_logits: bool = False) -> float:
  """% of known pattern pixels whose lit/dark class is right (probabilities, or logits)."""
  correct, known = pattern_counts(pred, target, from_logits)
  return 100.0 * correct / known if known else float("nan")


class PatternAccumulator:
  """Pools pattern accuracy over scenes."""

  def __init__(self):
    self.correct = 0
    self.known = 0

  def add(self, pred: np.ndarray, target: np.ndarray, from_logits: bool = False) -> None:
    """Adds one scene's predicted patterns and ground truth (NaN = unknown)."""
    c, k = pattern_counts(pred, target, from_logits)
    self.correct += c
    self.known += k

  def result(self) -> dict[str, Any]:
    """{'pattern_acc': %, 'pattern_n_pixels': known pixels}."""
    acc = 100.0 * self.correct / self.known if self.known else float("nan")
    return {"pattern_acc": acc, "pattern_n_pixels": self.known}
