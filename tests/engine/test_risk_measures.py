"""Risk measures behind one interface: objective and objective_gradient for neutral, cvar, wang, mean_cvar and
entropic, against closed forms, the reference estimators, and an exactly enumerated world; and every registered
measure (measure_cases), against its own closed form, its distortion and its parameters' ranges.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from enum import Enum
from statistics import NormalDist

import numpy as np
import pytest
from measure_cases import measure_cases
from omegaconf import OmegaConf
from support import exact_outcomes, rollouts, world_3x3

from riskplan.config.schema import RiskConf
from riskplan.engine.measures.entropic import _bootstrap_entropic
from riskplan.engine.measures.spectral import _bootstrap_distorted, _flat_from
from riskplan.engine.policy import move_features, probabilities, scores
from riskplan.engine.risk_measures import normal_cdf, normal_quantile, objective_and_gradient
from riskplan.engine.rng import resample_counts
from riskplan.risk import (
    MEASURES,
    Spectral,
    cvar,
    cvar_gradient,
    distortion,
    distortion_at,
    l_statistic,
    lookup,
    mean_gradient,
    objective,
    objective_gradient,
    risk_spec,
    spectral_gradient,
    spectral_weights,
    spectrum,
    tail_count,
    value_at_risk,
)
from riskplan.util.errors import BadInput

UNIT = NormalDist()
MU, SIGMA = 3.0, 2.0


def normal_cvar(mu: float, sigma: float, beta: float) -> float:
    """Lower-tail CVaR of N(mu, sigma^2): mu - sigma * phi(Phi^-1(beta)) / beta."""
    return mu - sigma * UNIT.pdf(UNIT.inv_cdf(beta)) / beta


def closed_form(risk: dict) -> float:
    """The measure of N(MU, SIGMA^2)."""
    measure = risk["measure"]
    if measure == "wang":
        return MU - risk["eta"] * SIGMA
    if measure == "entropic":
        return MU - risk["eta"] * SIGMA**2 / 2.0
    if measure == "cvar":
        return normal_cvar(MU, SIGMA, risk["beta"])
    return (1.0 - risk["weight"]) * MU + risk["weight"] * normal_cvar(MU, SIGMA, risk["beta"])


def standard_error(z: np.ndarray, risk: dict) -> float:
    """The plug-in estimate's standard error: delta method (entropic) or the L-statistic's influence function, whose
    variance is Var h(Z) with h(z) = -int_z^max phi(F(t)) dt (spectral)."""
    if risk["measure"] == "entropic":
        e = np.exp(-risk["eta"] * (z - z.mean()))
        return float(e.std() / (risk["eta"] * e.mean() * math.sqrt(z.size)))
    s = np.sort(z)
    phi = spectrum(np.arange(1, z.size) / z.size, risk)
    h = np.concatenate([-np.cumsum((phi * np.diff(s))[::-1])[::-1], [0.0]])
    return float(h.std() / math.sqrt(z.size))


def reference_spectral_gradient(z, s, risk, baseline):
    """The spectral estimator written out in numpy: argsort, h by a reversed cumulative sum, then the mean of S (h - b)."""
    n = z.size
    order = np.argsort(z, kind="stable")
    phi = spectrum(np.arange(1, n) / n, risk)
    h_sorted = np.concatenate([-np.cumsum((phi * np.diff(z[order]))[::-1])[::-1], [0.0]])
    h = np.empty(n)
    h[order] = h_sorted
    if baseline:
        h = h - h.mean()
    return h @ s / n


def samples(seed: int, n: int, ties: bool) -> np.ndarray:
    """n normal samples, rounded to a coarse grid (many ties) when `ties`."""
    z = np.random.default_rng(seed).normal(1.0, 3.0, n)
    return np.round(z) if ties else z


def random_scores(seed: int, n: int, m: int = 2) -> np.ndarray:
    return np.random.default_rng(seed + 1000).normal(0.0, 1.0, (n, m))


# --- Phi and Phi^-1 --------------------------------------------------------------------------------------------------


def test_normal_quantile_matches_statistics_inv_cdf_including_the_tails():
    p = np.concatenate(
        [
            np.logspace(-300, -1, 400),
            np.linspace(0.001, 0.999, 999),
            0.5 + np.logspace(-15, -2, 60),
            0.5 - np.logspace(-15, -2, 60),
            1.0 - np.logspace(-16, -1, 200),
            [0.02425, 0.97575, 0.5],  # Acklam's region boundaries and the centre
        ]
    )
    expected = np.array([UNIT.inv_cdf(float(q)) for q in p])
    got = normal_quantile(p)
    assert got.shape == p.shape
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=0.0)
    assert normal_quantile(0.5) == 0.0
    assert np.all(np.diff(got[np.argsort(p)]) >= 0)  # monotone


def test_normal_quantile_edges_and_shapes():
    assert normal_quantile(0.0) == -np.inf
    assert normal_quantile(1.0) == np.inf
    assert np.all(np.isnan(normal_quantile([-0.1, 1.1, np.nan])))
    grid = np.array([[0.1, 0.2], [0.3, 0.4]])
    np.testing.assert_allclose(normal_quantile(grid), [[UNIT.inv_cdf(q) for q in row] for row in grid], rtol=1e-12)


def test_normal_cdf_matches_statistics_and_inverts_the_quantile():
    x = np.linspace(-3.0, 8.0, 1101)  # where NormalDist's 1 + erf is accurate
    np.testing.assert_allclose(normal_cdf(x), [UNIT.cdf(v) for v in x], rtol=1e-13)
    p = np.concatenate([np.logspace(-300, -1, 300), np.linspace(0.1, 0.9, 81)])
    x = normal_quantile(p)
    # relative accuracy in the tails: Phi's condition number there is ~x^2, so round-off of x costs up to ~x^2 eps
    assert np.all(np.abs(normal_cdf(x) - p) <= 1e-15 * (1.0 + x**2) * p)
    np.testing.assert_allclose(normal_cdf(-x), 1.0 - p, rtol=1e-15, atol=1e-16)  # the upper tail by symmetry
    assert normal_cdf(-np.inf) == 0.0 and normal_cdf(np.inf) == 1.0


# --- distortions, spectra and weights --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "risk",
    [
        {"measure": "wang", "eta": 0.5},
        {"measure": "wang", "eta": 1.5},
        {"measure": "mean_cvar", "beta": 0.25, "weight": 0.3},
        {"measure": "cvar", "beta": 0.1},
        {"measure": "neutral"},
    ],
)
def test_spectrum_is_the_derivative_of_the_distortion(risk):
    u = np.linspace(0.003, 0.997, 300)
    u = u[np.abs(u - risk.get("beta", 2.0)) > 1e-3]  # away from cvar's kink
    step = 1e-6
    slope = (distortion_at(u + step, risk) - distortion_at(u - step, risk)) / (2 * step)
    np.testing.assert_allclose(slope, spectrum(u, risk), rtol=1e-6, atol=1e-8)
    assert distortion_at(0.0, risk) == 0.0
    assert distortion_at(1.0, risk) == pytest.approx(1.0, abs=1e-15)
    assert np.all(distortion_at(u, risk) >= u - 1e-15)  # risk-averse: the lower tail is weighted up


def test_wang_distortion_closed_form():
    u = np.linspace(0.01, 0.99, 99)
    expected = [UNIT.cdf(UNIT.inv_cdf(q) + 0.75) for q in u]
    np.testing.assert_allclose(distortion_at(u, {"measure": "wang", "eta": 0.75}), expected, rtol=1e-12)
    phi = [math.exp(-0.75 * UNIT.inv_cdf(q) - 0.75**2 / 2) for q in u]
    np.testing.assert_allclose(spectrum(u, {"measure": "wang", "eta": 0.75}), phi, rtol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 7, 6000])
def test_spectral_weights_are_cached_read_only_distributions(n):
    risk = {"measure": "wang", "eta": 1.5}
    w = spectral_weights(n, risk)
    assert w.shape == (n,)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(w > 0)
    if n > 1:
        assert np.all(np.diff(w) < 0)  # phi decreases: lower samples weigh more
        assert w[0] > 1.0 / n > w[-1]
    assert spectral_weights(n, dict(risk)) is w
    with pytest.raises(ValueError):
        w[0] = 0.0
    k = np.arange(n + 1) / n
    np.testing.assert_allclose(w, np.diff(distortion_at(k, risk)), rtol=1e-9, atol=1e-15)


# --- closed forms on a large normal sample ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def normal_sample() -> np.ndarray:
    return np.random.default_rng(20240611).normal(MU, SIGMA, 400_000)


@pytest.mark.parametrize(
    "risk",
    [
        {"measure": "wang", "eta": 0.25},
        {"measure": "wang", "eta": 0.75},
        {"measure": "wang", "eta": 1.5},
        {"measure": "entropic", "eta": 0.1},
        {"measure": "entropic", "eta": 0.5},
        {"measure": "mean_cvar", "beta": 0.25, "weight": 0.3},
        {"measure": "mean_cvar", "beta": 0.1, "weight": 0.8},
        {"measure": "cvar", "beta": 0.05},
        {"measure": "cvar", "beta": 0.25},
    ],
)
def test_normal_closed_forms(normal_sample, risk):
    """Each estimate within 4 standard errors (the SE is estimated from the sample and is ~0.003-0.008)."""
    se = standard_error(normal_sample, risk)
    assert 0.0 < se < 0.01  # a tolerance that could not hide a wrong formula: measures differ by >= 0.25 here
    assert objective(normal_sample, risk) == pytest.approx(closed_form(risk), abs=4 * se)


def test_neutral_is_the_mean_and_measures_are_ordered(normal_sample):
    assert objective(normal_sample, {"measure": "neutral"}) == normal_sample.mean()
    wang = [objective(normal_sample, {"measure": "wang", "eta": eta}) for eta in (0.1, 0.5, 1.0, 2.0)]
    entropic = [objective(normal_sample, {"measure": "entropic", "eta": eta}) for eta in (0.1, 0.5, 1.0, 2.0)]
    assert np.all(np.diff(wang) < 0) and np.all(np.diff(entropic) < 0)  # more averse, lower
    assert wang[0] < normal_sample.mean() and entropic[0] < normal_sample.mean()


# --- the reference estimators, bit for bit ---------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 7, 100, 1001, 6000])
@pytest.mark.parametrize("beta", [0.05, 0.07, 0.1, 0.3, 1 / 3, 1.0])
@pytest.mark.parametrize("ties", [False, True])
def test_cvar_and_neutral_are_the_reference_functions_bit_for_bit(n, beta, ties):
    z = samples(n + int(beta * 1000), n, ties)
    s = random_scores(n, n, 3)
    risk = {"measure": "cvar", "beta": beta}
    assert objective(z, risk) == cvar(z, beta)
    assert np.array_equal(objective_gradient(z, s, risk), cvar_gradient(z, s, beta))
    assert objective(z, {"measure": "neutral", "beta": beta}) == z.mean()
    assert np.array_equal(objective_gradient(z, s, {"measure": "neutral"}), mean_gradient(z, s))
    assert np.array_equal(
        objective_gradient(z, s, {"measure": "neutral"}, baseline=False), mean_gradient(z, s, baseline=False)
    )
    mixed = {"measure": "mean_cvar", "beta": beta, "weight": 0.3}
    assert np.array_equal(objective_gradient(z, s, mixed), 0.7 * mean_gradient(z, s) + 0.3 * cvar_gradient(z, s, beta))
    assert objective(z, mixed) == 0.7 * z.mean() + 0.3 * cvar(z, beta)
    assert np.array_equal(objective_gradient(z, s, {**mixed, "weight": 0.0}), mean_gradient(z, s))
    assert np.array_equal(objective_gradient(z, s, {**mixed, "weight": 1.0}), cvar_gradient(z, s, beta))
    assert objective(z, {**mixed, "weight": 0.0}) == z.mean()
    assert objective(z, {**mixed, "weight": 1.0}) == cvar(z, beta)
    if n > 10 and beta < 1.0:  # not vacuous: the two measures' gradients differ
        assert not np.allclose(cvar_gradient(z, s, beta), mean_gradient(z, s))


def test_typed_config_objects_and_enums_are_accepted():
    z, s = samples(3, 500, False), random_scores(3, 500)
    conf = RiskConf(measure="cvar", beta=0.2)
    assert np.array_equal(objective_gradient(z, s, conf), cvar_gradient(z, s, 0.2))
    assert objective(z, conf) == cvar(z, 0.2)

    class Plain(str, Enum):  # str() is "Plain.wang": the member's value names the measure
        wang = "wang"

    @dataclass(frozen=True)
    class Node:
        measure: object
        beta: float = 0.1
        eta: float = 0.75
        weight: float = 0.5

    wang = {"measure": "wang", "eta": 0.75}
    for node in (Node(Plain.wang), Node("wang"), OmegaConf.create(wang)):
        assert objective(z, node) == objective(z, wang)
        assert np.array_equal(objective_gradient(z, s, node), objective_gradient(z, s, wang))
    spec = risk_spec(Node("mean_cvar"))
    assert spec.measure.name == "mean_cvar" and spec.params == {"weight": 0.5, "beta": 0.1}
    assert sorted(MEASURES) == sorted(["cvar", "neutral", "wang", "mean_cvar", "entropic"])


# --- the generic L-statistic and spectral gradient with CVaR's spectrum ----------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 7, 10, 333, 6000])
@pytest.mark.parametrize("beta", [0.01, 0.07, 0.1, 0.25, 1 / 3, 0.5, 0.999, 1.0])
@pytest.mark.parametrize("ties", [False, True])
def test_generic_spectral_estimators_with_cvar_spectrum_match_eq_9(n, beta, ties):
    z = samples(7 * n + int(beta * 1000), n, ties)
    s = random_scores(n, n)
    risk = {"measure": "cvar", "beta": beta}
    scale = np.abs(z).max() + 1.0
    assert l_statistic(z, risk) == pytest.approx(cvar(z, beta), rel=1e-12, abs=1e-12 * scale)
    expected = cvar_gradient(z, s, beta)
    got = spectral_gradient(z, s, risk, baseline=False)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * scale * np.abs(s).max())
    if np.sum(z < value_at_risk(z, beta)) >= 1:
        assert np.any(np.abs(expected) > 1e-3)  # not vacuous: some sample below v
    # the baseline b = mean(h) = mean((z - v) 1{z <= v}) / beta = cvar - v shifts it by -b * mean(S), no more
    shifted = expected - (cvar(z, beta) - value_at_risk(z, beta)) * s.mean(axis=0)
    np.testing.assert_allclose(spectral_gradient(z, s, risk), shifted, rtol=1e-12, atol=1e-12 * scale * np.abs(s).max())


@pytest.mark.parametrize("beta, weight", [(0.25, 0.3), (0.07, 0.9), (1.0, 0.5)])
@pytest.mark.parametrize("ties", [False, True])
def test_generic_spectral_estimators_for_mean_cvar_and_neutral(beta, weight, ties):
    """The public mean_cvar estimator, (1 - lambda) mean_gradient + lambda cvar_gradient, is the spectral one up to
    its baselines: mean_gradient centres z on its mean, cvar_gradient none (the spectral b = mean(h) shifts it by
    -(cvar - v) mean(S))."""
    z, s = samples(11, 777, ties), random_scores(11, 777)
    mixed = {"measure": "mean_cvar", "beta": beta, "weight": weight}
    scale = np.abs(z).max()
    assert l_statistic(z, mixed) == pytest.approx(objective(z, mixed), rel=1e-12, abs=1e-12 * scale)
    cvar_part = cvar_gradient(z, s, beta) - (cvar(z, beta) - value_at_risk(z, beta)) * s.mean(axis=0)
    expected = (1 - weight) * mean_gradient(z, s) + weight * cvar_part
    np.testing.assert_allclose(spectral_gradient(z, s, mixed), expected, rtol=1e-11, atol=1e-12 * scale)
    assert not np.allclose(expected, objective_gradient(z, s, mixed), rtol=1e-3)  # the baselines do differ
    assert l_statistic(z, {"measure": "neutral"}) == pytest.approx(z.mean(), rel=1e-12, abs=1e-12 * scale)
    np.testing.assert_allclose(
        spectral_gradient(z, s, {"measure": "neutral"}), mean_gradient(z, s), rtol=1e-11, atol=1e-12 * scale
    )


@pytest.mark.parametrize("eta", [0.25, 1.5])
@pytest.mark.parametrize("ties", [False, True])
def test_wang_gradient_is_the_stated_estimator(eta, ties):
    """The numba kernel against the formula written out in numpy, with and without the baseline b = mean(h)."""
    z, s = samples(5, 2345, ties), random_scores(5, 2345)
    risk = {"measure": "wang", "eta": eta}
    got = objective_gradient(z, s, risk)
    np.testing.assert_allclose(got, reference_spectral_gradient(z, s, risk, True), rtol=1e-11)
    np.testing.assert_allclose(
        spectral_gradient(z, s, risk, baseline=False), reference_spectral_gradient(z, s, risk, False), rtol=1e-11
    )
    weights = np.diff(distortion_at(np.arange(z.size + 1) / z.size, risk))
    assert objective(z, risk) == pytest.approx(np.sort(z) @ weights, rel=1e-12)
    # the tie order does not matter: permuting the sample permutes nothing in the result
    perm = np.random.default_rng(9).permutation(z.size)
    np.testing.assert_allclose(objective_gradient(z[perm], s[perm], risk), got, rtol=1e-12)


@pytest.mark.parametrize(
    "risk",
    [
        {"measure": "wang", "eta": 0.8},
        {"measure": "entropic", "eta": 0.3},
        {"measure": "mean_cvar", "beta": 0.2, "weight": 0.4},
        {"measure": "cvar", "beta": 0.2},
        {"measure": "neutral"},
    ],
)
def test_batched_rows_equal_one_row_at_a_time(risk):
    z = np.random.default_rng(4).normal(0.0, 1.0, (3, 2, 400))
    s = np.random.default_rng(5).normal(0.0, 1.0, (3, 2, 400, 2))
    rows = np.array([[objective(z[i, j], risk) for j in range(2)] for i in range(3)])
    grads = np.array([[objective_gradient(z[i, j], s[i, j], risk) for j in range(2)] for i in range(3)])
    np.testing.assert_allclose(objective(z, risk), rows, rtol=1e-13)
    np.testing.assert_allclose(objective_gradient(z, s, risk), grads, rtol=1e-12, atol=1e-15)
    assert isinstance(objective(z[0, 0], risk), float)


# --- entropic --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("eta", [0.5, 1.0, 5.0])
def test_entropic_is_finite_for_large_rewards(eta):
    z = np.where(np.arange(1000) % 4 == 0, -1e4, 1e4)  # a quarter at -1e4
    s = random_scores(2, 1000)
    value = objective(z, {"measure": "entropic", "eta": eta})
    # -(1/eta) log(e^(1e4 eta) / 4 + 3 e^(-1e4 eta) / 4) = -1e4 + log(4) / eta, up to e^(-2e4 eta)
    assert value == pytest.approx(-1e4 + math.log(4.0) / eta, rel=1e-13)
    grad = objective_gradient(z, s, {"measure": "entropic", "eta": eta})
    low = z < 0
    w = np.where(low, 1.0 / low.sum(), 0.0)  # softmax(-eta z): all the weight on the low samples
    np.testing.assert_allclose(grad, -((w - 1.0 / z.size) @ s) / eta, rtol=1e-12)
    for scaled in (z + 1e4, z - 1e4, 1e4 * np.random.default_rng(0).standard_normal(1000)):
        assert np.isfinite(objective(scaled, {"measure": "entropic", "eta": eta}))
        assert np.all(np.isfinite(objective_gradient(scaled, s, {"measure": "entropic", "eta": eta})))
    assert z.min() <= value <= z.mean()


def test_entropic_rows_of_different_scales_in_one_batch():
    """A batch mixing a row where eta |z - mean| < 1 (expm1/log1p) and one where it is large (shifted exp)."""
    z = np.stack([np.random.default_rng(1).normal(0.0, 1e-3, 300), np.random.default_rng(2).normal(0.0, 1e3, 300)])
    s = np.random.default_rng(3).normal(0.0, 1.0, (2, 300, 2))
    risk = {"measure": "entropic", "eta": 0.5}
    together = objective(z, risk)
    np.testing.assert_array_equal(objective(z[::-1], risk), together[::-1])
    for i in range(2):
        e = np.exp(-0.5 * (z[i] - z[i].min()))
        direct = z[i].min() - math.log(e.mean()) / 0.5  # fine here: no overflow after the shift by the minimum
        assert together[i] == pytest.approx(objective(z[i], risk), rel=1e-14)
        assert together[i] == pytest.approx(direct, rel=1e-12, abs=1e-14)
        w = e / e.sum()
        np.testing.assert_allclose(objective_gradient(z, s, risk)[i], -((w - 1 / 300) @ s[i]) / 0.5, rtol=1e-9)


def test_entropic_small_eta_tends_to_the_mean_without_cancellation():
    z = np.random.default_rng(3).normal(5.0, 2.0, 10_000)
    for eta in (1e-3, 1e-6, 1e-9):
        # -(1/eta) log E e^(-eta Z) = mean - eta var / 2 + O(eta^2)
        expected = z.mean() - eta * z.var() / 2
        assert objective(z, {"measure": "entropic", "eta": eta}) == pytest.approx(expected, rel=1e-12, abs=1e-5 * eta)


# --- exact enumeration: a 3x3 world with deterministic rewards --------------------------------------------------------

THETA = np.array([0.5, 0.2])
EXACT_RISKS = [
    {"measure": "wang", "eta": 0.5},
    {"measure": "wang", "eta": 1.5},
    {"measure": "mean_cvar", "beta": 0.25, "weight": 0.3},
    {"measure": "entropic", "eta": 0.2},
]


@pytest.fixture(scope="module")
def tiny():
    return world_3x3()


def outcomes_at(setup, theta):
    """The exact outcomes (z_k, p_k, d p_k / d theta) of the paper's policy with weights theta."""
    features = move_features(setup.world)
    probs = probabilities(features, np.asarray(theta, dtype=float))
    return exact_outcomes(setup, probs, scores(features, probs))


