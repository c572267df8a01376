import math

import numpy as np
import pytest

from sljax.data.camera import Calib
from sljax.errors import SljaxError
from sljax.evaluation import metrics


def _calib(f=100.0, baseline=50.0, doffs=2.0):
  k = np.array([[f, 0, 5], [0, f, 5], [0, 0, 1]], dtype=np.float64)
  return Calib(cam0=k, cam1=k, doffs=doffs, baseline=baseline, width=4, height=2, ndisp=16)


def test_hand_computed_case_with_inf_masking():
  gt = np.array([[10.0, 20.0, np.inf, 40.0],
                 [2.0, 100.0, 8.0, np.inf]], dtype=np.float32)
  pred = np.array([[10.4, 21.5, 0.0, 43.5],
                   [2.0, 96.0, 8.75, 7.0]], dtype=np.float32)
  m = metrics.disparity_metrics(pred, gt)
  # Evaluated: the 6 finite-GT pixels; errors 0.4, 1.5, 3.5, 0, 4, 0.75.
  errs = [0.4, 1.5, 3.5, 0.0, 4.0, 0.75]
  assert m["n_pixels"] == 6
  assert m["mae"] == pytest.approx(sum(errs) / 6, rel=1e-6)
  assert m["rms"] == pytest.approx(math.sqrt(sum(e * e for e in errs) / 6), rel=1e-6)
  assert m["bad_0.5"] == pytest.approx(100 * 4 / 6)  # 1.5, 3.5, 4, 0.75
  assert m["bad_1"] == pytest.approx(100 * 3 / 6)
  assert m["bad_2"] == pytest.approx(100 * 2 / 6)
  assert m["bad_3"] == pytest.approx(100 * 2 / 6)
  # D1: 3.5 > 3 and 3.5 > 0.05*40=2 -> bad; 4 > 3 but 4 < 0.05*100=5 -> not bad.
  assert m["d1"] == pytest.approx(100 * 1 / 6)
  assert m["invalid_pred"] == 0.0
  # Sorted errors 0, .4, .75, 1.5, 3.5, 4: linear-interpolated percentiles by hand.
  # P25 at rank 1.25 -> .4 + .25*.35; P75 at rank 3.75 -> 1.5 + .75*2; P90 at rank 4.5 -> 3.75.
  assert m["iqr"] == pytest.approx((1.5 + 0.75 * 2.0) - (0.4 + 0.25 * 0.35), rel=1e-6)
  assert m["a90"] == pytest.approx(3.75, rel=1e-6)
  assert "depth_mae_mm" not in m


def test_region_mask_restricts_pixels():
  gt = np.array([[1.0, 2.0], [3.0, np.inf]])
  pred = np.array([[2.0, 2.0], [0.0, 5.0]])
  mask = np.array([[1, 0], [1, 1]], dtype=np.uint8)
  m = metrics.disparity_metrics(pred, gt, mask=mask)
  assert m["n_pixels"] == 2  # (0,0) and (1,0); (1,1) has no GT
  assert m["mae"] == pytest.approx((1.0 + 3.0) / 2)
  with pytest.raises(SljaxError, match="mask"):
    metrics.disparity_metrics(pred, gt, mask=np.ones((3, 2)))


def test_invalid_prediction_is_bad_and_excluded_from_error_statistics():
  gt = np.array([[10.0, 10.0, 10.0, 10.0]])
  pred = np.array([[10.0, np.inf, np.nan, 11.0]])
  m = metrics.disparity_metrics(pred, gt)
  assert m["n_pixels"] == 4
  assert m["invalid_pred"] == pytest.approx(50.0)
  assert m["mae"] == pytest.approx(0.5)  # over the two finite predictions
  assert m["bad_0.5"] == pytest.approx(75.0)  # two invalid + error 1
  assert m["bad_3"] == pytest.approx(50.0)
  assert m["d1"] == pytest.approx(50.0)


def test_no_valid_pixels_gives_nan():
  m = metrics.disparity_metrics(np.zeros((2, 2)), np.full((2, 2), np.inf))
  assert m["n_pixels"] == 0 and math.isnan(m["mae"]) and math.isnan(m["bad_2"])


def test_shape_mismatch_raises():
  with pytest.raises(SljaxError, match="shape"):
    metrics.disparity_metrics(np.zeros((2, 3)), np.zeros((2, 2)))


def test_depth_conversion():
  calib = _calib(f=100.0, baseline=50.0, doffs=2.0)
  gt = np.array([[8.0, 18.0, np.inf, 3.0]])
  pred = np.array([[3.0, 18.0, 5.0, np.inf]])
  m = metrics.disparity_metrics(pred, gt, calib=calib)
  # Z = 100 * 50 / (d + 2): gt 500, 250; pred 1000, 250. Pixel 3 has no prediction.
  assert m["depth_n_pixels"] == 2
  assert m["depth_mae_mm"] == pytest.approx((500.0 + 0.0) / 2, rel=1e-5)
  # Two errors 0 and 500: P25 = 125, P75 = 375.
  assert m["depth_iqr_mm"] == pytest.approx(250.0, rel=1e-5)


