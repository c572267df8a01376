"""Small-sample statistics for the experiment reports: Student-t intervals and paired tests.

Pure Python/NumPy (no SciPy): the t distribution's CDF is the regularised incomplete beta
function, evaluated by its continued fraction (Numerical Recipes, 'betacf'), and quantiles
are found by bisection on the CDF.
"""

import math
from collections.abc import Sequence

import numpy as np

CONFIDENCE = 0.95


def _betacf(a: float, b: float, x: float) -> float:
  """Continued fraction of the incomplete beta function (modified Lentz)."""
  tiny, eps = 1e-300, 1e-15
  qab, qap, qam = a + b, a + 1.0, a - 1.0
  c, d = 1.0, 1.0 - qab * x / qap
  d = 1.0 / (d if abs(d) > tiny else tiny)
  h = d
  for m in range(1, 400):
    m2 = 2 * m
    for num in (m * (b - m) * x / ((qam + m2) * (a + m2)),
                -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
      d = 1.0 + num * d
      d = 1.0 / (d if abs(d) > tiny else tiny)
      c = 1.0 + num / c
      c = c if abs(c) > tiny else tiny
      h *= d * c
    if abs(d * c - 1.0) < eps:
      break
  return h


def incomplete_beta(a: float, b: float, x: float) -> float:
  """The regularised incomplete beta function I_x(a, b), 0 <= x <= 1."""
  if x <= 0.0:
    return 0.0
  if x >= 1.0:
    return 1.0
  front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                   + a * math.log(x) + b * math.log1p(-x))
  if x < (a + 1.0) / (a + b + 2.0):
    return front * _betacf(a, b, x) / a
  return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def t_cdf(t: float, df: float) -> float:
  """P(T <= t) for Student's t with df degrees of freedom."""
  if math.isinf(t):
    return 1.0 if t > 0 else 0.0
  tail = 0.5 * incomplete_beta(df / 2.0, 0.5, df / (df + t * t))
  return 1.0 - tail if t > 0 else tail


def t_quantile(p: float, df: float) -> float:
  """The t with P(T <= t) = p (bisection to 1e-12)."""
  if not 0.0 < p < 1.0:
    raise ValueError(f"p must be in (0, 1), got {p}")
  if p < 0.5:
    return -t_quantile(1.0 - p, df)
  lo, hi = 0.0, 1.0
  while t_cdf(hi, df) < p:
    hi *= 2.0
  for _ in range(200):
    mid = 0.5 * (lo + hi)
    if t_cdf(mid, df) < p:
      lo = mid
    else:
      hi = mid
    if hi - lo < 1e-12:
      break
  return 0.5 * (lo + hi)


def mean_ci(values: Sequence[float], confidence: float = CONFIDENCE) -> dict[str, float]:
  """Mean, sample SD, n and the two-sided Student-t confidence interval of the mean.

  With one value the interval is unknown (NaN): one seed says nothing about the spread.
  """
  x = np.asarray(values, np.float64)
  n = int(x.size)
  if n == 0:
    return {"mean": math.nan, "sd": math.nan, "n": 0, "lo": math.nan, "hi": math.nan}
  mean = float(x.mean())
  if n == 1:
    return {"mean": mean, "sd": math.nan, "n": 1, "lo": math.nan, "hi": math.nan}
  sd = float(x.std(ddof=1))
  half = t_quantile(0.5 + confidence / 2.0, n - 1) * sd / math.sqrt(n)
  return {"mean": mean, "sd": sd, "n": n, "lo": mean - half, "hi": mean + half}


def paired_test(a: Sequence[float], b: Sequence[float],
                confidence: float = CONFIDENCE) -> dict[str, float]:
  """Paired comparison of a against b (same seeds, same order): the mean difference a - b with
  its t interval, the paired t statistic and its two-sided p-value, and how many pairs have
  a < b ('wins', i.e. a better for lower-is-better metrics) and a > b ('losses')."""
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  if a.shape != b.shape:
    raise ValueError(f"paired samples differ in length: {a.size} and {b.size}")
  d = a - b
  out = mean_ci(d, confidence)
  out["wins"], out["losses"] = int(np.sum(d < 0)), int(np.sum(d > 0))
  out["t"], out["p"] = math.nan, math.nan
  if d.size >= 2:
    if out["sd"] > 0:
      out["t"] = out["mean"] / (out["sd"] / math.sqrt(d.size))
      out["p"] = 2.0 * (1.0 - t_cdf(abs(out["t"]), d.size - 1))
    else:  # every pair differs by the same amount
      out["t"] = math.copysign(math.inf, out["mean"]) if out["mean"] else 0.0
      out["p"] = 0.0 if out["mean"] else 1.0
  return out


def delta_m(metrics: dict[str, float], baseline: dict[str, float]) -> float:
  """MTAN's multi-task gain (Liu et al. 2019 / Maninis et al. 2019) over lower-is-better
  metrics, in %: mean over k of (baseline_k - metric_k) / baseline_k * 100; > 0 is better.
  NaN where a baseline metric is 0 or not finite (e.g. a bad-2 of 0%): the relative change is
  undefined there."""
  keys = sorted(baseline)
  if not all(math.isfinite(baseline[k]) and baseline[k] != 0 for k in keys):
    return math.nan
  return float(np.mean([(baseline[k] - metrics[k]) / baseline[k] * 100.0 for k in keys]))