def exact_objective(setup, theta, risk) -> float:
    """rho of the exact discrete distribution: sum_k z_k [g(P_k) - g(P_(k-1))], or -(1/eta) log sum_k p_k e^(-eta z_k)."""
    z, p, _ = outcomes_at(setup, theta)
    if risk["measure"] == "entropic":
        return -math.log(np.sum(p * np.exp(-risk["eta"] * z))) / risk["eta"]
    cumulative = np.concatenate([[0.0], np.cumsum(p)[:-1], [1.0]])
    return float(z @ np.diff(distortion_at(cumulative, risk)))


def exact_gradient(setup, theta, risk) -> np.ndarray:
    """E[S h(Z)] with the exact F: h(z_k) = -sum_(j >= k) phi(P_j) (z_(j+1) - z_j) (spectral); for entropic
    h(z) = -(1/eta) e^(-eta z) / E[e^(-eta Z)]."""
    z, p, dp = outcomes_at(setup, theta)
    if risk["measure"] == "entropic":
        e = np.exp(-risk["eta"] * z)
        return -(e / np.sum(p * e)) @ dp / risk["eta"]
    phi = spectrum(np.cumsum(p)[:-1], risk)
    h = np.concatenate([-np.cumsum((phi * np.diff(z))[::-1])[::-1], [0.0]])
    return h @ dp


