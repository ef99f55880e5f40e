"""The risk estimators (riskplan.risk: VaR, CVaR, the mean and CVaR gradients of eqs. 4-9, tail counts) against closed
forms and exact small cases, and every registered measure's gradient (measure_cases) against its closed form's."""

from __future__ import annotations

from statistics import NormalDist

import numpy as np
import pytest
from measure_cases import measure_cases

from riskplan.risk import (
    cvar,
    cvar_gradient,
    mean_gradient,
    objective,
    risk_spec,
    summary_stats,
    tail_count,
    value_at_risk,
)
from riskplan.util.errors import BadInput


def normal_cvar(mu: float, sigma: float, beta: float) -> float:
    """Lower-tail CVaR of N(mu, sigma^2): mu - sigma * phi(Phi^-1(beta)) / beta."""
    unit = NormalDist()
    return mu - sigma * unit.pdf(unit.inv_cdf(beta)) / beta


@pytest.mark.parametrize("beta", [0.05, 0.1, 0.25, 0.5])
def test_normal_var_and_cvar_match_closed_form(beta):
    z = np.random.default_rng(1).normal(3.0, 2.0, 1_000_000)
    assert value_at_risk(z, beta) == pytest.approx(3.0 + 2.0 * NormalDist().inv_cdf(beta), abs=0.02)
    assert cvar(z, beta) == pytest.approx(normal_cvar(3.0, 2.0, beta), abs=0.02)


@pytest.mark.parametrize("beta", [0.05, 0.2, 0.7])
def test_uniform_var_and_cvar_match_closed_form(beta):
    z = np.random.default_rng(2).uniform(0.0, 1.0, 1_000_000)
    assert value_at_risk(z, beta) == pytest.approx(beta, abs=2e-3)
    assert cvar(z, beta) == pytest.approx(beta / 2.0, abs=2e-3)


def test_exact_small_cases():
    z = np.arange(10, 0, -1, dtype=float)  # unsorted 10..1
    assert value_at_risk(z, 0.3) == 3.0
    assert cvar(z, 0.3) == pytest.approx(2.0)  # mean of {1, 2, 3}: beta W whole, eq. (6)
    # beta W = 2.5 is not whole: m = 3, v = 3, cvar = 3 + ((1-3) + (2-3)) / 2.5
    assert value_at_risk(z, 0.25) == 3.0
    assert cvar(z, 0.25) == pytest.approx(1.8)
    assert cvar(z, 1.0) == pytest.approx(z.mean())
    assert value_at_risk(z, 1.0) == 10.0
    assert cvar(z, 0.01) == 1.0  # m = 1: the minimum


def test_tail_count_guards_float_error():
    assert 0.07 * 100 != 7  # the trap this guards against
    assert tail_count(0.07, 100) == 7
    assert tail_count(0.1, 6000) == 600
    assert tail_count(0.3, 10) == 3
    assert tail_count(0.25, 10) == 3
    assert tail_count(1e-9, 10) == 1
    with pytest.raises(ValueError):
        tail_count(0.0, 10)
    with pytest.raises(ValueError):
        tail_count(1.5, 10)


def test_cvar_gradient_location_scale_normal():
    """z ~ N(mu, sigma^2): dCVaR/dmu = 1 and dCVaR/dsigma = -phi(Phi^-1(beta)) / beta."""
    mu, sigma, beta = 1.0, 2.0, 0.1
    z = np.random.default_rng(3).normal(mu, sigma, 2_000_000)
    scores = np.stack([(z - mu) / sigma**2, ((z - mu) ** 2 - sigma**2) / sigma**3], axis=1)
    grad = cvar_gradient(z, scores, beta)
    unit = NormalDist()
    assert grad[0] == pytest.approx(1.0, abs=0.03)
    assert grad[1] == pytest.approx(-unit.pdf(unit.inv_cdf(beta)) / beta, abs=0.05)


def test_mean_gradient_location_scale_normal():
    mu, sigma = -2.0, 1.5
    z = np.random.default_rng(4).normal(mu, sigma, 1_000_000)
    scores = np.stack([(z - mu) / sigma**2, ((z - mu) ** 2 - sigma**2) / sigma**3], axis=1)
    for baseline in (True, False):
        grad = mean_gradient(z, scores, baseline=baseline)
        assert grad == pytest.approx([1.0, 0.0], abs=0.02)


