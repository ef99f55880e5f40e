"""policy.features beyond the paper's signals (risky, stay): the feature columns, theta0 and theta_names, the
logit bound, the score function, and the kernel's distribution of Z and its mean gradient on a world small enough
to enumerate every trajectory (static sources, and the mobile kernel's on-the-fly features).

Known answers only: hand-written feature columns and names, finite differences of log mu, an exact enumeration.
"""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf
from support import WORLD_3X3, exact_distribution, exact_mean, rollouts

from riskplan.config.schema import RiskplanConf
from riskplan.engine.policy import make_policy, move_features, probabilities, scores, tables
from riskplan.engine.step import logit_bound
from riskplan.risk import mean_gradient
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput

# A 3x2 world with an obstacle at (1, 1), height 2: cells c = 2x + y, so (0,0)=0 (0,1)=1 (1,0)=2 (1,1)=3 (2,0)=4
# (2,1)=5. Regions, first match wins: "hot" = {(1,0)} risky; "ground" = everything, not risky; "late" = {(2,1)}
# risky, but "ground" matches (2,1) first, so the only risky cell is (1,0).
LAYOUT = {
    "world": {
        "size": [3, 2],
        "start": [0, 0],
        "horizon": 3,
        "obstacles": [[1, 1]],
        "sources": [
            {"name": "far", "position": [2, 0], "covariance": [[1.0, 0.0], [0.0, 1.0]], "reward": 5.0},
            {"name": "near", "position": [0, 1], "covariance": [[2.0, 0.0], [0.0, 2.0]], "reward": 1.0},
        ],
        "regions": [
            {"name": "hot", "cells": [[1, 0]], "reward": -1.0, "risky": True},
            {"name": "ground", "rect": [0, 0, 2, 1], "reward": 0.0},
            {"name": "late", "cells": [[2, 1]], "reward": 3.0, "risky": True},
        ],
    },
    "train": {"theta0": [1.0, 1.0]},
}
E, W, STAY, N, S = range(5)
# (cell, move) whose x + u is (1, 0), worked out by hand (blocked moves stay: off the grid, or into the obstacle)
RISKY_MOVES = {(0, E), (2, STAY), (2, N), (2, S), (3, S), (4, W)}

ALL = ["signals", "risky", "stay"]
THETA = np.array([0.5, 0.2, -1.5, 0.8])  # safe, risky signal, risky_region, stay


def built(data: dict, *extra: dict):
    cfg = OmegaConf.merge(OmegaConf.structured(RiskplanConf), data, *extra)
    return build_setup(cfg)


def with_policy(features, theta0=None, **policy) -> dict:
    out = {"policy": {"features": list(features), **policy}}
    if theta0 is not None:
        out["train"] = {"theta0": [float(t) for t in theta0]}
    return out


# -- the feature columns --------------------------------------------------------------------------------------------


def test_move_features_are_the_hand_computed_columns():
    world = built(LAYOUT).world
    feats = move_features(world, features=ALL)
    assert feats.shape == (6, 5, 4)
    np.testing.assert_array_equal(feats[..., :2], world.signals()[world.next_cell])  # eq. (3), as before
    risky = np.zeros((6, 5))
    for cell, move in RISKY_MOVES:
        risky[cell, move] = 1.0
    np.testing.assert_array_equal(feats[..., 2], risky)
    stay = np.zeros((6, 5))
    stay[:, STAY] = 1.0
    np.testing.assert_array_equal(feats[..., 3], stay)
    # the order of policy.features is the order of the columns
    np.testing.assert_array_equal(move_features(world, features=["stay", "signals"]), feats[..., [3, 0, 1]])
    np.testing.assert_array_equal(move_features(world, features=["risky"]), feats[..., 2:3])


def test_the_kernel_packs_the_policy_columns():
    setup = built(LAYOUT, with_policy(["risky", "signals", "stay"]))
    expected = move_features(setup.world, features=["risky", "signals", "stay"])
    np.testing.assert_array_equal(setup.kernel.features, expected)
    assert setup.kernel.tables.signal_at == 1 and setup.kernel.tables.extra_at.tolist() == [0, 3]
    np.testing.assert_array_equal(setup.kernel.tables.extras, expected[..., [0, 3]])
    assert not setup.kernel.tables.tabular


def test_the_default_policy_is_the_papers():
    setup = build_setup(compose([]))
    np.testing.assert_array_equal(setup.kernel.features, setup.world.signals()[setup.world.next_cell])
    assert setup.theta_names == ("safe", "risky") == setup.world.source_names
    assert setup.theta0.tolist() == [20.0, 20.0]
    assert (
        setup.kernel.tables.signal_at == 0
        and setup.kernel.tables.extra_at.size == 0
        and setup.kernel.tables.extras.shape[-1] == 0
    )
    assert setup.network.n_params == 2


# -- theta0 and theta_names -----------------------------------------------------------------------------------------