def central_difference(f, theta, step=1e-5) -> np.ndarray:
    """d f / d theta_j by central differences, stacked on the last axis (f may be array-valued)."""
    columns = []
    for j in range(theta.size):
        e = np.zeros_like(theta)
        e[j] = step
        columns.append((np.asarray(f(theta + e)) - np.asarray(f(theta - e))) / (2 * step))
    return np.stack(columns, axis=-1)


def test_enumeration_is_a_distribution_with_zero_mean_score(tiny):
    z, p, dp = outcomes_at(tiny, THETA)
    assert len(z) >= 5
    assert p.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(dp.sum(axis=0), 0.0, atol=1e-12)  # E[S] = 0
    np.testing.assert_allclose(dp, central_difference(lambda t: outcomes_at(tiny, t)[1], THETA), atol=1e-9)


@pytest.mark.parametrize("risk", EXACT_RISKS, ids=lambda r: f"{r['measure']}-{r.get('eta', r.get('weight'))}")
def test_exact_gradient_matches_finite_differences_of_the_exact_objective(tiny, risk):
    _, p, _ = outcomes_at(tiny, THETA)
    if "beta" in risk:  # mean_cvar's g has a kink at beta: no cumulative probability may sit on it
        assert np.min(np.abs(np.cumsum(p) - risk["beta"])) > 1e-3
    truth = central_difference(lambda t: exact_objective(tiny, t, risk), THETA)
    assert np.all(np.abs(truth) > 0.05)  # not vacuous
    np.testing.assert_allclose(exact_gradient(tiny, THETA, risk), truth, rtol=1e-6)


