"""Reachability, checked when a run is built (riskplan.run.build): a static source that no start reaches within the
horizon is one line naming the source, its distance and the horizon; `riskplan check` and `riskplan train` print
each source's fewest moves from each start and the share of theta0's episodes that reach it, with a warning when
that share is under 1%."""

from __future__ import annotations

import warnings

import pytest
from support import TINY, bad_input, setup_of
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.run.build import REACH_EPISODES, initial_shares, reach_lines

runner = CliRunner()


@pytest.mark.slow  # builds three worlds: about 2 s
def test_a_source_beyond_the_horizon_is_bad_input():
    # (11, 10) is 21 moves from the start (0, 0), one more than the horizon's 20
    err = bad_input("world.sources.0.position=[11,10]")
    assert err.where == "world.sources.0.position"
    assert err.problem == (
        "'safe' at (11, 10) is 21 moves from the nearest start, beyond world.horizon=20: no episode can reach it; "
        "move it or the start nearer, or lengthen world.horizon"
    )
    setup_of("world.sources.0.position=[11,10]", "world.horizon=21")  # exactly the horizon is reachable
    # a wall's detour counts: round the top of x = 6 (gap at y = 11), 28 moves
    wall = "world.obstacles=[" + ",".join(f"[6,{y}]" for y in range(11)) + "]"
    assert "'safe' at (9, 3) is 28 moves from the nearest start" in bad_input(wall).problem


def test_one_start_within_reach_is_enough_and_a_random_walk_is_not_refused():
    # robot 1 starts 21 moves from 'safe', robot 0 12: the team reaches it
    team = setup_of("team.robots=2", "team.starts=[[0,0],[0,11]]", "world.sources.0.position=[9,1]")
    lines = reach_lines(team)
    assert lines[0] == "reach from the starts (0, 0), (0, 11) within horizon K=20:"
    assert lines[1].startswith("  source 0 'safe': 10 moves, 19 moves;")
    # a random walk 21 moves away may walk nearer: measured from its start cell, and not refused
    walk = ["world.sources.0.position=[11,10]", "world.sources.0.motion.kind=random_walk"]
    mobile = setup_of(*walk, "world.sources.0.motion.prob=0.5")
    with warnings.catch_warnings(record=True):
        assert reach_lines(mobile)[1].startswith("  source 0 'safe': 21 moves (a random walk: from its start cell);")


def test_the_shares_of_theta0_episodes_that_reach_each_source():
    # a uniform policy (theta0 = 0) and one move: E reaches (1, 0) and N reaches (0, 1), each with probability 1/5
    setup = setup_of(
        "world.horizon=1", "world.sources.0.position=[1,0]", "world.sources.1.position=[0,1]", "train.theta0=[0,0]"
    )
    shares = initial_shares(setup)
    spread = 5 * (0.2 * 0.8 / REACH_EPISODES) ** 0.5
    assert shares.shape == (2,) and abs(shares[0] - 0.2) < spread and abs(shares[1] - 0.2) < spread
    # a strong pull to 'safe' reaches it almost always
    assert initial_shares(setup_of("train.theta0=[60,0]"))[0] > 0.95


def test_a_source_theta0_rarely_reaches_gets_one_warning_saying_what_to_change():
    with pytest.warns(UserWarning) as caught:
        lines = reach_lines(setup_of("train.theta0=[0,0]"))  # the uniform policy: 12 moves in 20 is rare
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2 and all("\n" not in m for m in messages)
    assert messages[0].startswith("source 0 'safe' is reached by 0.0% of the initial policy's episodes (under 1%")
    assert (
        "train.theta0" in messages[0] and "world.sources.0.covariance" in messages[0] and "world.horizon" in messages[0]
    )
    assert "theta0's episodes reach it in 0.0%" in lines[1]


def test_a_policy_that_sees_no_signal_is_not_told_to_weigh_one():
    """Without signals in policy.features, theta0 holds no source's weight and a wider signal changes nothing."""
    with pytest.warns(UserWarning) as caught:
        reach_lines(setup_of("policy.features=[stay]", "train.theta0=[0]"))
    (first, _) = [str(w.message) for w in caught]
    assert first.endswith(
        "training will rarely see it; add signals to policy.features (the policy sees no source's signal) or "
        "lengthen world.horizon"
    )


@pytest.mark.parametrize("experiment", ["paper_single", "paper_team", "floor_plan"])
def test_every_shipped_experiment_passes_without_a_warning(experiment):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lines = reach_lines(setup_of(f"experiment={experiment}"))
    assert [line.split(";")[0] for line in lines[1:]] == ["  source 0 'safe': 12 moves", "  source 1 'risky': 12 moves"]


@pytest.mark.slow  # trains a run through the CLI
def test_train_prints_the_reach_and_an_unreachable_source_leaves_nothing(in_tmp):
    result = runner.invoke(app, ["train", *TINY])
    assert result.exit_code == 0, result.output
    assert "reach from the start (0, 0) within horizon K=20:\n  source 0 'safe': 12 moves;" in result.output
    far = runner.invoke(app, ["train", *TINY, "world.horizon=11"])
    assert far.exit_code == 2
    assert far.output.strip().splitlines() == [
        "error: world.sources.0.position: 'safe' at (9, 3) is 12 moves from the nearest start, beyond "
        "world.horizon=11: no episode can reach it; move it or the start nearer, or lengthen world.horizon"
    ]
    assert len(list((in_tmp / "outputs" / "runs").iterdir())) == 1  # the first run's, nothing of the second
