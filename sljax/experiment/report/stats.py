"""Small-sample statistics for the experiment reports: Student-t intervals, paired tests,
Holm's step-down adjustment, the power of the paired t-test and MTL's Delta_m.

Pure Python/NumPy (no SciPy): the t distribution's CDF is the regularised incomplete beta
function, evaluated by its continued fraction (Numerical Recipes, 'betacf'), and quantiles
are found by bisection on the CDF. The noncentral t's tail (power) is an integral over the
chi distribution of the sample SD, evaluated by quadrature on a fixed grid (float64).
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
  if d.size >= 2 and np.isfinite(d).all():  # a NaN SD must not read as "no spread" (p = 0)
    if out["sd"] > 0:
      out["t"] = out["mean"] / (out["sd"] / math.sqrt(d.size))
      out["p"] = 2.0 * (1.0 - t_cdf(abs(out["t"]), d.size - 1))
    else:  # every pair differs by the same amount
      out["t"] = math.copysign(math.inf, out["mean"]) if out["mean"] else 0.0
      out["p"] = 0.0 if out["mean"] else 1.0
  return out


def holm(pvalues: Sequence[float]) -> list[float]:
  """Holm's step-down adjusted p-values (same order as given; NaN stays NaN and is not counted).

  Sorted ascending p_(1) <= ... <= p_(m): adjusted p_(i) = max over j <= i of min(1, (m - j + 1)
  p_(j)). Rejecting where the adjusted p < alpha controls the family-wise error at alpha.
  """
  p = [float(v) for v in pvalues]
  live = sorted((v, i) for i, v in enumerate(p) if not math.isnan(v))
  m = len(live)
  out = [math.nan] * len(p)
  running = 0.0
  for rank, (v, i) in enumerate(live):
    running = max(running, min(1.0, (m - rank) * v))
    out[i] = running
  return out


_ERFC = np.vectorize(math.erfc, otypes=[np.float64])


def _two_sided_tail(ncp: float, c: float, df: float) -> float:
  """P(|T| > c) for T noncentral t (df, ncp): E_X[Phi(ncp - c X / sqrt(df)) + Phi(-ncp - c X /
  sqrt(df))] over X = sqrt(V), V chi-square(df), whose density 2 x g(x^2) has no singularity;
  trapezoid quadrature on 4001 points out to 12 SDs past the mean of V (float64)."""
  x = np.linspace(0.0, math.sqrt(df + 12.0 * math.sqrt(2.0 * df) + 40.0), 4001)
  with np.errstate(divide="ignore"):
    power_term = (df - 1.0) * np.log(x) if df != 1.0 else np.zeros_like(x)  # 0 * log 0 = 0
  w = np.exp(power_term - x * x / 2.0 + math.log(2.0) - (df / 2.0) * math.log(2.0)
             - math.lgamma(df / 2.0))
  s = x / math.sqrt(df)
  root2 = math.sqrt(2.0)
  f = 0.5 * _ERFC(-(ncp - c * s) / root2) + 0.5 * _ERFC(-(-ncp - c * s) / root2)
  return float(np.trapezoid(w * f, x))


def paired_power(delta: float, sd: float, n: float, alpha: float = 0.05) -> float:
  """Power of the two-sided paired t-test at level alpha to detect a true mean difference delta
  with per-pair SD sd over n pairs: P(|T| > t_crit), T noncentral t with df n - 1 and
  noncentrality delta sqrt(n) / sd; n may be fractional (as pwr's sample-size solver)."""
  df = n - 1.0
  if not (df > 0 and sd > 0 and math.isfinite(sd)):
    return math.nan
  c = t_quantile(1.0 - alpha / 2.0, df)
  return _two_sided_tail(abs(delta) * math.sqrt(n) / sd, c, df)


def detectable_difference(sd: float, n: int, power: float = 0.8, alpha: float = 0.05) -> float:
  """The smallest true paired mean difference the two-sided paired t-test at alpha detects
  with the given power, for per-pair SD sd and n pairs (bisection on the power); NaN for
  n < 2 or an unknown SD."""
  if n < 2 or not (sd > 0 and math.isfinite(sd)):
    return math.nan
  df = n - 1.0
  c = t_quantile(1.0 - alpha / 2.0, df)
  scale = math.sqrt(n) / sd
  lo, hi = 0.0, sd
  while _two_sided_tail(hi * scale, c, df) < power:
    hi *= 2.0
  for _ in range(50):
    mid = 0.5 * (lo + hi)
    if _two_sided_tail(mid * scale, c, df) < power:
      lo = mid
    else:
      hi = mid
  return 0.5 * (lo + hi)


def delta_m(metrics: dict[str, float], baseline: dict[str, float],
            higher_better: Sequence[str] = ()) -> float:
  """The multi-task gain Delta_m of Maninis et al. 2019 / Vandenhende et al. 2021, in %: the
  mean over the given primary metrics k (one per task) of (-1)^l_k (M_k - B_k) / B_k * 100,
  l_k = 1 for lower-is-better metrics, 0 for those named in higher_better; > 0 is better.
  NaN where a baseline metric is 0 or not finite: the relative change is undefined there."""
  keys = sorted(baseline)
  if not keys or not all(math.isfinite(baseline[k]) and baseline[k] != 0 for k in keys):
    return math.nan
  signs = {k: (1.0 if k in higher_better else -1.0) for k in keys}
  return float(np.mean([signs[k] * (metrics[k] - baseline[k]) / baseline[k] * 100.0
                        for k in keys]))