@pytest.fixture(scope="module")
def tiny_batch(tiny):
    return rollouts(tiny, THETA, 200_000, seed=7)


@pytest.mark.parametrize("risk", EXACT_RISKS, ids=lambda r: f"{r['measure']}-{r.get('eta', r.get('weight'))}")
def test_sample_estimator_from_kernel_episodes_matches_the_exact_gradient(tiny, tiny_batch, risk):
    """objective_gradient on 16 batches of 12,500 of the kernel's episodes: their mean within 4 standard errors of
    the exact gradient, and the objective likewise."""
    z = tiny_batch.total_reward.reshape(16, -1)
    s = tiny_batch.score.reshape(16, z.shape[1], -1)
    grads = np.array([objective_gradient(z[b], s[b], risk) for b in range(16)])
    se = grads.std(axis=0, ddof=1) / 4.0
    truth = exact_gradient(tiny, THETA, risk)
    assert np.all(se < 0.1 * np.abs(truth))  # not vacuous: the tolerance is a small fraction of the gradient
    np.testing.assert_array_less(np.abs(grads.mean(axis=0) - truth), 4 * se)
    values = np.array([objective(z[b], risk) for b in range(16)])
    assert abs(values.mean() - exact_objective(tiny, THETA, risk)) < 4 * values.std(ddof=1) / 4.0


