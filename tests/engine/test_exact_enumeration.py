"""A 3x3 world, K = 3, deterministic rewards: every trajectory enumerated, so objectives are exact.

Checks the kernel's distribution of Z, the score function along whole trajectories (eq. 10), and the mean and
CVaR gradient estimators, and every registered measure's (measure_cases), against finite differences of the exact
objectives.
"""

from __future__ import annotations

import numpy as np
import pytest
from measure_cases import measure_cases
from support import exact_distribution, exact_mean, rollouts, world_3x3

from riskplan.risk import cvar_gradient, mean_gradient, risk_spec, tail_count


@pytest.fixture(scope="module")
def setup():
    return world_3x3()


def exact_cvar(setup, theta, beta) -> float:
    """Rockafellar-Uryasev CVaR at the exact beta-quantile v: v + E[(Z - v) 1{Z <= v}] / beta."""
    dist = sorted(exact_distribution(setup, theta).items())
    cum = np.cumsum([p for _, p in dist])
    v = dist[int(np.searchsorted(cum, beta - 1e-12))][0]
    return v + sum(p * (z - v) for z, p in dist if z <= v) / beta


def finite_difference(f, theta, h=1e-5) -> np.ndarray:
    theta = np.asarray(theta, dtype=float)
    grad = np.zeros_like(theta)
    for j in range(theta.size):
        step = np.zeros_like(theta)
        step[j] = h
        grad[j] = (f(theta + step) - f(theta - step)) / (2 * h)
    return grad


def test_enumeration_is_a_distribution(setup):
    dist = exact_distribution(setup, [0.5, 0.2])
    assert sum(dist.values()) == pytest.approx(1.0, abs=1e-12)


def test_kernel_samples_the_exact_distribution(setup):
    theta = [0.5, 0.2]
    dist = exact_distribution(setup, theta)
    batch = rollouts(setup, theta, 400_000)
    values, counts = np.unique(batch.total_reward, return_counts=True)
    empirical = dict(zip(values.round(9), counts / counts.sum()))
    assert set(empirical) <= {round(z, 9) for z in dist}
    for z, p in dist.items():
        sd = np.sqrt(p * (1 - p) / 400_000)
        assert empirical.get(round(z, 9), 0.0) == pytest.approx(p, abs=5 * sd + 1e-6)


def test_trajectory_score_gives_exact_mean_gradient(setup):
    """sum over paths of p(xi) z(xi) score(xi) == d E[Z] / d theta, checked via the estimator on many samples."""
    theta = np.array([0.5, 0.2])
    truth = finite_difference(lambda t: exact_mean(setup, t), theta)
    batch = rollouts(setup, theta, 1_000_000, seed=1)
    estimate = mean_gradient(batch.total_reward, batch.score)
    stderr = np.std((batch.total_reward - batch.total_reward.mean())[:, None] * batch.score, axis=0) / 1000.0
    np.testing.assert_array_less(np.abs(estimate - truth), 5 * stderr)


@pytest.mark.parametrize("beta", [0.1, 0.3])
def test_cvar_gradient_matches_exact_objective(setup, beta):
    theta = np.array([0.5, 0.2])
    truth = finite_difference(lambda t: exact_cvar(setup, t, beta), theta)
    estimates = []
    for seed in range(4):
        batch = rollouts(setup, theta, 250_000, seed=seed + 10)
        estimates.append(cvar_gradient(batch.total_reward, batch.score, beta))
    estimates = np.array(estimates)
    spread = estimates.std(axis=0, ddof=1) / 2.0 + 0.02 * np.abs(truth) + 1e-3
    np.testing.assert_array_less(np.abs(estimates.mean(axis=0) - truth), 5 * spread)
    assert np.all(np.sign(estimates.mean(axis=0)) == np.sign(truth))


def test_tail_count_on_whole_and_fractional_beta_w():
    assert tail_count(0.3, 250_000) == 75_000
    assert tail_count(0.3, 7) == 3  # 2.1 -> 3


# --- every registered measure against the exact objective ------------------------------------------------------------


@pytest.fixture(scope="module")
def episodes(setup):
    return rollouts(setup, [0.5, 0.2], 200_000, seed=7)


def exact_objective(setup, theta, measure, params) -> float:
    """The measure of the exact distribution of Z under theta (`Measure.of_distribution`)."""
    dist = sorted(exact_distribution(setup, theta).items())
    return measure.of_distribution(np.array([z for z, _ in dist]), np.array([p for _, p in dist]), params)


@pytest.mark.parametrize("risk", measure_cases())
def test_every_measures_gradient_estimate_matches_the_exact_gradient(setup, episodes, risk):
    """Each measure's estimator on 16 batches of 12,500 of the kernel's episodes: their mean within 4 standard
    errors of the finite differences of the exact objective, and the objective likewise."""
    measure, params = risk_spec(risk)
    theta = np.array([0.5, 0.2])
    if measure.of_distribution(np.array([0.0]), np.array([1.0]), params) is None:
        pytest.skip(f"{measure.name} cannot measure a discrete distribution")
    truth = finite_difference(lambda t: exact_objective(setup, t, measure, params), theta)
    assert np.linalg.norm(truth) > 0.1  # not vacuous
    z = episodes.total_reward.reshape(16, -1)
    s = episodes.score.reshape(16, z.shape[1], -1)
    grads = np.array([measure.gradient(z[b], s[b], params) for b in range(16)])
    se = grads.std(axis=0, ddof=1) / 4.0
    assert np.all(se < 0.05 * np.linalg.norm(truth))  # the tolerance is a small fraction of the gradient
    np.testing.assert_array_less(np.abs(grads.mean(axis=0) - truth), 4 * se)
    values = measure.objective(z, params)
    assert abs(values.mean() - exact_objective(setup, theta, measure, params)) < 4 * values.std(ddof=1) / 4.0
