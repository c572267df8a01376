"""Experiment statistics against closed forms, published quantiles and hand computations."""

import math

import numpy as np
import pytest

from sljax.experiment.report import stats


@pytest.mark.parametrize("t", [-7.0, -1.3, 0.0, 0.4, 2.5, 30.0])
def test_t_cdf_closed_forms(t):
  # df = 1 is the Cauchy distribution, df = 2 has F(t) = 1/2 + t / (2 sqrt(2 + t^2)).
  assert stats.t_cdf(t, 1) == pytest.approx(0.5 + math.atan(t) / math.pi, abs=1e-12)
  assert stats.t_cdf(t, 2) == pytest.approx(0.5 + t / (2 * math.sqrt(2 + t * t)), abs=1e-12)


@pytest.mark.parametrize("df, q", [(1, 12.706205), (2, 4.302653), (3, 3.182446), (4, 2.776445),
                                   (9, 2.262157), (29, 2.045230)])
def test_t_quantile_matches_tables(df, q):
  assert stats.t_quantile(0.975, df) == pytest.approx(q, abs=2e-6)
  assert stats.t_quantile(0.025, df) == pytest.approx(-q, abs=2e-6)


def test_mean_ci_by_hand():
  # 1, 2, 3, 6: mean 3, sd sqrt(14/3), half width t(0.975, 3) * sd / 2.
  ci = stats.mean_ci([1.0, 2.0, 3.0, 6.0])
  half = 3.182446 * math.sqrt(14.0 / 3.0) / 2.0
  assert ci["mean"] == 3.0 and ci["n"] == 4
  assert ci["lo"] == pytest.approx(3.0 - half, abs=1e-5)
  assert ci["hi"] == pytest.approx(3.0 + half, abs=1e-5)
  one = stats.mean_ci([2.5])
  assert one["mean"] == 2.5 and math.isnan(one["lo"]) and math.isnan(one["sd"])


def test_paired_test_on_a_small_table():
  # Three seeds; the strategy beats the baseline by 1, 2 and 3 px: d = -1, -2, -3.
  strategy = [0.5, 1.0, 1.5]
  baseline = [1.5, 3.0, 4.5]
  res = stats.paired_test(strategy, baseline)
  assert res["mean"] == pytest.approx(-2.0) and res["sd"] == pytest.approx(1.0)
  t = -2.0 / (1.0 / math.sqrt(3.0))
  assert res["t"] == pytest.approx(t)
  # df = 2: p = 2 (1 - F(|t|)) = 1 - |t| / sqrt(2 + t^2).
  assert res["p"] == pytest.approx(1.0 - abs(t) / math.sqrt(2.0 + t * t), abs=1e-10)
  half = 4.302653 / math.sqrt(3.0)
  assert (res["lo"], res["hi"]) == (pytest.approx(-2 - half, abs=1e-5),
                                    pytest.approx(-2 + half, abs=1e-5))
  assert res["wins"] == 3 and res["losses"] == 0
  same = stats.paired_test([1.0, 2.0], [1.0, 2.0])
  assert same["t"] == 0.0 and same["p"] == 1.0 and same["wins"] == 0 and same["losses"] == 0
  mixed = stats.paired_test([1.0, 3.0, 2.0], [2.0, 2.0, 2.0])
  assert (mixed["wins"], mixed["losses"]) == (1, 1)
  with pytest.raises(ValueError):
    stats.paired_test([1.0], [1.0, 2.0])


def test_delta_m_by_hand():
  base = {"mae": 2.0, "bad_2": 10.0}
  assert stats.delta_m({"mae": 1.0, "bad_2": 12.0}, base) == pytest.approx((50.0 - 20.0) / 2)
  assert stats.delta_m(base, base) == 0.0


def test_delta_m_is_nan_where_a_baseline_metric_is_zero():
  # A fine-tuned baseline can reach a bad-2 of exactly 0%: the relative change is undefined
  # (the report showed a ZeroDivisionError instead of writing itself).
  assert math.isnan(stats.delta_m({"mae": 1.0, "bad_2": 1.0}, {"mae": 2.0, "bad_2": 0.0}))
  assert math.isnan(stats.delta_m({"mae": 1.0}, {"mae": float("nan")}))
  assert math.isnan(stats.mean_ci([1.0, math.nan, 2.0])["mean"])  # the report then shows "-"


def test_incomplete_beta_symmetry_and_bounds():
  for a, b, x in ((2.0, 3.0, 0.3), (0.5, 4.5, 0.9), (10.0, 0.5, 0.99)):
    assert stats.incomplete_beta(a, b, x) == pytest.approx(
        1.0 - stats.incomplete_beta(b, a, 1.0 - x), abs=1e-12)
  # I_x(1, 1) = x; I_x(a, 1) = x^a.
  assert stats.incomplete_beta(1.0, 1.0, 0.37) == pytest.approx(0.37)
  assert stats.incomplete_beta(3.0, 1.0, 0.5) == pytest.approx(0.125)
  assert np.isclose(stats.incomplete_beta(2.0, 2.0, 0.0), 0.0)