# --- bad arguments ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "risk, message",
    [
        (
            {"measure": "variance"},
            r"risk\.measure: got 'variance'; expected a built-in measure \(cvar, neutral, wang, mean_cvar, entropic\) "
            r"or one an installed package registers in the entry-point group riskplan\.risk_measures",
        ),
        ({"measure": None}, r"risk\.measure: got None; expected a measure's name"),
        ({}, r"risk\.measure: got None"),
        ({"measure": "wang"}, r"risk\.eta: missing; measure 'wang' needs a finite eta > 0"),
        ({"measure": "wang", "eta": 0.0}, r"risk\.eta: got 0; expected a finite eta > 0"),
        ({"measure": "entropic", "eta": -1.0}, r"risk\.eta: got -1; expected a finite eta > 0"),
        ({"measure": "entropic", "eta": float("nan")}, r"risk\.eta: got nan; expected a finite eta > 0"),
        ({"measure": "wang", "eta": float("inf")}, r"risk\.eta: got inf; expected a finite eta > 0"),
        ({"measure": "wang", "eta": "big"}, r"risk\.eta: got 'big'; expected a number"),
        ({"measure": "wang", "eta": True}, r"risk\.eta: got True; expected a number"),
        ({"measure": "mean_cvar", "beta": 0.1, "weight": 1.5}, r"risk\.weight: got 1\.5; expected 0 <= weight <= 1"),
        ({"measure": "mean_cvar", "beta": 0.1, "weight": -0.1}, r"risk\.weight: got -0\.1; expected 0 <= weight <= 1"),
        ({"measure": "mean_cvar", "beta": 0.1}, r"risk\.weight: missing; measure 'mean_cvar' needs 0 <= weight <= 1"),
        ({"measure": "mean_cvar", "beta": 0.0, "weight": 0.5}, r"risk\.beta: got 0; expected 0 < beta <= 1"),
        ({"measure": "cvar", "beta": 1.5}, r"risk\.beta: got 1\.5; expected 0 < beta <= 1"),
        ({"measure": "cvar", "beta": float("nan")}, r"risk\.beta: got nan; expected 0 < beta <= 1"),
        ({"measure": "cvar"}, r"risk\.beta: missing; measure 'cvar' needs 0 < beta <= 1"),
        (
            {"measure": "wang", "eta": 0.5, "params": {"eta": 0.7}},
            r"risk\.params\.eta: the built-in measure 'wang' takes risk\.eta",
        ),
        (
            {"measure": "neutral", "params": {"gamma": 0.7}},
            r"risk\.params\.gamma: the built-in measure 'neutral' takes no",
        ),
    ],
)
def test_bad_risk_nodes_raise_bad_input_naming_the_key(risk, message):
    z, s = samples(0, 50, False), random_scores(0, 50)
    with pytest.raises(BadInput, match=message):
        objective(z, risk)
    with pytest.raises(BadInput, match=message):
        objective_gradient(z, s, risk)


