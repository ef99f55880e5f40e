"""Softmax policy (eqs. 2-3): stability, the score function against finite differences of log mu, and the kernel's
tables against the numpy policy, whatever the thread count."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from riskplan.engine.policy import move_features, probabilities, scores, tables
from riskplan.run.build import build_setup
from riskplan.run.compose import compose


@pytest.fixture(scope="module")
def world():
    return build_setup(compose([])).world


def test_score_matches_finite_differences(world):
    features = move_features(world)
    theta = np.array([3.0, -1.5])
    analytic = scores(features, probabilities(features, theta))
    h = 1e-6
    for j in range(2):
        step = np.zeros(2)
        step[j] = h
        numeric = (np.log(probabilities(features, theta + step)) - np.log(probabilities(features, theta - step))) / (
            2 * h
        )
        np.testing.assert_allclose(analytic[..., j], numeric, atol=1e-7)


def test_probabilities_are_stable_for_huge_theta(world):
    features = move_features(world)
    probs = probabilities(features, np.array([1e8, 0.0]))
    assert np.all(np.isfinite(probs))
    np.testing.assert_allclose(probs.sum(axis=-1), 1.0)
    # a huge positive weight on the safe source makes the move with the strongest safe signal certain
    best = np.argmax(features[..., 0], axis=-1)
    chosen = np.argmax(probs, axis=-1)
    ties = np.isclose(np.sort(features[..., 0], axis=-1)[:, -1], np.sort(features[..., 0], axis=-1)[:, -2])
    assert np.all((best == chosen) | ties)


def test_blocked_moves_see_their_own_cell(world):
    features = move_features(world)
    corner = 0  # (0, 0): West and South are blocked and equal Stay
    np.testing.assert_array_equal(features[corner, 1], features[corner, 2])
    np.testing.assert_array_equal(features[corner, 4], features[corner, 2])
    signals = world.signals()
    assert signals.max() == pytest.approx(1.0)  # scale w = 2 pi sqrt(det): the peak is 1 at each source


@pytest.mark.parametrize("thetas", [[[20.0, 20.0]], [[3.0, -1.5], [0.0, 0.0], [1e8, -1e8]]])
def test_the_kernel_tables_are_the_numpy_policy_and_scores(world, thetas):
    """tables() (numba loops, what the rollouts use) against probabilities() and scores() (numpy, eqs. 2-3)."""
    thetas = np.asarray(thetas)
    cum, score = tables(world, thetas)
    features = move_features(world)
    probs = probabilities(features, thetas)
    np.testing.assert_allclose(np.diff(cum, prepend=0.0, axis=-1)[..., :4], probs[..., :4], rtol=1e-12, atol=1e-15)
    assert np.all(cum[..., 4] == 1.0) and np.all(np.diff(cum, axis=-1) >= 0)
    np.testing.assert_allclose(score, scores(features, probs), rtol=1e-12, atol=1e-12)


def test_policy_tables_do_not_depend_on_the_thread_count():
    world = build_setup(compose([])).world
    thetas = np.random.default_rng(0).normal(size=(64, world.sources)) * 10
    results = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        previous = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            results.append(tables(world, thetas))
        finally:
            numba.set_num_threads(previous)
    assert all(np.array_equal(a, b) for a, b in zip(results[0], results[1]))
    few = tables(world, thetas[:5])  # fewer than PARALLEL_POLICIES: the serial loop
    assert np.array_equal(few[0], results[0][0][:5]) and np.array_equal(few[1], results[0][1][:5])
    features = move_features(world)
    cum, score = results[0]
    np.testing.assert_allclose(np.diff(cum, axis=-1, prepend=0.0), probabilities(features, thetas), atol=1e-12)
    np.testing.assert_allclose(score, scores(features, probabilities(features, thetas)), atol=1e-12)
