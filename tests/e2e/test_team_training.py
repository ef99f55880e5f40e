"""Whole team runs: the order of consensus and gradient steps, rounds of mixing per iteration, a team of one, and
per-robot start cells."""

from __future__ import annotations

import numpy as np
import pytest
from support import TINY

from riskplan import compose, train
from riskplan.engine.team.convergence import second_largest_eigenvalue_modulus
from riskplan.run.build import build_setup

pytestmark = pytest.mark.slow

# 40 iterations of 1000 samples: long enough for the contraction and the gradient-noise floor to show
CENTRAL = [*TINY, "train.iterations=40", "train.samples=1000"]
TEAM = ["experiment=paper_team", *CENTRAL]


def final_error(tmp_path, *overrides) -> float:
    run = train(compose([*TEAM, *overrides]), tmp_path / "_".join(overrides))
    return float(run.metrics[run.metrics.robot == -1].consensus_error.iloc[-1])


def test_adapt_then_combine_rounds_shrink_disagreement_geometrically(tmp_path):
    slem = second_largest_eigenvalue_modulus(build_setup(compose(TEAM)).network.weights[..., 0])
    one = final_error(tmp_path, "team.order=adapt_then_combine", "team.consensus_rounds=1")
    four = final_error(tmp_path, "team.order=adapt_then_combine", "team.consensus_rounds=4")
    assert slem == pytest.approx(2 / 3)
    assert four < one * slem**3 * 2  # three more contractions by about the SLEM each


def test_combine_then_adapt_keeps_a_gradient_noise_floor(tmp_path):
    """Eq. (14) mixes before the own gradient step: disagreement cannot fall below eps * |Delta_i - Delta_j|."""
    one = final_error(tmp_path, "team.consensus_rounds=1")
    eight = final_error(tmp_path, "team.consensus_rounds=8")
    assert eight > 0.3 * one


def test_a_team_of_one_equals_a_centralized_run(tmp_path):
    a = train(compose(CENTRAL), tmp_path / "single")
    b = train(compose([*CENTRAL, "team.graph=ring", "team.consensus_rounds=3"]), tmp_path / "ring_of_one")
    np.testing.assert_array_equal(a.metrics.theta_0, b.metrics.theta_0)
    np.testing.assert_array_equal(a.eval.total_reward, b.eval.total_reward)


def test_per_robot_start_cells(tmp_path):
    run = train(
        compose([*TEAM, "train.paths=2", "train.iterations=2", "team.starts=[[0,0],[11,0],[0,11]]"]),
        tmp_path / "starts",
    )
    first = run.trajectories[(run.trajectories.step == 0) & (run.trajectories.robot >= 0)]
    starts = first.groupby("robot")[["x", "y"]].first()
    assert starts.loc[0].tolist() == [0, 0] and starts.loc[1].tolist() == [11, 0] and starts.loc[2].tolist() == [0, 11]