@pytest.mark.slow  # four set-ups composed and built
def test_theta0_pads_with_zeros_and_names_follow_the_features():
    paper = build_setup(compose(["policy.features=[signals,risky]"]))  # the paper's theta0: [20, 20]
    assert paper.theta0.tolist() == [20.0, 20.0, 0.0]
    assert paper.theta_names == ("safe", "risky", "risky_region")
    assert paper.network.n_params == 3
    extras = build_setup(compose(["policy.features=[stay,risky]", "train.theta0=[1.5]"]))
    assert extras.theta0.tolist() == [1.5, 0.0]  # without signals, theta0's first entries are the extras
    assert extras.theta_names == ("stay", "risky_region")
    ordered = build_setup(compose(["policy.features=[risky,signals,stay]", "train.theta0=[1,2,3,4]"]))
    assert ordered.theta_names == ("risky_region", "safe", "risky", "stay")
    assert ordered.theta0.tolist() == [1.0, 2.0, 3.0, 4.0]
    empty = build_setup(compose(["train.theta0=[]"]))
    assert empty.theta0.tolist() == [0.0, 0.0]


def test_too_many_theta0_entries_are_bad_input_naming_the_parameters():
    with pytest.raises(BadInput) as err:
        build_setup(compose(["train.theta0=[1,2,3]"]))
    assert err.value.where == "train.theta0"
    assert "the policy has 2 parameters (safe, risky); give at most 2 numbers" in str(err.value)
    with pytest.raises(BadInput) as err:
        build_setup(compose(["policy.features=[signals,stay]", "train.theta0=[1,2,3,4]"]))
    assert err.value.where == "train.theta0" and "3 parameters (safe, risky, stay)" in str(err.value)
    assert "\n" not in str(err.value)


def test_theta_names_stay_unique():
    clash = {
        "world": {
            "sources": [
                {"name": "risky_region", "position": [2, 0], "covariance": [[1, 0], [0, 1]], "reward": 1.0},
                {"name": "stay", "position": [0, 2], "covariance": [[1, 0], [0, 1]], "reward": 1.0},
            ]
        }
    }
    setup = built(WORLD_3X3, clash, with_policy(ALL))
    assert setup.theta_names == ("risky_region", "stay", "feature_risky_region", "feature_stay")
    taken = {
        "world": {
            "sources": [
                {"name": "stay", "position": [2, 0], "covariance": [[1, 0], [0, 1]], "reward": 1.0},
                {"name": "feature_stay", "position": [0, 2], "covariance": [[1, 0], [0, 1]], "reward": 1.0},
            ]
        }
    }
    names = built(WORLD_3X3, taken, with_policy(["signals", "stay"])).theta_names
    assert names == ("stay", "feature_stay", "feature_stay_2")


# -- the logit bound ------------------------------------------------------------------------------------------------


def test_logit_bound_counts_the_extra_features():
    paper = build_setup(compose([]))
    thetas = np.array([[3.0, -4.0], [1.0, 1.0]])
    old = float(np.max(np.abs(thetas) @ np.abs(paper.world.source_amplitude)))  # the formula before the extras
    assert logit_bound(paper.world, thetas) == old
    assert logit_bound(paper.world, thetas, paper.policy) == old
    setup = built(LAYOUT, with_policy(ALL))
    amplitude = np.abs(setup.world.source_amplitude)
    theta = np.array([2.0, -3.0, -5.0, 7.0])
    exact = 2.0 * amplitude[0] + 3.0 * amplitude[1] + 5.0 + 7.0
    assert logit_bound(setup.world, theta, setup.policy) == pytest.approx(exact, rel=1e-15)
    logits = np.einsum("caj,j->ca", move_features(setup.world, features=ALL), theta)
    assert np.abs(logits).max() <= exact
    assert logit_bound(setup.world, theta) >= exact  # without the policy: an upper bound whatever the order


def test_theta0_whose_extra_logits_overflow_is_bad_input():
    with pytest.raises(BadInput) as err:
        build_setup(compose(["policy.features=[risky,stay]", "train.theta0=[1e308,1e308]"]))
    assert err.value.where == "train.theta0" and "overflow to infinity" in str(err.value)
    assert build_setup(compose(["policy.features=[risky,stay]", "train.theta0=[1e308,0]"])).theta0[0] == 1e308


# -- the score function ---------------------------------------------------------------------------------------------


def test_score_with_extra_features_matches_finite_differences():
    world = built(LAYOUT).world
    features = move_features(world, features=ALL)
    analytic = scores(features, probabilities(features, THETA))
    h = 1e-6
    for j in range(len(THETA)):
        step = np.zeros(len(THETA))
        step[j] = h
        numeric = (np.log(probabilities(features, THETA + step)) - np.log(probabilities(features, THETA - step))) / (
            2 * h
        )
        np.testing.assert_allclose(analytic[..., j], numeric, atol=1e-7)


