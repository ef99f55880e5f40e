"""Batched rollouts: reproducible, independent of threads, independent streams, mobile sources."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.run.build import build_setup
from riskplan.run.compose import compose


@pytest.fixture(scope="module")
def paper():
    return build_setup(compose([]))


def run(setup, seed=0, episodes=5000, thetas=None, record=False):
    thetas = np.array([[20.0, 20.0]]) if thetas is None else thetas
    starts = np.repeat(setup.world.starts[:1], len(thetas))
    return simulate(
        setup.world,
        setup.kernel,
        thetas,
        starts,
        rng.robot_keys(seed, rng.TRAIN, 0, len(thetas)),
        episodes,
        record=record,
    )


def test_same_keys_same_numbers_whatever_the_thread_count(paper):
    default = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = run(paper)
        numba.set_num_threads(default)
        many = run(paper)
    finally:
        numba.set_num_threads(default)
    np.testing.assert_array_equal(one.total_reward, many.total_reward)
    np.testing.assert_array_equal(one.score, many.score)
    np.testing.assert_array_equal(one.steps, many.steps)


def test_different_seeds_are_independent_streams(paper):
    a, b = run(paper, seed=0), run(paper, seed=1)
    assert not np.array_equal(a.total_reward, b.total_reward)
    # same distribution: means agree within sampling error, correlation of paired draws is ~0
    assert abs(a.total_reward.mean() - b.total_reward.mean()) < 5 * a.total_reward.std() / np.sqrt(5000) * 1.5
    assert abs(np.corrcoef(a.total_reward, b.total_reward)[0, 1]) < 0.05


def test_episode_streams_do_not_depend_on_batch_size(paper):
    small, large = run(paper, episodes=100), run(paper, episodes=3000)
    np.testing.assert_array_equal(small.total_reward, large.total_reward[:100])


def test_recorded_paths_are_consistent(paper):
    batch = run(paper, episodes=50, record=True)
    cells = batch.path_cells
    moves = np.abs(np.diff(np.stack(paper.world.xy(np.where(cells >= 0, cells, 0))), axis=2)).sum(axis=0)
    alive = cells[:, 1:] >= 0
    assert np.all(moves[alive] <= 1)  # one E/W/N/S step or a stay per time step
    assert np.array_equal(alive.sum(axis=1), batch.steps)
    np.testing.assert_allclose(batch.path_rewards.sum(axis=1), batch.total_reward)
    ended = batch.source_reached >= 0
    last = cells[np.arange(50), batch.steps]
    assert np.all(np.isin(last[ended], paper.world.source_cells))


def test_policies_in_one_batch_match_separate_calls(paper):
    thetas = np.array([[20.0, 20.0], [40.0, 0.0]])
    both = run(paper, thetas=thetas, episodes=1000)
    keys = rng.robot_keys(0, rng.TRAIN, 0, 2)
    second = simulate(paper.world, paper.kernel, thetas[1:], paper.world.starts, keys[1:], 1000)
    np.testing.assert_array_equal(both.total_reward[1000:], second.total_reward)


@pytest.mark.slow  # 120,000 episodes through the online-feature path: about a second
def test_mobile_sources_follow_the_same_policy_as_static_ones():
    """A source that almost never moves takes the online-feature path but must give the static statistics."""
    static = build_setup(compose(["world.sources.1.reward=2000"]))
    mobile = build_setup(
        compose(
            [
                "world.sources.1.reward=2000",
                "world.sources.0.motion.kind=random_walk",
                "world.sources.0.motion.prob=1e-12",
            ]
        )
    )
    assert mobile.world.mobile and not static.world.mobile
    a, b = run(static, episodes=60_000), run(mobile, episodes=60_000)
    for field in ("steps", "risky_steps"):
        x, y = getattr(a, field), getattr(b, field)
        assert abs(x.mean() - y.mean()) < 5 * np.sqrt(x.var() / x.size + y.var() / y.size)
    np.testing.assert_allclose(a.score.mean(axis=0), b.score.mean(axis=0), atol=5 * a.score.std(axis=0).max() / 200)
    for j in (-1, 0, 1):
        pa, pb = np.mean(a.source_reached == j), np.mean(b.source_reached == j)
        assert abs(pa - pb) < 5 * np.sqrt(pa * (1 - pa) / 30_000) + 1e-3


def test_moving_sources_move():
    """With a source that always steps, reaching it takes a different number of steps than if it stayed."""
    still = build_setup(compose(["world.sources.0.position=[2,0]", "world.sources.1.position=[10,10]"]))
    walking = build_setup(
        compose(
            [
                "world.sources.0.position=[2,0]",
                "world.sources.1.position=[10,10]",
                "world.sources.0.motion.kind=random_walk",
                "world.sources.0.motion.prob=1.0",
            ]
        )
    )
    theta = np.array([[60.0, 0.0]])
    a, b = run(still, thetas=theta, episodes=20_000), run(walking, thetas=theta, episodes=20_000)
    assert np.mean(a.source_reached == 0) > 0.95
    assert abs(a.steps.mean() - b.steps.mean()) > 0.5
