"""Counter-based random streams (riskplan.engine.rng): a distinct key for every seed, purpose, iteration and robot,
the vectorised robot keys equal to the scalar ones, and independent episode streams for different seeds."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from riskplan import compose
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.engine.step import starts
from riskplan.run.build import build_setup


def test_stream_keys_are_distinct_for_every_seed_purpose_iteration_and_robot():
    purposes = (rng.TRAIN, rng.EVAL, rng.PATHS, rng.BOOTSTRAP, rng.LANDSCAPE)
    keys = [
        rng.stream_key(seed, purpose, iteration, robot)
        for seed, purpose, iteration, robot in itertools.product(range(20), purposes, range(40), range(4))
    ]
    assert len(set(keys)) == len(keys)
    assert len({rng.stream_key(seed) for seed in range(-1000, 1000)}) == 2000


def test_different_seeds_give_independent_episode_streams():
    setup = build_setup(compose([]))
    theta = np.tile(setup.theta0, (1, 1))
    episodes = 20_000
    rewards = {}
    for seed in (0, 1, 2):
        batch = simulate(
            setup.world, setup.kernel, theta, starts(setup)[:1], rng.robot_keys(seed, rng.TRAIN, 0, 1), episodes
        )
        rewards[seed] = batch.total_reward
    for a, b in itertools.combinations(rewards, 2):
        # Same policy, so the same distribution; independent streams: no shared draws, no correlation.
        assert not set(rewards[a]) & set(rewards[b])
        assert abs(np.corrcoef(rewards[a], rewards[b])[0, 1]) < 0.03  # 4 standard errors at n = 20000
        assert abs(np.corrcoef(rewards[a][1:], rewards[b][:-1])[0, 1]) < 0.03  # nor a shifted copy
        assert abs(rewards[a].mean() - rewards[b].mean()) < 5 * rewards[a].std() / np.sqrt(episodes / 2)


@pytest.mark.parametrize(
    "seed,purpose,iteration,robots",
    [
        (0, rng.TRAIN, 0, 1),
        (0, rng.TRAIN, 7, 1000),
        (2**63 - 1, rng.PATHS, 2**40 + 3, 50),
        (12345, rng.EVAL, 1, 3),
        (5, rng.TRAIN, 0, 0),
        (2**63 - 1, rng.TRAIN, 2**64 - 1, 5),
        (77, rng.BOOTSTRAP, 3, 4),
    ],
)
def test_robot_keys_are_the_scalar_stream_keys(seed, purpose, iteration, robots):
    keys = rng.robot_keys(seed, purpose, iteration, robots)
    expected = np.array([rng.stream_key(seed, purpose, iteration, r) for r in range(robots)], dtype=np.uint64)
    assert keys.dtype == np.uint64 and keys.shape == (robots,)
    assert np.array_equal(keys, expected)


def test_robot_keys_known_values():
    """Keys as the scalar loop gave them before robot_keys was vectorised."""
    assert rng.robot_keys(0, rng.TRAIN, 0, 3).tolist() == [
        15060180617161591093,
        17701245739403276522,
        902475832917225024,
    ]
    assert int(rng.robot_keys(2**63 - 1, rng.EVAL, 99, 5)[4]) == 7221517220371294345


@pytest.mark.parametrize("n", [1, 2, 7, 1000])  # odd n takes the unpaired draw
def test_resample_counts_are_the_streams_draws_counted_and_reused_arrays_change_nothing(n):
    """resample b's counts: the indices floor(u n / 2^32) of the 32-bit halves u of its stream's draws (the stream
    recomputed here in Python ints), the low half first; count_resample into arrays that held another resample
    gives the same counts."""
    key, b = 1234567, 5
    state, indices = rng._mix_int(key ^ rng._mix_int((b + rng.GOLDEN) & rng.MASK)), []
    while len(indices) < n:
        state = (state + rng.GOLDEN) & rng.MASK
        bits = rng._mix_int(state)
        indices += [((bits & 0xFFFFFFFF) * n) >> 32, ((bits >> 32) * n) >> 32]
    expected = np.bincount(indices[:n], minlength=n)
    counts = rng.resample_counts(np.uint64(key), b, n)
    np.testing.assert_array_equal(counts, expected)
    reused, drawn = rng.resample_counts(np.uint64(key), b + 1, n), np.full(n, 7, dtype=np.uint32)
    rng.count_resample(np.uint64(key), b, reused, drawn)
    np.testing.assert_array_equal(reused, expected)


@pytest.mark.parametrize("used", [1, 3, rng.LANES])
def test_lanes_hold_their_resamples_counts_and_sum_each_in_order(used):
    """count_lanes puts resamples first..first+used-1's counts in the first `used` rows and leaves the others as they
    were; lane_sums gives each row's sum of count * value, added in index order (a Python loop's bits)."""
    n, key, first = 257, np.uint64(41), 6
    lanes = np.full((rng.LANES, n), 7, dtype=np.int32)
    rng.count_lanes(key, first, used, lanes, np.empty(n, dtype=np.uint32))
    for lane in range(rng.LANES):
        expected = rng.resample_counts(key, first + lane, n) if lane < used else np.full(n, 7)
        np.testing.assert_array_equal(lanes[lane], expected)
    values = np.random.default_rng(used).normal(size=n) * 1e3
    for row, total in zip(lanes, rng.lane_sums(lanes, values)):
        in_order = 0.0
        for count, value in zip(row.tolist(), values.tolist()):
            in_order += count * value
        assert total == in_order
