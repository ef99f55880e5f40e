"""summary.json's diagnosis (riskplan.run.evaluation.diagnose): a run whose evaluation reaches no source, or whose
objective ends below the initial policy's (95% intervals apart), says so with the likely cause; θ0's evaluation
reuses the headline policy's evaluation streams without changing a number; the paper's run is not flagged."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support import TINY, setup_of
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.engine.measures.registry import risk_spec
from riskplan.run.compose import compose
from riskplan.run.evaluation import JUDGED, diagnose, evaluate, initial_objective
from riskplan.run.intervals import objective_interval
from riskplan.run.training import train_summary

# Both sources lie 12 moves from the start and the horizon is 12: reachable only along a shortest path, which a
# policy pushed away from the signals (negative weights) all but never takes.
OUT_OF_REACH = ["world.horizon=12", "train.theta0=[-20.0,-20.0]"]


def test_a_policy_that_cannot_reach_a_source_in_the_horizon_reached_no_source(tmp_path):
    summary = train_summary(compose([*TINY, *OUT_OF_REACH]), tmp_path / "run")
    assert summary["source_reached"]["none"] == 1.0
    diagnosis = summary["diagnosis"]
    assert diagnosis["degenerate"] is True
    assert [f["check"] for f in diagnosis["findings"]] == ["reached_no_source"]
    assert diagnosis["initial_objective"]["reached_none"] == 1.0  # θ0 reached none either: the world's doing
    message = diagnosis["findings"][0]["message"]
    assert "reached no source in its 200 evaluation episodes, nor did the initial policy" in message
    assert "world.horizon=12" in message and "riskplan check" in message
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["diagnosis"] == diagnosis


def test_the_closing_line_of_a_degenerate_run_says_so(in_tmp):
    with pytest.warns(UserWarning, match=r"source \d '\w+' is reached by 0\.0% of the initial policy's") as caught:
        result = CliRunner().invoke(app, ["train", *TINY, *OUT_OF_REACH, "hydra.run.dir=run"])
    assert result.exit_code == 0, result.output
    assert len(caught) == 2  # both sources, out of reach
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("warning: degenerate run: reached no source in its 200 evaluation episodes")
    assert "none 100.0% -> run" in result.stdout


def test_a_final_objective_whose_interval_lies_below_the_initial_one_is_below_initial():
    setup = setup_of()
    initial = initial_objective(setup)
    below = {"measure": "cvar", "value": initial["low"] - 50, "low": initial["low"] - 80, "high": initial["low"] - 1}
    diagnosis = diagnose(setup, below, reached_none=0.5)
    assert [f["check"] for f in diagnosis["findings"]] == ["below_initial"] and diagnosis["degenerate"]
    message = diagnosis["findings"][0]["message"]
    assert f"{below['value']:.1f} [{below['low']:.1f}, {below['high']:.1f}] against {initial['value']:.1f}" in message
    assert "train.step_size" in message
    # lower, but the intervals overlap: noise, no finding
    overlapping = {**below, "high": initial["low"] + 1}
    assert diagnose(setup, overlapping, reached_none=0.5) == {
        "degenerate": False,
        "findings": [],
        "initial_objective": initial,
    }


def test_intervals_of_too_few_evaluation_episodes_are_not_judged_apart():
    """train.eval_episodes=1: each interval is one episode's total, so two are 'apart' by chance, and a run was
    called degenerate (below the initial policy) from one episode against another."""
    setup = setup_of("train.eval_episodes=1")
    initial = initial_objective(setup)
    assert initial["episodes"] == 1 and initial["low"] == initial["high"]
    below = {"measure": "cvar", "value": initial["low"] - 50, "low": initial["low"] - 50, "high": initial["low"] - 50}
    assert diagnose(setup, below, reached_none=0.0)["findings"] == []
    judged = setup_of(f"train.eval_episodes={JUDGED}")
    initial = initial_objective(judged)
    below = {"measure": "cvar", "value": initial["low"] - 50, "low": initial["low"] - 80, "high": initial["low"] - 1}
    assert [f["check"] for f in diagnose(judged, below, reached_none=0.0)["findings"]] == ["below_initial"]


def test_a_policy_that_learned_to_reach_nothing_where_the_initial_did_is_told_apart():
    setup = setup_of()  # the paper's θ0 reaches a source in some episodes
    initial = initial_objective(setup)
    assert 0 < initial["reached_none"] < 1
    figure = {k: initial[k] for k in ("measure", "value", "low", "high")}
    (finding,) = diagnose(setup, figure, reached_none=1.0)["findings"]
    assert finding["check"] == "reached_no_source"
    assert (
        f"where the initial policy reached one in {1 - initial['reached_none']:.1%}: it learned to go"
        in (finding["message"])
    )


def test_the_initial_policy_is_judged_on_the_headline_policys_evaluation_streams():
    """θ0's figure is its measure on the first episodes evaluate would draw for the headline policy at θ0: the same
    streams, in a call of its own (so no evaluated number changes)."""
    for team in ([], ["experiment=paper_team"]):
        setup = setup_of(*team, "train.eval_episodes=300")
        evaluation = evaluate(setup, np.tile(setup.theta0, (setup.robots, 1)))
        headline = -1 if setup.team else 0
        z = evaluation["total_reward"][evaluation["robot"] == headline]
        want, _ = objective_interval(z, setup.params.risk, setup.params.train.bootstrap, setup.params.seed)
        got = initial_objective(setup)
        assert {k: got[k] for k in want} == want and got["episodes"] == 300
        reached = evaluation["source_reached"][evaluation["robot"] == headline]
        assert got["reached_none"] == float((reached < 0).mean())
        assert risk_spec(setup.params.risk).measure.name == got["measure"]


@pytest.mark.slow  # the paper's whole run (200 iterations of 6000 episodes, 100,000 evaluated)
def test_the_paper_run_is_not_flagged(tmp_path):
    summary = train_summary(compose([]), tmp_path / "run")
    assert summary["diagnosis"]["degenerate"] is False and summary["diagnosis"]["findings"] == []
    assert summary["objective"]["low"] > summary["diagnosis"]["initial_objective"]["high"]  # it learned


FAULTY = ["experiment=paper_team", "team.robots=5", "team.graph=complete", "train.eval_episodes=200"]  # 3-robust
BYZANTINE = "{robot:4,kind:byzantine,from:0,value:[-10,40]}"


@pytest.mark.parametrize(
    ("extra", "cause"),
    [
        ([f"team.faults=[{BYZANTINE}]"], "the faulty robot of team.faults (robot 4: byzantine) pulling the healthy"),
        (
            [f"team.faults=[{BYZANTINE},{{robot:2,kind:stuck,from:5}}]"],
            "the faulty robots of team.faults (robot 4: byzantine, robot 2: stuck) pulling the healthy ones through "
            "team.aggregate=mean, which resists none; team.aggregate=trimmed_mean or wmsr with team.trim=2 resists",
        ),
        (["team.faults=[{robot:4,kind:crash,from:0}]"], "too large a step size"),  # a crash sends nothing to resist
        ([f"team.faults=[{BYZANTINE}]", "team.aggregate=trimmed_mean", "team.trim=1"], "too large a step size"),
        ([], "too large a step size"),
    ],
)
def test_the_likely_cause_of_a_team_made_worse_is_its_faulty_robots_where_the_mean_takes_them_in(extra, cause):
    """The faults study's mean runs (robot 6 Byzantine) were told to lower the step size or raise the samples."""
    setup = setup_of(*FAULTY, *extra)
    initial = initial_objective(setup)
    below = {"measure": "cvar", "value": initial["low"] - 50, "low": initial["low"] - 80, "high": initial["low"] - 1}
    for reached_none, finding in ((0.5, "below_initial"), (1.0, "reached_no_source")):
        found = {f["check"]: f["message"] for f in diagnose(setup, below, reached_none)["findings"]}
        assert cause in found[finding] and ("faulty" in cause) == ("faulty" in found[finding])
