"""A 3x3 world, K = 3, deterministic rewards: every trajectory enumerated, so objectives are exact.

Checks the kernel's distribution of Z, the score function along whole trajectories (eq. 10), and the mean and
CVaR gradient estimators against finite differences of the exact objectives.
"""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from riskplan.config.schema import RiskplanConf
from riskplan.engine import rng
from riskplan.engine.policy import move_features, probabilities
from riskplan.engine.rollout import simulate
from riskplan.risk import cvar_gradient, mean_gradient, tail_count
from riskplan.run.build import build_setup

WORLD_3X3 = {
    "world": {
        "size": [3, 3],
        "start": [0, 0],
        "horizon": 3,
        "stop_at_source": True,
        "sources": [
            {"position": [2, 0], "covariance": [[1.0, 0.0], [0.0, 1.0]], "reward": 10.0},
            {"position": [0, 2], "covariance": [[2.0, 0.5], [0.5, 1.0]], "reward": 4.0},
        ],
        "regions": [
            {"name": "bad", "rect": [1, 1, 1, 2], "reward": -6.0, "risky": True},
            {"name": "rest", "rect": [0, 0, 2, 2], "reward": 1.0},
        ],
    },
    "train": {"theta0": [0.5, 0.2]},
}


@pytest.fixture(scope="module")
def setup():
    cfg = OmegaConf.merge(OmegaConf.structured(RiskplanConf), WORLD_3X3)
    return build_setup(cfg)


def exact_distribution(setup, theta) -> dict[float, float]:
    """P(Z = z) by enumerating every path (episodes stop at a source)."""
    world = setup.world
    probs = probabilities(move_features(world), np.asarray(theta, dtype=float))
    sources = {int(c): j for j, c in enumerate(world.source_cells)}
    rewards = [r.params[0] for r in world.region_rewards]
    source_rewards = [r.params[0] for r in world.source_rewards]
    out: dict[float, float] = {}

    def walk(cell, k, z, p):
        if k == world.horizon:
            out[z] = out.get(z, 0.0) + p
            return
        for a in range(5):
            nxt = int(world.next_cell[cell, a])
            gain = rewards[world.region_of[nxt]]
            if nxt in sources:
                gain += source_rewards[sources[nxt]]
                out[z + gain] = out.get(z + gain, 0.0) + p * probs[cell, a]
            else:
                walk(nxt, k + 1, z + gain, p * probs[cell, a])

    walk(int(world.starts[0]), 0, 0.0, 1.0)
    return out


def exact_mean(setup, theta) -> float:
    dist = exact_distribution(setup, theta)
    return sum(z * p for z, p in dist.items())


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


def rollouts(setup, theta, episodes, seed=0):
    return simulate(
        setup.world,
        setup.kernel,
        np.array([theta]),
        setup.world.starts,
        rng.robot_keys(seed, rng.TRAIN, 0, 1),
        episodes,
    )


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
