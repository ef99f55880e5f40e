"""riskplan.envs' SoftmaxPolicy with policy.features beyond the signals and with policy.kind=tabular.

Its move probabilities are the engine's (known answers, cell by cell), and `run_episodes` under such a policy has
the kernel's distribution (mean total reward, moves, risky steps and the source reached, within 4 standard errors
of the difference, estimated from the two samples), with static and with walking sources.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from riskplan.engine import rng as R
from riskplan.engine.policy import move_features, probabilities, tabular_probabilities
from riskplan.engine.rollout import simulate
from riskplan.envs import SoftmaxPolicy, Worlds, make_setup, run_episodes

ALL = "policy.features=[signals,risky,stay]"
MOBILE = [
    "world.sources.0.motion.kind=random_walk",
    "world.sources.0.motion.prob=0.5",
    "world.sources.1.motion.kind=random_walk",
    "world.sources.1.motion.prob=0.3",
]
THETA = (20.0, 20.0, -2.0, -1.0)  # the paper's theta0, then risky_region and stay


def observed(setup):
    """Every cell's observation: (signals (C, 5, M), positions (C, 2))."""
    world = setup.world
    worlds = Worlds(world, np.arange(world.cells))
    return worlds.signals(), worlds.positions()


def test_features_policy_probabilities_are_the_engines():
    setup = make_setup([ALL])
    signals, positions = observed(setup)
    policy = SoftmaxPolicy(THETA, setup)
    expected = probabilities(move_features(setup.world, features=["signals", "risky", "stay"]), np.array(THETA))
    np.testing.assert_allclose(policy.probabilities(signals, positions), expected, rtol=1e-12)
    for cell in (0, 17, setup.world.cells - 1):
        np.testing.assert_allclose(policy.probabilities(signals[cell], positions[cell]), expected[cell], rtol=1e-12)
    assert policy.needs_position
    with pytest.raises(ValueError, match="position"):
        policy.probabilities(signals[0])


def test_tabular_policy_probabilities_are_the_tables():
    setup = make_setup(["policy.kind=tabular"])
    signals, positions = observed(setup)
    table = setup.theta0 + np.random.default_rng(1).normal(size=setup.theta0.size)
    policy = SoftmaxPolicy(table, setup)
    np.testing.assert_allclose(
        policy.probabilities(signals, positions), tabular_probabilities(table, setup.world.cells), rtol=1e-12
    )
    move = policy({"signals": signals[5], "position": positions[5], "step": 0}, np.random.default_rng(0))
    assert 0 <= move < 5


def test_the_papers_policy_needs_no_position():
    setup = make_setup([])
    signals, _ = observed(setup)
    plain, configured = SoftmaxPolicy((46.6, -0.8)), SoftmaxPolicy((46.6, -0.8), setup)
    assert not configured.needs_position
    np.testing.assert_array_equal(configured.probabilities(signals), plain.probabilities(signals))


def test_a_theta_of_the_wrong_length_is_refused():
    with pytest.raises(ValueError, match="theta has 2 entries; the config's features policy has 4"):
        SoftmaxPolicy((1.0, 2.0), [ALL])
    with pytest.raises(ValueError, match="tabular policy has 720"):
        run_episodes(["policy.kind=tabular"], (1.0, 2.0), 10, np.random.default_rng(0))


def se(x: np.ndarray) -> float:
    return float(np.std(x, ddof=1) / math.sqrt(x.size))


def agree(env, ker) -> None:
    """Means of the outcomes within 4 standard errors of the difference."""
    for field in ("total_reward", "steps", "risky_steps"):
        x, y = np.asarray(getattr(env, field), float), np.asarray(getattr(ker, field), float)
        assert abs(x.mean() - y.mean()) <= 4 * math.hypot(se(x), se(y)), field
    for j in (-1, 0, 1):
        x, y = (np.asarray(env.source_reached) == j).astype(float), (ker.source_reached == j).astype(float)
        assert abs(x.mean() - y.mean()) <= 4 * math.hypot(se(x), se(y)) + 1e-9, f"source {j}"


@pytest.mark.slow  # distributions of many episodes in numpy and in the kernel
@pytest.mark.parametrize("mobile", [False, True], ids=["static", "mobile"])
@pytest.mark.parametrize("kind", ["features", "tabular"])
def test_run_episodes_have_the_kernels_distribution(kind, mobile):
    overrides = [ALL if kind == "features" else "policy.kind=tabular", *(MOBILE if mobile else [])]
    setup = make_setup(overrides)
    theta = np.array(THETA) if kind == "features" else setup.theta0
    episodes = run_episodes(setup, theta, 20_000, np.random.default_rng(7))
    keys = R.robot_keys(11, R.EVAL, 0, 1)
    ker = simulate(setup.world, setup.kernel, theta[None, :], setup.world.starts[:1], keys, 200_000, scores=False)
    agree(episodes, ker)
    assert episodes.risky_steps.mean() > 0.1  # the risky region is visited: its feature is exercised


def test_the_gym_environment_runs_a_configured_policy():
    pytest.importorskip("gymnasium")
    from riskplan.envs import SensorPlanningEnv

    env = SensorPlanningEnv([ALL])
    policy, generator = SoftmaxPolicy(THETA, env.setup), np.random.default_rng(2)
    obs, info = env.reset(seed=3)
    done, steps = False, 0
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs, generator))
        done, steps = terminated or truncated, steps + 1
    assert steps == info["steps"] >= 1
