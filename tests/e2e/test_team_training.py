"""Distributed training: the order of consensus and gradient steps, and rounds of mixing per iteration."""

from __future__ import annotations

import numpy as np
import pytest

from riskplan import compose, train
from riskplan.engine.team.convergence import second_largest_eigenvalue_modulus
from riskplan.run.build import build_setup
from riskplan.util.errors import BadInput

FAST = [
    "experiment=paper_team",
    "train.iterations=40",
    "train.samples=1000",
    "train.eval_episodes=1000",
    "train.bootstrap=10",
    "train.paths=1",
]


def final_error(tmp_path, *overrides) -> float:
    run = train(compose([*FAST, *overrides]), tmp_path / "_".join(overrides))
    return float(run.metrics[run.metrics.robot == -1].consensus_error.iloc[-1])


def test_adapt_then_combine_rounds_shrink_disagreement_geometrically(tmp_path):
    slem = second_largest_eigenvalue_modulus(build_setup(compose(FAST)).network.weights[..., 0])
    one = final_error(tmp_path, "team.order=adapt_then_combine", "team.consensus_rounds=1")
    four = final_error(tmp_path, "team.order=adapt_then_combine", "team.consensus_rounds=4")
    assert slem == pytest.approx(2 / 3)
    assert four < one * slem**3 * 2  # three more contractions by about the SLEM each


def test_combine_then_adapt_keeps_a_gradient_noise_floor(tmp_path):
    """Eq. (14) mixes before the own gradient step: disagreement cannot fall below eps * |Delta_i - Delta_j|."""
    one = final_error(tmp_path, "team.consensus_rounds=1")
    eight = final_error(tmp_path, "team.consensus_rounds=8")
    assert eight > 0.3 * one


def test_unknown_order_is_bad_input():
    with pytest.raises(BadInput) as err:
        compose(["team.order=sideways"])
    assert err.value.where == "team.order"


def test_a_team_of_one_equals_a_centralized_run(tmp_path):
    a = train(compose(FAST[1:]), tmp_path / "single")
    b = train(compose([*FAST[1:], "team.graph=ring", "team.consensus_rounds=3"]), tmp_path / "ring_of_one")
    np.testing.assert_array_equal(a.metrics.theta_0, b.metrics.theta_0)
    np.testing.assert_array_equal(a.eval.total_reward, b.eval.total_reward)


def test_per_robot_start_cells(tmp_path):
    run = train(
        compose([*FAST[:-1], "train.paths=2", "train.iterations=2", "team.starts=[[0,0],[11,0],[0,11]]"]),
        tmp_path / "starts",
    )
    first = run.trajectories[(run.trajectories.step == 0) & (run.trajectories.robot >= 0)]
    starts = first.groupby("robot")[["x", "y"]].first()
    assert starts.loc[0].tolist() == [0, 0] and starts.loc[1].tolist() == [11, 0] and starts.loc[2].tolist() == [0, 11]


def test_starts_must_match_the_team_size():
    with pytest.raises(BadInput) as err:
        compose(["experiment=paper_team", "team.starts=[[0,0]]"])
    assert err.value.where == "team.starts"


def test_growing_sample_schedule(tmp_path):
    run = train(
        compose(
            [
                "train.iterations=4",
                "train.samples=100",
                "train.samples_growth=1.0",
                "train.eval_episodes=100",
                "train.bootstrap=5",
                "train.paths=1",
            ]
        ),
        tmp_path / "grow",
    )
    assert run.metrics.samples.tolist() == [100, 200, 300, 400]  # W_l = W (1 + l)^g
