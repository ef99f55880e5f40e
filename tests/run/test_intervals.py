"""The summary's percentile bootstrap (riskplan.run.intervals): exact resampling law on tiny samples, and interval widths
against the asymptotic standard errors of the mean and of CVaR for a normal sample."""

import itertools
import math
from statistics import NormalDist

import numpy as np
import pytest

from riskplan.engine.rng import resample_counts
from riskplan.risk import cvar, tail_count, value_at_risk
from riskplan.run.intervals import (
    REPORT_BETAS,
    _bootstrap,
    bootstrap_intervals,
    objective_interval,
    objective_intervals,
)

STD = NormalDist()


def resample_stats(z, resamples, seed=0, beta=0.5):
    """The raw per-resample statistics [mean, VaR_beta, CVaR_beta, CVaR at REPORT_BETAS]."""
    z = np.sort(np.asarray(z, dtype=float))
    betas = np.array([beta, *REPORT_BETAS])
    tails = np.array([tail_count(b, z.size) for b in betas], dtype=np.int64)
    out = np.empty((resamples, 2 + betas.size))
    _bootstrap(z, betas, tails, np.uint64(seed), out)
    return out


@pytest.mark.parametrize("values", [[1.0, 2.0, 3.0], [1.0, 2.0, 4.0, 8.0]])  # odd n takes the unpaired draw
def test_resample_means_follow_the_exact_law_of_drawing_with_replacement(values):
    n, resamples = len(values), 40_000
    means = resample_stats(values, resamples)[:, 0]
    exact: dict[float, float] = {}
    for draw in itertools.product(values, repeat=n):  # all n^n equally likely resamples
        key = round(sum(draw) / n, 9)
        exact[key] = exact.get(key, 0.0) + 1.0 / n**n
    seen = {key: np.mean(np.isclose(means, key)) for key in exact}
    assert sum(seen.values()) == pytest.approx(1.0)  # no resample mean outside the exact support
    for key, p in exact.items():
        assert abs(seen[key] - p) < 4 * math.sqrt(p * (1 - p) / resamples), (key, seen[key], p)


def test_one_value_gives_a_zero_width_interval():
    figures = bootstrap_intervals(np.array([7.5]), 0.1, 50, 3)
    for name, figure in figures.items():
        assert figure["low"] == figure["value"] == figure["high"] == 7.5, name


def test_intervals_match_the_asymptotic_standard_errors_of_a_normal_sample():
    n, beta = 50_000, 0.1
    z = np.random.default_rng(5).normal(size=n)
    figures = bootstrap_intervals(z, beta, 1000, 11)
    half = {name: (f["high"] - f["low"]) / 2 for name, f in figures.items()}
    assert half["mean"] == pytest.approx(1.96 / math.sqrt(n), rel=0.12)
    # CVaR_b = v + E[(X - v) 1{X <= v}] / b: its estimator's variance is Var((X - v) 1{X <= v}) / (b^2 n)
    v = STD.inv_cdf(beta)
    phi = math.exp(-v * v / 2) / math.sqrt(2 * math.pi)
    tail_mean = -phi - v * beta  # E[(X - v) 1{X <= v}], with E[X 1{X <= v}] = -phi(v)
    tail_square = beta + v * phi + v * v * beta  # E[(X - v)^2 1{X <= v}], with E[X^2 1{X <= v}] = beta - v phi(v)
    se = math.sqrt((tail_square - tail_mean**2) / (beta**2 * n))
    assert half["cvar"] == pytest.approx(1.96 * se, rel=0.12)
    assert abs(figures["cvar"]["value"] - (-phi / beta)) < 4 * se  # the analytic CVaR of N(0, 1)


def test_the_same_seed_gives_the_same_intervals_and_another_seed_others():
    z = np.random.default_rng(2).exponential(size=10_001)
    first, again = bootstrap_intervals(z, 0.2, 200, 4), bootstrap_intervals(z, 0.2, 200, 4)
    assert first == again
    assert bootstrap_intervals(z, 0.2, 200, 5)["mean"] != first["mean"]


@pytest.mark.parametrize("resamples", [1, 3, 4, 9])  # the kernel sums LANES = 4 resamples side by side
@pytest.mark.parametrize("beta", [0.1, 0.3])  # 0.1 is also a reported level: its CVaR is read once
def test_each_resample_row_is_the_statistics_of_its_own_draws(resamples, beta):
    z = np.sort(np.random.default_rng(4).normal(10.0, 3.0, 501))
    seed = 7
    rows = resample_stats(z, resamples, seed=seed, beta=beta)
    for b, row in enumerate(rows):
        counts = resample_counts(np.uint64(seed), b, z.size)
        assert counts.sum() == z.size
        drawn = np.repeat(z, counts)
        total = 0.0
        for c, value in zip(counts, z):  # the kernel's order of additions: the same number, bit for bit
            total += c * value
        assert row[0] == total / z.size
        assert row[1] == value_at_risk(drawn, beta)
        for level, got in zip([beta, *REPORT_BETAS], row[2:]):
            assert got == pytest.approx(cvar(drawn, level), rel=1e-12)


def test_the_terms_of_a_team_bootstrap_together_to_each_terms_own_interval():
    """objective_intervals (each resample drawn once for the terms of one measure and size) gives every term the
    interval and resamples it has alone: measures, levels and sizes mixed."""
    rng = np.random.default_rng(12)
    zs = [rng.normal(50.0, 9.0, 2000), rng.normal(40.0, 3.0, 2000), rng.normal(45.0, 5.0, 1500), rng.normal(0, 1, 2000)]
    risks = [
        {"measure": "cvar", "beta": 0.1},
        {"measure": "cvar", "beta": 0.3},
        {"measure": "cvar", "beta": 0.1},
        {"measure": "entropic", "eta": 0.5},
    ]
    together = objective_intervals(zs, risks, 300, 9)
    for (figure, values), z, risk in zip(together, zs, risks):
        alone, alone_values = objective_interval(z, risk, 300, 9)
        assert figure == alone
        np.testing.assert_array_equal(values, alone_values)
    assert together[0][0]["value"] < together[0][0]["high"] and together[0][0]["low"] < together[0][0]["value"]


def test_point_values_are_bit_for_bit_those_of_the_episodes_in_their_order():
    """summary.json's mean and CVaR were of the sorted episodes, summed in another order than numpy and
    riskplan.risk sum eval.parquet's: MLflow's summary/mean and report.csv differed in the last digit."""
    z = np.random.default_rng(5).normal(1721.3, 900.0, 6000)  # each figure summed sorted differs here
    figures = bootstrap_intervals(z, 0.1, 40, seed=0)
    assert figures["mean"]["value"] == float(np.mean(z))
    assert figures["cvar"]["value"] == cvar(z, 0.1)
    assert figures["cvar_0.05"]["value"] == cvar(z, 0.05)