def test_claim_of_the_baseline_counts_its_own_wins():
  """A claim that the baseline beats an arm flips the difference and counts the baseline's wins."""
  from types import SimpleNamespace
  from sljax.experiment.report.build import claims
  diff = stats.paired_test([2.0, 2.1, 1.9], [1.0, 1.0, 1.0])  # unet-sl - unet-disp: all worse
  agg = {"groups": [{"factors": {"data": "objects"},
                     "sets": {"heldout": {"paired": {"unet-sl": {"mae": diff,
                                                                  "seg_mae": diff}}}}}]}
  first = claims(SimpleNamespace(name="table1"), agg)[0]
  assert "unet-disp) has a lower Full MAE" in first["claim"]
  d = first["difference"]
  assert d["mean"] == pytest.approx(-1.0) and d["hi"] < 0
  assert (d["wins"], d["losses"]) == (3, 0)
  assert first["verdict"] == "holds"


def test_holm_by_hand():
  # Sorted: 0.005 x 4 = 0.02; 0.01 x 3 = 0.03; 0.03 x 2 = 0.06; 0.04 x 1 = 0.04 -> max 0.06.
  adjusted = stats.holm([0.01, 0.04, 0.03, 0.005])
  assert adjusted == pytest.approx([0.03, 0.06, 0.06, 0.02])
  # NaN is not a test: it keeps its place and does not count in m.
  mixed = stats.holm([0.02, math.nan, 0.5])
  assert mixed[0] == pytest.approx(0.04) and math.isnan(mixed[1]) and mixed[2] == 0.5
  assert stats.holm([0.9, 0.8]) == [1.0, 1.0]  # 0.8 x 2 capped at 1; then max(1, 0.9)
  assert stats.holm([]) == []


def test_power_of_the_paired_t_test_matches_published_values():
  # pwr.t.test(d = 1, n = 10, type = "one.sample") = 0.8031; the n for d = 0.5 at 80% power
  # is 33.367 (pwr); at delta = 0 the power is alpha.
  assert stats.paired_power(1.0, 1.0, 10) == pytest.approx(0.80310, abs=1e-4)
  assert stats.paired_power(0.5, 1.0, 33.367) == pytest.approx(0.8, abs=1e-4)
  assert stats.paired_power(0.0, 2.0, 5) == pytest.approx(0.05, abs=1e-9)
  # Large df: the normal approximation Phi(ncp - z) + Phi(-ncp - z) with the t quantile.
  n, delta = 2000, 0.07
  c = stats.t_quantile(0.975, n - 1)
  ncp = delta * math.sqrt(n)
  phi = lambda x: 0.5 * math.erfc(-x / math.sqrt(2))  # noqa: E731
  assert stats.paired_power(delta, 1.0, n) == pytest.approx(phi(ncp - c) + phi(-ncp - c),
                                                            abs=2e-4)


@pytest.mark.parametrize("n", [2, 3, 5, 10])
def test_detectable_difference_has_80_percent_power_by_simulation(n):
  """Simulated paired t-tests (float64, 400k draws) at the detectable difference reject about
  80% of the time; the difference scales with the SD."""
  sd = 0.3
  delta = stats.detectable_difference(sd, n)
  assert stats.detectable_difference(2 * sd, n) == pytest.approx(2 * delta, rel=1e-6)
  rng = np.random.default_rng(n)
  d = rng.normal(delta, sd, (400_000, n))
  t = d.mean(1) / (d.std(1, ddof=1) / math.sqrt(n))
  power = np.mean(np.abs(t) > stats.t_quantile(0.975, n - 1))
  assert power == pytest.approx(0.8, abs=0.004)  # 6 standard errors of the simulation
  assert math.isnan(stats.detectable_difference(sd, 1))
  assert math.isnan(stats.detectable_difference(0.0, n))


def test_delta_m_with_a_higher_is_better_metric_by_hand():
  # MAE 2.0 -> 1.5 is +25%; pattern accuracy 80 -> 90 is +12.5%: mean +18.75%.
  got = stats.delta_m({"mae": 1.5, "pattern_acc": 90.0}, {"mae": 2.0, "pattern_acc": 80.0},
                      higher_better=("pattern_acc",))
  assert got == pytest.approx(18.75)
  assert stats.delta_m({"mae": 3.0}, {"mae": 2.0}) == pytest.approx(-50.0)


# ------------------------------------------------------------
# Experiment statistics where mutants of sljax/experiment/report/stats.py survived the other tests.
#
# Closed forms: df = 1 is the Cauchy distribution, F(t) = 1/2 + atan(t) / pi, quantile
# tan(pi (p - 1/2)); df = 2 has F(t) = 1/2 + t / (2 sqrt(2 + t^2)), quantile
# u sqrt(2 / (1 - u^2)) with u = 2p - 1.


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
