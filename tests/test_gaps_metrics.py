"""Metrics where mutants of sljax/metrics.py survived the other tests."""

import numpy as np

from sljax import metrics


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