def test_bad_samples_and_scores_raise_value_error():
    risk = {"measure": "wang", "eta": 0.5}
    z = samples(0, 50, False)
    for measure in ({"measure": "cvar", "beta": 0.1}, {"measure": "neutral"}, risk, {"measure": "entropic", "eta": 1}):
        with pytest.raises(ValueError, match=r"W >= 1"):
            objective(np.array([]), measure)
        with pytest.raises(ValueError, match=r"W >= 1"):
            objective(5.0, measure)
        for bad in (np.zeros(50), np.zeros((51, 2)), np.zeros((50, 2, 1)), np.zeros((2, 50, 2))):
            with pytest.raises(ValueError, match=r"scores: must have shape \(50, 'M'\)"):
                objective_gradient(z, bad, measure)
    with pytest.raises(ValueError, match=r"W >= 1"):
        spectral_weights(0, risk)
    with pytest.raises(ValueError, match="not spectral"):
        distortion_at(0.5, {"measure": "entropic", "eta": 1.0})
    with pytest.raises(ValueError, match=r"beta: must be in \(0, 1\]"):
        tail_count(0.0, 10)


@pytest.mark.parametrize("risk", [*EXACT_RISKS, {"measure": "cvar", "beta": 0.1}, {"measure": "neutral"}])
def test_objective_and_gradient_together_are_the_two_calls_bit_for_bit(risk):
    z = np.random.default_rng(5).normal(100.0, 30.0, (3, 2001)).round(1)  # rounded: ties among the samples
    scores = np.random.default_rng(6).normal(size=(3, 2001, 2))
    value, gradient = objective_and_gradient(z, scores, risk)
    np.testing.assert_array_equal(value, objective(z, risk))
    np.testing.assert_array_equal(gradient, objective_gradient(z, scores, risk))


# --- every registered measure: the registry's own tests (a new measure needs no new test code) -----------------------

CASES = measure_cases()
SPECTRAL_CASES = measure_cases(spectral_only=True)