def test_cvar_gradient_exact_small_case():
    z = np.array([5.0, 1.0, 3.0, 2.0, 4.0])
    scores = np.arange(10, dtype=float).reshape(5, 2)
    # beta = 0.4: m = 2, v = 2; tail {1 (row 1), 2 (row 3)}: weights (1-2) and 0
    expected = (-1.0 * scores[1]) / (0.4 * 5)
    assert cvar_gradient(z, scores, 0.4) == pytest.approx(expected)


def test_beta_one_cvar_gradient_is_unbiased_mean_gradient():
    """At beta = 1 the tail is everything and v = max: an unbiased mean gradient with baseline max(z)."""
    rng = np.random.default_rng(5)
    z = rng.normal(size=1000)
    scores = rng.normal(size=(1000, 3))
    expected = ((z - z.max()) @ scores) / z.size
    assert cvar_gradient(z, scores, 1.0) == pytest.approx(expected)


@pytest.mark.parametrize("risk", measure_cases())
def test_every_measures_gradient_on_the_normal_family_is_its_closed_forms_derivative(risk):
    """z ~ N(mu, sigma^2) with the scores of (mu, sigma): the estimate, over 16 batches of 125,000, within 4
    standard errors of the central differences of the measure's closed form (`of_normal`) in mu and sigma."""
    measure, params = risk_spec(risk)
    mu, sigma, h = 1.0, 1.0, 1e-4
    if measure.of_normal(mu, sigma, params) is None:
        pytest.skip(f"{measure.name} has no closed form on a normal")
    expected = [
        (measure.of_normal(mu + h, sigma, params) - measure.of_normal(mu - h, sigma, params)) / (2 * h),
        (measure.of_normal(mu, sigma + h, params) - measure.of_normal(mu, sigma - h, params)) / (2 * h),
    ]
    z = np.random.default_rng(6).normal(mu, sigma, (16, 125_000))
    scores = np.stack([(z - mu) / sigma**2, ((z - mu) ** 2 - sigma**2) / sigma**3], axis=-1)
    grads = measure.gradient(z, scores, params)
    se = grads.std(axis=0, ddof=1) / 4.0
    assert np.all(se < 0.02)  # a tolerance that could not hide a wrong estimator
    np.testing.assert_array_less(np.abs(grads.mean(axis=0) - expected), 4 * se)


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda z, s: cvar(None, 0.1), "z: must have shape (..., W)"),
        (lambda z, s: value_at_risk(np.float64(3.0), 0.5), "z: must have shape (..., W)"),
        (lambda z, s: cvar_gradient(z, s[:50], 0.1), "scores: must have shape (100, 'M')"),
        (lambda z, s: cvar_gradient(z, z, 0.1), "scores: must have shape (100, 'M')"),
        (lambda z, s: mean_gradient(z, s[:10]), "scores: must have shape (100, 'M')"),
        (lambda z, s: cvar(z, 0.0), "beta: must be in (0, 1], got 0.0"),
        (lambda z, s: value_at_risk(z, 1.5), "beta: must be in (0, 1], got 1.5"),
        (lambda z, s: cvar_gradient(z, s, -0.1), "beta: must be in (0, 1], got -0.1"),
        # a TypeError of a comparison or of round(), or (True) beta = 1 in silence
        (lambda z, s: cvar(z, None), "beta: must be a number in (0, 1], got None"),
        (lambda z, s: cvar(z, "0.1"), "beta: must be a number in (0, 1], got '0.1'"),
        (lambda z, s: cvar(z, np.array([0.1])), "beta: must be a number in (0, 1], got array([0.1])"),
        (lambda z, s: value_at_risk(z, True), "beta: must be a number in (0, 1], got True"),
        (lambda z, s: objective(z, "cvar"), "risk: got 'cvar'; give a risk node, a mapping such as"),
        # numpy cast these: a complex sample lost its imaginary part with a warning, text failed naming no argument
        (lambda z, s: cvar(z + 1j, 0.1), "z: got complex numbers; expected real numbers"),
        (lambda z, s: value_at_risk(np.array(["a", "b"]), 0.5), "z: got values of dtype <U1; expected real numbers"),
        (lambda z, s: cvar_gradient(z, s * 1j, 0.1), "scores: got complex numbers; expected real numbers"),
    ],
)
def test_arrays_of_the_wrong_shape_are_one_line_naming_them(call, words):
    """The public estimators (riskplan.risk) say what shape they take, not numpy's broadcast or index error."""
    z = np.random.default_rng(0).normal(size=100)
    scores = np.random.default_rng(1).normal(size=(100, 2))
    with pytest.raises(BadInput) as refused:  # the CLI's one-line error, still a ValueError
        call(z, scores)
    assert words in str(refused.value) and "\n" not in str(refused.value)