def test_depth_is_capped_at_twice_the_scenes_farthest_truth():
  """A predicted disparity near 0 (or negative) is a depth near infinity: capped at
  DEPTH_CAP_FACTOR x the largest ground-truth depth, the capped share reported."""
  assert metrics.DEPTH_CAP_FACTOR == 2.0
  calib = _calib(f=100.0, baseline=50.0, doffs=0.0)
  # gt depths 5000/10 = 500, 5000/5 = 1000 (the farthest: cap 2000), 5000/20 = 250, 250.
  gt = np.array([[10.0, 5.0, 20.0, 20.0]])
  # pred depths 500 (exact), 5000/1e-9 (capped to 2000), inf for -1 px (capped), 5000/25 = 200.
  pred = np.array([[10.0, 1e-9, -1.0, 25.0]])
  m = metrics.disparity_metrics(pred, gt, calib=calib)
  errors = [0.0, 2000.0 - 1000.0, 2000.0 - 250.0, 50.0]
  assert m["depth_n_pixels"] == 4 and m["depth_capped"] == pytest.approx(50.0)
  assert m["depth_mae_mm"] == pytest.approx(np.mean(errors), rel=1e-6)
  assert math.isfinite(m["depth_iqr_mm"])
  # Pooled: the cap is per scene (its own farthest truth), the share over all pixels.
  acc = metrics.DisparityAccumulator()
  acc.add(pred, gt, calib=calib)
  # A near scene (truth 20 px = 250 mm: cap 500 mm) with a prediction near 0 px: capped at its
  # own 500 (error 250), not at the first scene's 2000 (error 1750).
  acc.add(np.array([[1e-9]]), np.array([[20.0]]), calib=calib)
  pooled = acc.result()
  assert pooled["depth_capped"] == pytest.approx(60.0)
  assert pooled["depth_mae_mm"] == pytest.approx((np.sum(errors) + 250.0) / 5, rel=1e-6)
  # Without a capped pixel nothing changes.
  assert metrics.disparity_metrics(gt, gt, calib=calib)["depth_capped"] == 0.0


def test_pooled_accumulates_pixels_not_means():
  rng = np.random.default_rng(0)
  gts = [rng.uniform(1, 50, (4, 5)), rng.uniform(1, 50, (9, 3))]
  preds = [g + rng.normal(0, 2, g.shape) for g in gts]
  gts[1][0, 0] = np.inf
  pooled = metrics.pooled_disparity_metrics(preds, gts)
  err = np.concatenate([np.abs(p - g)[np.isfinite(g)] for p, g in zip(preds, gts)])
  assert pooled["n_pixels"] == err.size
  assert pooled["mae"] == pytest.approx(err.mean(), rel=1e-5)
  assert pooled["iqr"] == pytest.approx(np.subtract(*np.percentile(err, [75, 25])), rel=1e-5)
  assert pooled["bad_2"] == pytest.approx(100 * np.mean(err > 2))
  per_scene_mean = np.mean([metrics.disparity_metrics(p, g)["mae"] for p, g in zip(preds, gts)])
  assert pooled["mae"] != pytest.approx(per_scene_mean, rel=1e-4)


def test_pattern_accuracy_over_known_pixels():
  target = np.array([[[1.0, 0.0], [np.nan, 1.0]]])
  prob = np.array([[[0.9, 0.6], [0.1, 0.4]]])
  # Known: (0,0,0) right, (0,0,1) wrong, (0,1,1) wrong -> 1/3.
  assert metrics.pattern_accuracy(prob, target) == pytest.approx(100 / 3)
  logits = np.log(prob / (1 - prob))
  assert metrics.pattern_accuracy(logits, target, from_logits=True) == pytest.approx(100 / 3)
  acc = metrics.PatternAccumulator()
  acc.add(prob, target)
  acc.add(np.ones((1, 1, 1)), np.ones((1, 1, 1)))
  assert acc.result() == {"pattern_acc": pytest.approx(50.0), "pattern_n_pixels": 4}


# ------------------------------------------------------------
# Metrics where mutants of sljax/evaluation/metrics.py survived the other tests.



def test_bad_x_counts_errors_strictly_above_the_threshold():
  """Errors exactly 0.5, 1, 2 and 3 px (representable in binary) are not bad at that X."""
  gt = np.full((1, 5), 10.0)
  pred = gt + np.array([[0.5, 1.0, 2.0, 3.0, 3.5]])
  m = metrics.disparity_metrics(pred, gt)
  # bad_0.5: 1, 2, 3, 3.5 -> 4 of 5; bad_1: 2, 3, 3.5; bad_2: 3, 3.5; bad_3: 3.5.
  assert (m["bad_0.5"], m["bad_1"], m["bad_2"], m["bad_3"]) == (80.0, 60.0, 40.0, 20.0)
  # D1: error > 3 px and > 5% of the truth (0.5 px here): only the 3.5 px pixel.
  assert m["d1"] == 20.0


def test_nothing_accumulated_gives_nan_statistics():
  m = metrics.DisparityAccumulator().result()
  assert m["n_pixels"] == 0
  assert all(np.isnan(m[k]) for k in ("mae", "iqr", "rms", "a90", "bad_1", "d1"))


def test_pattern_counts_take_probabilities_by_default_and_half_is_dark():
  """Lit where p > 0.5 (so p = 0.5 is dark); with from_logits, where the logit is > 0."""
  pred = np.array([0.3, 0.5, 0.7, -1.0])
  target = np.array([0.0, 0.0, 1.0, np.nan])
  assert metrics.pattern_counts(pred, target) == (3, 3)
  assert metrics.pattern_counts(pred, target, from_logits=True) == (1, 3)  # 0.3, 0.5 lit
  assert metrics.pattern_accuracy(pred, target) == 100.0