@pytest.fixture(scope="module")
def unit_normal_sample() -> np.ndarray:
    return np.random.default_rng(20250101).normal(MU, 1.0, 400_000)


@pytest.mark.parametrize("risk", CASES)
def test_every_measure_estimates_its_closed_form_on_a_normal(unit_normal_sample, risk):
    """The plug-in estimate within 4 bootstrap standard errors (each measure's own resampling) of `of_normal`."""
    measure, params = risk_spec(risk)
    expected = measure.of_normal(MU, 1.0, params)
    if expected is None:
        pytest.skip(f"{measure.name} has no closed form on a normal")
    resampled = np.empty(200)
    measure.bootstrap(np.sort(unit_normal_sample), params, np.uint64(2024), resampled)
    se = resampled.std()
    assert 0.0 < se < 0.01  # a tolerance that could not hide a wrong formula
    assert measure.objective(unit_normal_sample, params) == pytest.approx(expected, abs=4 * se)
    assert objective(unit_normal_sample, risk) == measure.objective(unit_normal_sample, params)


@pytest.mark.parametrize("risk", CASES)
def test_every_measures_rows_bootstrap_alone_and_each_resample_is_the_measure_of_its_draws(risk):
    """bootstrap_rows (a team's terms in one call) gives each row what it gives that row alone, bit for bit, and
    resample b's value is the measure of the sample drawn with resample_counts(key, b)."""
    measure, params = risk_spec(risk)
    rows = np.sort(np.random.default_rng(8).normal(100.0, 30.0, (3, 3001)).round(1), axis=1)  # with ties
    key = np.uint64(77)
    together = np.empty((3, 40))
    measure.bootstrap_rows(rows, [params] * 3, key, together)
    for row, values in zip(rows, together):
        alone = np.empty(40)
        measure.bootstrap(row.copy(), params, key, alone)
        np.testing.assert_array_equal(values, alone)
        for b in range(5):
            drawn = np.repeat(row, resample_counts(key, b, row.size))
            assert values[b] == pytest.approx(measure.objective(drawn, params), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("risk", SPECTRAL_CASES)
def test_a_distortion_bootstrap_that_stops_where_its_table_turns_flat_gives_the_whole_sums(risk):
    """_bootstrap_distorted stops a row's sum once the cumulative count reaches the table's flat part (_flat_from:
    CVaR_beta's g from beta n on): every term it skips is z * 0.0, so the resamples equal the whole sums bit for bit.
    The flat part is where the table first equals its last value and stays there."""
    measure, params = risk_spec(risk)
    n = 2001
    rows = np.sort(np.random.default_rng(5).normal(-20.0, 30.0, (2, n)), axis=1)  # negative z: its z * 0.0 is -0.0
    table = measure.distortion(np.arange(n + 1) / n, params)
    flat = _flat_from(table)
    assert np.all(table[flat:] == table[-1]) and (flat == 0 or table[flat - 1] != table[-1])
    if measure.name == "cvar":
        assert flat - 1 <= params["beta"] * n <= flat
    tables = np.stack([table, table])
    stopped, whole = np.empty((2, 60)), np.empty((2, 60))
    key = np.uint64(31)
    _bootstrap_distorted(rows, tables, np.array([flat, flat]), key, stopped, 0, 60)
    _bootstrap_distorted(rows, tables, np.array([n + 1, n + 1]), key, whole, 0, 60)  # never stops early
    assert stopped.tobytes() == whole.tobytes()


@pytest.mark.parametrize("n", [1, 2, 7, 3001])
def test_the_entropic_bootstrap_sums_four_resamples_side_by_side_to_each_ones_own_sum(n):
    """_bootstrap_entropic takes the exponentials once and sums LANES resamples side by side: any split of the
    resamples into ranges (a thread's share, a group cut short at its end) gives each resample the bits it has
    alone, and that is -(1/eta) log of the mean of exp(-eta z) over its draws."""
    z = np.sort(np.random.default_rng(n).normal(100.0, 30.0, n).round(1))
    key, eta, resamples = np.uint64(5), 0.05, 23
    whole, split, alone = (np.full(resamples, np.nan) for _ in range(3))
    _bootstrap_entropic(z, eta, key, whole, 0, resamples)
    for begin, end in [(0, 3), (3, 10), (10, 11), (11, resamples)]:
        _bootstrap_entropic(z, eta, key, split, begin, end)
    for b in range(resamples):
        _bootstrap_entropic(z, eta, key, alone, b, b + 1)
    assert whole.tobytes() == split.tobytes() == alone.tobytes()
    for b in range(resamples):
        drawn = np.repeat(z, resample_counts(key, b, n))
        expected = drawn.min() - math.log(np.mean(np.exp(-eta * (drawn - drawn.min())))) / eta
        assert whole[b] == pytest.approx(expected, rel=1e-12) and whole[b] >= drawn.min() - 1e-9


@pytest.mark.parametrize("risk", SPECTRAL_CASES)
def test_every_spectral_measure_is_its_distortion(risk):
    """g is a distortion (g(0) = 0, g(1) = 1, increasing), phi its derivative, the closed form on a normal the
    quantile integral int F^-1 dg, and the L-statistic's weights the increments of g."""
    measure, params = risk_spec(risk)
    u = np.linspace(0.003, 0.997, 300)
    u = u[np.abs(u - params.get("beta", 2.0)) > 1e-3]  # away from a CVaR kink
    g = measure.distortion(u, params)
    assert measure.distortion(np.array([0.0]), params)[0] == 0.0
    assert measure.distortion(np.array([1.0]), params)[0] == pytest.approx(1.0, abs=1e-15)
    assert np.all(np.diff(g) >= 0) and g[-1] > g[0]
    step = 1e-6
    slope = (measure.distortion(u + step, params) - measure.distortion(u - step, params)) / (2 * step)
    np.testing.assert_allclose(slope, measure.spectrum(u, params), rtol=1e-5, atol=1e-8)
    quantile_integral = Spectral.of_normal(measure, MU, SIGMA, params)
    assert measure.of_normal(MU, SIGMA, params) == pytest.approx(quantile_integral, abs=1e-6)
    n = 1000
    weights = spectral_weights(n, risk)
    np.testing.assert_allclose(weights, np.diff(measure.distortion(np.arange(n + 1) / n, params)), atol=1e-15)
    assert weights.sum() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("risk", CASES)
def test_every_measure_gives_the_same_numbers_together_batched_and_by_node(risk):
    """objective_and_gradient is the two calls bit for bit; rows of a batch are the rows one at a time; the
    measure's methods are what a risk node names."""
    measure, params = risk_spec(risk)
    z = np.random.default_rng(5).normal(100.0, 30.0, (3, 2001)).round(1)  # rounded: ties among the samples
    s = np.random.default_rng(6).normal(size=(3, 2001, 2))
    value, gradient = measure.objective_and_gradient(z, s, params)
    np.testing.assert_array_equal(value, measure.objective(z, params))
    np.testing.assert_array_equal(gradient, measure.gradient(z, s, params))
    np.testing.assert_array_equal(value, objective(z, risk))
    np.testing.assert_array_equal(gradient, objective_gradient(z, s, risk))
    rows = [measure.objective(z[i], params) for i in range(3)]
    np.testing.assert_allclose(value, rows, rtol=1e-13)
    np.testing.assert_allclose(gradient, [measure.gradient(z[i], s[i], params) for i in range(3)], rtol=1e-12)
    assert isinstance(rows[0], float)


@pytest.mark.parametrize("risk", CASES)
def test_every_measure_checks_its_parameters_and_names_itself(risk):
    measure, params = risk_spec(risk)
    assert measure.check(dict(params)) == params
    assert not measure.built_in or lookup(measure.name) is measure  # the tests' own distortions are not registered
    label = measure.label(params)
    assert label and "\n" not in label
    for p in measure.parameters:
        key = measure.key(p.name)
        outside = (p.low - 1.0 if p.low_closed else p.low, p.high + 1.0 if p.high_closed else p.high)
        for bad in (*outside, math.nan, "x"):
            given = {**params, p.name: bad}
            with pytest.raises(BadInput, match=rf"^{re.escape(key)}: got .*; expected"):
                measure.check(given)
        assert f"{params[p.name]:g}" in label
    with pytest.raises(BadInput, match=r"unknown parameter"):
        measure.check({**params, "nonsense": 1.0})


def test_a_distortion_is_checked_when_its_parameters_are():
    """G(0) = 0, G(1) = 1 and G increasing, with the given parameters; the problem in one line naming the key."""
    shifted = distortion("shifted", lambda u, c: u + c, c=(-1.0, 1.0))
    assert shifted.check({"c": 0.0}) == {"c": 0.0}
    with pytest.raises(
        BadInput, match=r"^risk\.params: shifted's G\(u, c=0\.5\) gives G\(0\) = 0\.5 and G\(1\) = 1\.5"
    ):
        shifted.check({"c": 0.5})
    falling = distortion("falling", lambda u, a: u + a * np.sin(2 * np.pi * u), a=(0.0, 1.0))
    with pytest.raises(BadInput, match=r"gives a G that decreases"):
        falling.check({"a": 0.5})
    infinite = distortion("infinite", lambda u, a: u / (a - 0.9) * (a - 0.9), a=(0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"), pytest.raises(BadInput, match=r"values that are not finite"):
        infinite.check({"a": 0.9})

    def lookup_table(u, a):
        raise KeyError(a)

    broken = distortion("broken", lookup_table, a=(0.0, 1.0))
    with pytest.raises(BadInput, match=r"^risk\.params: broken's G\(u, a=0\.25\) raised KeyError: 0\.25$"):
        broken.check({"a": 0.25})
    with pytest.raises(ValueError, match=r"letters, digits and underscores"):
        distortion("two words", lambda u: u)
    with pytest.raises(TypeError, match=r"the range of gamma is \(low, high\)"):
        distortion("bad", lambda u, gamma: u**gamma, gamma=0.5)
    with pytest.raises(ValueError, match=r"low < high"):
        distortion("bad", lambda u, gamma: u**gamma, gamma=(1, 0))


def test_the_built_in_measures_and_nothing_else_are_found_without_packages():
    assert MEASURES == ("cvar", "neutral", "wang", "mean_cvar", "entropic")
    assert all(lookup(name).name == name and lookup(name).built_in for name in MEASURES)
    with pytest.raises(BadInput, match=r"^team\.risk\.2\.measure: got 'nonexistent'; expected a built-in measure"):
        risk_spec({"measure": "nonexistent"}, "team.risk.2")