def test_a_nan_sample_gives_nan_from_value_at_risk_as_from_cvar_and_the_mean():
    """numpy's partition sorts a NaN last, so VaR alone would ignore it; every estimator says NaN instead, row by
    row: the finite row keeps its numbers."""
    z = np.array([[3.0, np.nan, 1.0, 2.0], [4.0, 1.0, 3.0, 2.0]])
    assert np.isnan(value_at_risk(z, 0.5)[0]) and np.isnan(cvar(z, 0.5)[0]) and np.isnan(z.mean(axis=-1)[0])
    assert value_at_risk(z, 0.5)[1] == 2.0 and cvar(z, 0.5)[1] == 1.5
    assert np.isnan(value_at_risk([np.nan], 1.0)) and np.isnan(cvar([np.nan], 1.0))
    stats = summary_stats(z, 0.5)  # all four at once, as a report's table takes them
    assert all(np.isnan(stats[name][0]) for name in ("mean", "cvar", "value_at_risk", "std"))
    assert (stats["value_at_risk"][1], stats["cvar"][1]) == (2.0, 1.5)
    assert np.isnan(summary_stats(np.array([1.0, np.nan]), 0.1)["value_at_risk"])


@pytest.mark.parametrize(
    "z, beta, expected",
    [
        ([1e308, 1e308, -1e308], 1.0, 1e308 / 3),  # the mean of the three, where z - v overflows
        ([1e308, 1e308, -1e308], 0.5, -1e308 / 3),  # beta W = 1.5: v = 1e308, v + (-2e308) / 1.5
        ([-1.5e308, 1.7e308, 1.7e308], 1.0, 1.9 / 3 * 1e308),
        ([-0.9e308] * 4 + [0.9e308], 1.0, -0.54e308),  # each z - v is finite, their sum is not
    ],
)
def test_cvar_of_samples_near_the_largest_float_is_their_tail_mean_not_inf(z, beta, expected):
    value = cvar(np.array(z), beta)
    assert np.isfinite(value) and value == pytest.approx(expected, rel=1e-12, abs=1e292)
    assert cvar(np.array([z, [1.0] * len(z)]), beta)[1] == 1.0  # a batch: only the overflowing row is measured again


@pytest.mark.parametrize("z", [[1.7e308] * 10, [1e308, 1e308, -1e308], [-0.9e308] * 4 + [0.9e308]])
def test_the_mean_and_its_gradient_near_the_largest_float_do_not_overflow(z):
    """The mean is CVaR_1: the objective of risk=neutral, summary_stats' mean and the baseline of mean_gradient
    were inf (its gradient -inf, where the exact one is 0) where cvar(z, 1) was finite."""
    z = np.array(z)
    expected = cvar(z, 1.0)
    assert objective(z, {"measure": "neutral"}) == pytest.approx(expected, rel=1e-12)
    stats = summary_stats(z, 0.5)
    assert stats["mean"] == pytest.approx(expected, rel=1e-12) and stats["cvar"] == pytest.approx(cvar(z, 0.5))
    half_range = z.max() / 2 - z.min() / 2  # (numpy's ptp overflows here)
    assert 0 <= stats["std"] <= half_range + 1e-15 * np.abs(z).max()  # finite: at most half the range
    # equal scores: the centred rewards sum to 0 up to rounding (relative to the rewards' size), never to -inf
    grads = mean_gradient(z, np.ones((len(z), 2)))
    assert np.all(np.abs(grads) <= 1e-15 * np.abs(z).max())
