"""The benchmark's plain-Python baseline has the kernel's semantics (else its ratio would mean nothing)."""

from __future__ import annotations

import numpy as np

from riskplan import rng
from riskplan.bench import python_rollouts
from riskplan.config import compose
from riskplan.rollout import simulate
from riskplan.setup import build_setup


def test_python_baseline_matches_the_kernel_in_distribution():
    setup = build_setup(compose(["train.theta0=[40,5]"]))
    python_z, python_steps = python_rollouts(setup.world, setup.theta0, 3000, seed=1)
    batch = simulate(setup.world, setup.kernel, setup.theta0[None, :], setup.world.starts,
                     rng.robot_keys(1, rng.TRAIN, 0, 1), 100_000)
    stderr = np.sqrt(python_z.var() / python_z.size + batch.total_reward.var() / batch.total_reward.size)
    assert abs(python_z.mean() - batch.total_reward.mean()) < 5 * stderr
    assert abs(python_steps / 3000 - batch.steps.mean()) < 5 * batch.steps.std() / np.sqrt(3000)
    for q in (0.1, 0.5, 0.9):  # quantiles agree too, not only the mean
        a, b = np.quantile(python_z, q), np.quantile(batch.total_reward, q)
        assert abs(a - b) < 0.1 * batch.total_reward.std()
