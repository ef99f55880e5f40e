"""The paper's Section V claims on the default worlds, one seed (the README has the 5-seed tables)."""

from __future__ import annotations

import numpy as np
import pytest

from riskplan import compose, train
from riskplan.risk import cvar

pytestmark = pytest.mark.slow

EVAL = ["train.eval_episodes=40000", "train.bootstrap=100", "train.paths=5"]


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    root = tmp_path_factory.mktemp("paper")
    return {measure: train(compose([f"risk={measure}", *EVAL]), root / measure) for measure in ("cvar", "neutral")}


def test_cvar_policy_is_risk_averse_figs_1_2(single):
    averse, neutral = single["cvar"].eval, single["neutral"].eval
    assert cvar(averse.total_reward, 0.1) - cvar(neutral.total_reward, 0.1) >= 500
    assert (averse.risky_steps > 0).mean() < 1 / 3
    assert (neutral.risky_steps > 0).mean() > 0.9
    assert (averse.source_reached == 0).mean() > 0.8  # the safe source, not a policy that wanders
    assert neutral.total_reward.mean() > averse.total_reward.mean()  # the risk-neutral one wins on average


def test_training_curves_show_the_gap_fig_2(single):
    late = {m: r.metrics[r.metrics.iteration >= 150] for m, r in single.items()}
    assert late["cvar"].cvar.mean() > late["neutral"].cvar.mean() + 500
    assert late["neutral"]["mean"].mean() > late["cvar"]["mean"].mean()


def test_team_matches_centralized_figs_3_4(single, tmp_path):
    team = train(compose(["experiment=paper_team", *EVAL]), tmp_path / "team")
    average = team.eval[team.eval.robot == -1].total_reward
    central = single["cvar"].eval.total_reward
    assert abs(cvar(average, 0.1) - cvar(central, 0.1)) <= 0.05 * abs(cvar(central, 0.1))
    rows = team.metrics[team.metrics.robot == -1]
    error = rows.consensus_error.to_numpy()
    theta_norm = np.hypot(rows.theta_0, rows.theta_1).to_numpy()
    assert error[-1] < 0.01 * theta_norm[-1]
    assert error[-1] * 10 <= error.max()
    assert set(team.eval.robot) == {-1, 0, 1, 2}
    assert np.isnan(single["cvar"].metrics.consensus_error).all()
