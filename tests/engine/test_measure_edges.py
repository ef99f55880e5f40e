"""The entropic and Wang measures at the edges of their parameters: an aversion eta so large that exp(-eta z), eta^2
or eta |z - mean| overflows. Every value, gradient and bootstrap resample stays finite and right (log-sum-exp
shifted where it must be), and nothing changes where nothing overflowed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from riskplan.engine.estimators import entropic, entropic_gradient, normal_quantile
from riskplan.engine.measures.base import Params
from riskplan.engine.measures.entropic import Entropic, _bootstrap_entropic
from riskplan.engine.measures.wang import Wang
from riskplan.engine.rng import resample_counts

LARGEST = np.finfo(np.float64).max


def by_hand(values: np.ndarray, eta: float) -> float:
    """-(1/eta) log mean exp(-eta z) in exact arithmetic, for a sample whose z's are at least 1000 / eta apart:
    min z + log(W / #{min z}) / eta, up to terms below e^-1000."""
    low = values.min()
    return low + math.log(values.size / np.count_nonzero(values == low)) / eta


def test_entropic_of_a_two_point_sample_where_the_naive_exponential_overflows():
    """z = (-1000, 0), eta = 2: exp(-eta z) = e^2000 overflows, and the risk is -1000 + log(2) / 2 (the e^-2000 of
    the other point is far below a float's precision)."""
    z = np.array([-1000.0, 0.0])
    with np.errstate(over="ignore"):
        assert not np.isfinite(-math.log(np.mean(np.exp(-2.0 * z))) / 2.0)  # naively: -inf
    assert entropic(z, 2.0) == pytest.approx(-1000.0 + math.log(2.0) / 2.0, rel=1e-15)
    assert entropic(z + 5000.0, 2.0) == pytest.approx(4000.0 + math.log(2.0) / 2.0, rel=1e-15)
    # the gradient's weights: softmax(-eta z) puts everything on the low point
    scores = np.array([[1.0, 0.0], [0.0, 1.0]])
    np.testing.assert_allclose(entropic_gradient(z, scores, 2.0), -np.array([0.5, -0.5]) / 2.0, rtol=1e-15)


def test_entropic_of_a_normal_is_mu_minus_eta_sigma_squared_over_two_where_exp_underflows():
    """N(1000, 1) at eta = 1: exp(-eta z) = e^-1000 underflows to 0 (naively log 0), yet the plug-in estimate
    of 10^6 draws is within its standard error, sqrt((e^(eta^2 sigma^2) - 1) / W) / eta ~ 0.0013, of 999.5."""
    mu, sigma, eta = 1000.0, 1.0, 1.0
    z = np.random.default_rng(11).normal(mu, sigma, 1_000_000)
    expected = Entropic().of_normal(mu, sigma, Params({"eta": eta}))
    assert expected == mu - eta * sigma**2 / 2.0 == 999.5
    assert entropic(z, eta) == pytest.approx(expected, abs=0.01)


@pytest.mark.parametrize("eta", [1e306, 1.7e308, float(LARGEST)])
def test_entropic_when_eta_times_the_spread_overflows_is_the_minimum_plus_its_log_share(eta):
    """eta |z - mean| beyond the largest float: the risk is min z + log(W / #min) / eta (here min z itself), the
    gradient's weights all on the minimum, and no warning."""
    z = np.array([[-300.0, 10.0, 10.0, 2500.0], [7.0, 7.0, 8.0, 9.0]])
    scores = np.random.default_rng(2).normal(size=(2, 4, 3))
    with np.errstate(over="raise", invalid="raise", divide="raise"):
        values = entropic(z, eta)
        grads = entropic_gradient(z, scores, eta)
    np.testing.assert_array_equal(values, [by_hand(z[0], eta), by_hand(z[1], eta)])
    np.testing.assert_array_equal(values, [-300.0, 7.0])
    weights = np.array([[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]]) - 0.25
    np.testing.assert_allclose(grads, np.einsum("rw,rwm->rm", weights, scores) / -eta, rtol=1e-12)
    assert np.all(np.isfinite(grads))


def test_entropic_rows_that_overflow_leave_the_others_bit_for_bit():
    z = np.random.default_rng(4).normal(500.0, 200.0, (3, 50))
    z[1, 0] = -1e300  # eta |z - mean| = 1e306 overflows in this row alone
    alone = [entropic(z[i], 1e7) for i in (0, 2)]
    together = entropic(z, 1e7)
    assert together[0] == alone[0] and together[2] == alone[1]
    assert together[1] == pytest.approx(-1e300, rel=1e-15)


def test_the_entropic_bootstrap_of_a_resample_that_misses_the_minimum_is_finite():
    """A resample without the sample's smallest z: its weights exp(-eta (z - min z)) all underflow to 0, so the
    shared shift gave log 0 and +inf, and a percentile interval of NaN (the entropic run of risk.eta=2 that failed
    writing summary.json). Each resample is now the measure of its own draws, by hand."""
    eta = 2.0
    z = np.array([0.0, 1000.0])  # the two-point sample: resamples (2, 0), (1, 1) and (0, 2)
    key, resamples = np.uint64(3), 64
    out = np.full(resamples, np.nan)
    _bootstrap_entropic(z, eta, key, out, 0, resamples)
    counts = [tuple(resample_counts(key, b, 2)) for b in range(resamples)]
    expected = {(2, 0): 0.0, (1, 1): math.log(2.0) / eta, (0, 2): 1000.0}
    assert (0, 2) in counts and (1, 1) in counts  # the case that overflowed is among them
    np.testing.assert_allclose(out, [expected[c] for c in counts], rtol=1e-15, atol=0.0)


@pytest.mark.parametrize("eta", [1.6, 2.0, 50.0, 1e300, float(LARGEST)])
def test_the_entropic_bootstrap_is_each_resamples_measure_for_rewards_hundreds_apart(eta):
    """The paper's total rewards (hundreds to thousands, gaps of tens to hundreds) at the aversions that failed."""
    rng = np.random.default_rng(int(math.log10(eta) * 10))
    z = np.sort(np.concatenate([rng.normal(250.0, 20.0, 2), rng.uniform(800.0, 3000.0, 198)]).round(1))
    key, resamples = np.uint64(9), 200
    out = np.full(resamples, np.nan)
    _bootstrap_entropic(z, eta, key, out, 0, resamples)
    assert np.all(np.isfinite(out))
    missed = [b for b in range(resamples) if not resample_counts(key, b, z.size)[:2].any()]
    assert len(missed) > 10  # resamples without the two low rewards: 550 and more above them, e^-880 underflows
    for b in range(resamples):
        drawn = np.repeat(z, resample_counts(key, b, z.size))
        assert out[b] == pytest.approx(entropic(drawn, eta), rel=1e-12, abs=1e-12)
    low, high = np.percentile(out, [2.5, 97.5])
    assert z.min() <= low <= high <= z.max()


@pytest.mark.parametrize("eta", [1e-3, 1e-12, 1e-17, 1e-20, 1e-300])
def test_the_entropic_bootstrap_of_a_small_aversion_is_each_resamples_measure_near_its_mean(eta):
    """For eta (max z - min z) below about 1e-16, log of a mean of weights within 1e-16 of 1 rounded to 0 and every
    resample was the sample's smallest z: risk.eta=1e-20 printed 'entropic 3594.3 [-1878.6, -1878.6]'. Each
    resample is now its measure (which tends to its mean as eta -> 0), and the interval brackets the value."""
    z = np.sort(np.random.default_rng(4).normal(2000.0, 2500.0, 400).round(1))
    key, resamples = np.uint64(5), 200
    out = np.full(resamples, np.nan)
    _bootstrap_entropic(z, eta, key, out, 0, resamples)
    for b in range(resamples):
        drawn = np.repeat(z, resample_counts(key, b, z.size))
        assert out[b] == pytest.approx(entropic(drawn, eta), rel=1e-12, abs=1e-9)
        if eta <= 1e-12:  # mu - eta sigma^2 / 2 within rounding: the resample's mean
            assert out[b] == pytest.approx(drawn.mean(), rel=1e-6)
    low, high = np.percentile(out, [2.5, 97.5])
    assert low < entropic(z, eta) < high


def test_the_entropic_bootstrap_keeps_its_numbers_where_no_sum_underflowed():
    """Where every resample's sum is a normal float, the shared shift's numbers, bit for bit (the fingerprinted
    runs' case): the same as the plain formula with the sample's minimum as the shift."""
    z = np.sort(np.random.default_rng(6).normal(1000.0, 300.0, 500).round(1))
    key, eta, resamples = np.uint64(21), 0.01, 40
    out = np.empty(resamples)
    _bootstrap_entropic(z, eta, key, out, 0, resamples)
    weights = np.exp(-eta * (z - z[0]))
    for b in range(resamples):
        counts = resample_counts(key, b, z.size)
        total = 0.0
        for c, w in zip(counts, weights):
            total += c * w
        assert out[b] == z[0] - math.log(total / z.size) / eta


# --- Wang ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("eta", [2.0**512, 1e155, 1e300, float(LARGEST)])
def test_wang_beyond_where_eta_squared_overflows_is_the_minimum_with_a_zero_spectrum(eta):
    """phi = exp(-eta x - eta^2 / 2): eta^2 overflowed (an OverflowError for risk.eta=1e155). Its value is 0 at every
    finite x for any eta past 1e154 (as it is, computed, at 1e154), and the measure the sample's minimum."""
    wang, params = Wang(), Params({"eta": eta})
    near = Params({"eta": 1e154})  # the largest eta that ran before
    weights, phi = wang.make_tables(params, 200)
    near_weights, near_phi = wang.make_tables(near, 200)
    np.testing.assert_array_equal(weights, near_weights)
    np.testing.assert_array_equal(phi, near_phi)
    assert np.all(phi == 0.0)
    u = np.array([0.0, 1e-300, 0.3, 0.5, 1.0])
    np.testing.assert_array_equal(wang.spectrum(u, params), [np.inf, 0.0, 0.0, 0.0, 0.0])
    z = np.random.default_rng(7).normal(800.0, 400.0, (2, 200))
    scores = np.random.default_rng(8).normal(size=(2, 200, 3))
    values, grads = wang.objective_and_gradient(z, scores, params)
    np.testing.assert_array_equal(values, z.min(axis=-1))
    assert np.all(grads == 0.0)
    out = np.empty(30)
    wang.bootstrap(np.sort(z[0]), params, np.uint64(1), out)
    assert np.all(np.isfinite(out))


def test_wang_below_the_overflow_keeps_its_spectrum_bit_for_bit():
    x_u = np.array([0.01, 0.2, 0.5, 0.9])
    wang = Wang()
    for eta in (0.25, 0.75, 3.0, 1e100, 1e154):
        expected = np.exp(-eta * normal_quantile(x_u) - 0.5 * eta**2)
        assert wang.spectrum(x_u, Params({"eta": eta})).tobytes() == expected.tobytes()
