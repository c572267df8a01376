"""Experiment statistics where mutants of sljax/experiment/stats.py survived the other tests.

Closed forms: df = 1 is the Cauchy distribution, F(t) = 1/2 + atan(t) / pi, quantile
tan(pi (p - 1/2)); df = 2 has F(t) = 1/2 + t / (2 sqrt(2 + t^2)), quantile
u sqrt(2 / (1 - u^2)) with u = 2p - 1.
"""

import math

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
