"""Experiment statistics where mutants of sljax/experiment/stats.py survived the other tests.

Closed forms: df = 1 is the Cauchy distribution, F(t) = 1/2 + atan(t) / pi, quantile
tan(pi (p - 1/2)); df = 2 has F(t) = 1/2 + t / (2 sqrt(2 + t^2)), quantile
u sqrt(2 / (1 - u^2)) with u = 2p - 1.
"""

import math

import numpy as np
import pytest

from sljax.experiment import stats


def test_t_cdf_at_infinity():
  assert stats.t_cdf(math.inf, 3) == 1.0
  assert stats.t_cdf(-math.inf, 3) == 0.0


@pytest.mark.parametrize("t", [-0.999, -0.5, -0.01])
def test_t_cdf_between_minus_one_and_zero(t):
  assert stats.t_cdf(t, 1) == pytest.approx(0.5 + math.atan(t) / math.pi, abs=1e-12)
  assert stats.t_cdf(t, 2) == pytest.approx(0.5 + t / (2 * math.sqrt(2 + t * t)), abs=1e-12)


@pytest.mark.parametrize("p", [0.51, 0.6, 0.7, 0.3])
def test_t_quantile_below_one(p):
  """Quantiles with |t| < 1 (the bisection's first bracket is [0, 1])."""
  assert stats.t_quantile(p, 1) == pytest.approx(math.tan(math.pi * (p - 0.5)), abs=1e-10)
  u = 2 * p - 1
  assert stats.t_quantile(p, 2) == pytest.approx(u * math.sqrt(2 / (1 - u * u)), abs=1e-10)


@pytest.mark.parametrize("p", [0.0, 1.0, -0.5, 1.5])
def test_t_quantile_names_the_bad_probability(p):
  with pytest.raises(ValueError, match=rf"got {p}$"):
    stats.t_quantile(p, 3)


def test_mean_ci_of_no_values_and_of_one():
  empty = stats.mean_ci([])
  assert empty["n"] == 0
  assert all(math.isnan(empty[k]) for k in ("mean", "sd", "lo", "hi"))
  one = stats.mean_ci([4.0])
  assert one["n"] == 1 and one["mean"] == 4.0
  assert all(math.isnan(one[k]) for k in ("sd", "lo", "hi"))


def test_paired_test_with_a_constant_nonzero_difference():
  """Every pair differs by the same amount: sd 0, t infinite with the difference's sign, p 0."""
  worse = stats.paired_test([2.0, 3.0, 4.5], [1.0, 2.0, 3.5])
  assert worse["t"] == math.inf and worse["p"] == 0.0 and worse["losses"] == 3
  better = stats.paired_test([1.0, 2.0], [1.5, 2.5])
  assert better["t"] == -math.inf and better["p"] == 0.0 and better["wins"] == 2


def _t_cdf_by_simpson(t, df, n=200_000):
  """P(T <= t) as 1/2 + the integral of the t density from 0 to t (Simpson, float64)."""
  c = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)) / math.sqrt(df * math.pi)
  x = np.linspace(0.0, abs(t), n + 1)
  f = c * (1 + x * x / df) ** (-(df + 1) / 2)
  integral = (x[1] - x[0]) / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum())
  return 0.5 + math.copysign(integral, t)


@pytest.mark.parametrize("df", [3000, 30000])
def test_t_cdf_with_many_degrees_of_freedom(df):
  """The continued fraction for the side of the switch point it converges on (a wrong side
  is off by 5e-9 at df = 3000 after the 400 terms)."""
  for t in (0.3, -0.3, 1.0):
    assert stats.t_cdf(t, df) == pytest.approx(_t_cdf_by_simpson(t, df), abs=1e-11)


def test_mean_ci_of_two_values():
  """Two seeds: sd = |a - b| / sqrt(2), half width t(0.975, 1) sd / sqrt(2) = 12.706205."""
  ci = stats.mean_ci([1.0, 3.0])
  assert ci["n"] == 2 and ci["mean"] == 2.0 and ci["sd"] == pytest.approx(math.sqrt(2.0))
  assert (ci["lo"], ci["hi"]) == (pytest.approx(2.0 - 12.706205, abs=1e-5),
                                  pytest.approx(2.0 + 12.706205, abs=1e-5))


def test_paired_test_with_a_nan_difference_has_no_p():
  """A NaN value makes the mean and SD NaN; the test is then undefined (p NaN), not a certain
  rejection: the zero-SD branch once took the NaN SD for 0 and returned t = inf, p = 0.0."""
  res = stats.paired_test([1.0, math.nan, 2.0], [1.5, 2.0, 2.5])
  assert math.isnan(res["mean"])
  assert math.isnan(res["p"])
  assert math.isnan(res["t"])
  adjusted = stats.holm([res["p"], 0.02])  # left out of the family, not counted as a rejection
  assert math.isnan(adjusted[0]) and adjusted[1] == pytest.approx(0.02)