def test_the_kernel_tables_with_extra_features_are_the_numpy_policy():
    world = built(LAYOUT).world
    features = move_features(world, features=ALL)
    thetas = np.array([THETA, -THETA, np.zeros(4)])
    cum, score = tables(world, thetas, features)
    probs = probabilities(features, thetas)
    np.testing.assert_allclose(np.diff(cum, prepend=0.0, axis=-1)[..., :4], probs[..., :4], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(score, scores(features, probs), rtol=1e-12, atol=1e-12)


# -- the kernel against an exact enumeration ------------------------------------------------------------------------


# "mobile": a source that almost never walks (1e-12 per step), so the distribution is the static world's, but the
# mobile kernel computes the features on the fly (`rollout_kernels._mobile_policy`, with the extras).
@pytest.fixture(scope="module", params=["static", "mobile"])
def tiny(request):
    data = OmegaConf.to_container(OmegaConf.create(WORLD_3X3))
    if request.param == "mobile":
        data["world"]["sources"][0]["motion"] = {"kind": "random_walk", "prob": 1e-12}
    setup = built(data, with_policy(ALL, THETA))
    assert setup.world.mobile == (request.param == "mobile")
    return setup


def test_the_enumeration_is_a_distribution_that_sees_the_extras(tiny):
    dist = exact_distribution(tiny, THETA)
    assert sum(dist.values()) == pytest.approx(1.0, abs=1e-12)
    plain = exact_distribution(tiny, np.append(THETA[:2], [0.0, 0.0]))
    assert max(abs(dist.get(z, 0.0) - p) for z, p in plain.items()) > 0.01  # the extra weights change the law


def test_kernel_with_extra_features_samples_the_exact_distribution(tiny):
    dist = exact_distribution(tiny, THETA)
    episodes = 400_000
    batch = rollouts(tiny, THETA, episodes)
    values, counts = np.unique(batch.total_reward, return_counts=True)
    empirical = dict(zip(values.round(9), counts / counts.sum()))
    assert set(empirical) <= {round(z, 9) for z in dist}
    for z, p in dist.items():
        sd = np.sqrt(p * (1 - p) / episodes)
        assert empirical.get(round(z, 9), 0.0) == pytest.approx(p, abs=5 * sd + 1e-6)


@pytest.mark.slow  # kernel episodes against the exact enumeration
def test_trajectory_score_with_extra_features_gives_the_exact_mean_gradient(tiny):
    h = 1e-5
    truth = np.array(
        [
            (exact_mean(tiny, THETA + h * np.eye(4)[j]) - exact_mean(tiny, THETA - h * np.eye(4)[j])) / (2 * h)
            for j in range(4)
        ]
    )
    episodes = 1_000_000
    batch = rollouts(tiny, THETA, episodes, seed=1)
    estimate = mean_gradient(batch.total_reward, batch.score)
    centred = (batch.total_reward - batch.total_reward.mean())[:, None] * batch.score
    stderr = np.std(centred, axis=0) / np.sqrt(episodes)
    np.testing.assert_array_less(np.abs(estimate - truth), 4 * stderr)


def test_make_policy_rejects_what_validation_would():
    world = built(LAYOUT).world
    with pytest.raises(ValueError):
        make_policy(world, "features", ["signals", "nearby"])
    with pytest.raises(ValueError):
        make_policy(world, "greedy")


def test_the_mobile_kernels_general_policy_is_its_signals_loop_without_extras():
    """`_mobile_policy` (any features) with the signals alone gives `_mobile_signals`' numbers (the paper's path)
    bit for bit, at every cell, for sources anywhere; with extras, the extras' columns and terms."""
    from riskplan.engine.rollout_kernels import _mobile_policy, _mobile_signals

    setup = build_setup(compose(["world.sources.0.motion.kind=random_walk", "world.sources.0.motion.prob=0.3"]))
    world, theta = setup.world, np.array([3.0, -1.5])
    extras = setup.kernel.tables.extras
    src = np.array([5, 100], dtype=np.int64)
    cum_a, feats_a, cum_b, feats_b = np.empty(5), np.empty((5, 2)), np.empty(5), np.empty((5, 2))
    for cell in range(world.cells):
        args = (cell, theta, src, world.next_cell, world.source_amplitude, world.source_precision, world.height)
        _mobile_signals(*args, cum_a, feats_a)
        _mobile_policy(*args, 0, setup.kernel.tables.extra_at, extras, cum_b, feats_b)
        assert np.array_equal(cum_a, cum_b) and np.array_equal(feats_a, feats_b)
    ordered = build_setup(compose(["policy.features=[stay,signals,risky]"]))
    k, theta = ordered.kernel.tables, np.array([0.7, 3.0, -1.5, -2.0])
    feats = np.empty((5, 4))
    columns = move_features(world, signals=world.signals(src), features=["stay", "signals", "risky"])
    for cell in range(world.cells):
        args = (cell, theta, src, world.next_cell, world.source_amplitude, world.source_precision, world.height)
        _mobile_policy(*args, k.signal_at, k.extra_at, k.extras, cum_b, feats)
        np.testing.assert_allclose(feats, columns[cell], rtol=1e-14, atol=1e-300)
        expected = np.cumsum(probabilities(columns[cell][None], theta)[0])
        np.testing.assert_allclose(cum_b[:4], expected[:4], rtol=1e-12)
