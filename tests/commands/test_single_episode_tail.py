"""A CVaR gradient whose tail holds one episode: ceil(beta W) = 1 of train.samples W, so the tail is the worst
episode alone, its total is the VaR v, every (z - v) of eq. 9 is 0 and the gradient is exactly zero. It trained
nothing without a word (`riskplan check train.samples=5` said config OK); now check and train warn in one line, with
the fewest samples that train. Only a gradient with a CVaR tail is affected (cvar, mean_cvar's CVaR part)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from support import TINY, run_cli, train_cli
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.engine.estimators import cvar_gradient
from riskplan.run.build import build_setup
from riskplan.run.compose import compose

pytestmark = pytest.mark.slow  # many configs composed and checked: seconds in all (the quick tier stays under a minute)

runner = CliRunner()
ZERO = (
    "risk.beta=0.1 with train.samples=5: CVaR's tail holds ceil(0.1 x 5) = 1 episode, the worst, so every (z - v) of "
    "eq. 9 is 0 and the gradient is zero: theta never moves; use train.samples >= 11"
)


def all_warnings(*overrides: str) -> list[str]:
    """The warnings of building TINY plus overrides."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_setup(compose([*TINY, *overrides], validate=False))
    return [str(w.message) for w in caught]


def tail_warnings(*overrides: str) -> list[str]:
    """The tail warnings of building TINY plus overrides."""
    return [message for message in all_warnings(*overrides) if "CVaR's tail holds" in message]


def test_the_gradient_of_a_one_episode_tail_is_zero():
    """What the warning says, on the estimator itself: at W = 10 and beta = 0.1 the gradient is 0 for any sample."""
    rng = np.random.default_rng(0)
    z, scores = rng.normal(size=(50, 10)), rng.normal(size=(50, 10, 2))
    assert not cvar_gradient(z, scores, 0.1).any()
    assert cvar_gradient(rng.normal(size=(50, 11)), rng.normal(size=(50, 11, 2)), 0.1).all()  # a tail of two


def test_check_warns_in_one_line_with_the_samples_that_train(in_tmp):
    with pytest.warns(UserWarning) as caught:
        result = runner.invoke(app, ["check", "train.samples=5"])
    assert result.exit_code == 0 and "config OK" in result.stdout
    assert [str(w.message) for w in caught if "CVaR's tail" in str(w.message)] == [ZERO]


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["train.samples=10"], "ceil(0.1 x 10) = 1 episode"),  # 0.1 x 10 is 1: still one
        (["risk.beta=0.25", "train.samples=4"], "use train.samples >= 5"),
        (["risk=mean_cvar", "train.samples=5"], "and the gradient's CVaR part is zero; use train.samples >= 11"),
        (["risk=mean_cvar", "risk.weight=1", "train.samples=5"], "the gradient is zero: theta never moves;"),
        (
            ["risk.schedule.kind=linear", "train.samples=5"],
            "theta never moves (except in iterations where soft risk or train.samples_growth raise beta_l x W_l",
        ),
        (["train.samples=5", "train.samples_growth=1"], "never moves (except in iterations where soft risk"),
    ],
)
def test_a_gradient_with_a_one_episode_cvar_tail_warns(overrides, expected):
    (found,) = tail_warnings(*overrides)
    assert expected in found


@pytest.mark.parametrize(
    "overrides",
    [
        ["train.samples=11"],
        ["risk=wang", "train.samples=5"],  # an L-statistic: every episode weighs
        ["risk=entropic", "train.samples=5"],
        ["risk=neutral", "train.samples=5"],
        ["risk=mean_cvar", "risk.weight=0", "train.samples=5"],  # the mean alone: no CVaR part to lose
    ],
)
def test_other_gradients_do_not_warn(overrides):
    assert tail_warnings(*overrides) == []


def test_a_team_names_its_robots_node_and_the_samples_every_robot_needs():
    nodes = "team.risk=[{measure: cvar, beta: 0.2}, {measure: wang}, {measure: cvar, beta: 0.05}]"
    assert tail_warnings("experiment=paper_team", "team.robots=3", "train.samples=8", nodes) == [
        "team.risk.2.beta=0.05 with train.samples=8: CVaR's tail holds ceil(0.05 x 8) = 1 episode, the worst, so "
        "every (z - v) of eq. 9 is 0 and robot 2's gradient is zero (its theta moves only by consensus); use "
        "train.samples >= 21"
    ]
    every = "team.risk=[{measure: cvar, beta: 0.1}, {measure: cvar, beta: 0.05}]"
    assert tail_warnings("experiment=paper_team", "team.robots=2", "train.samples=8", every) == [
        "team.risk.0.beta=0.1 (and 1 more of team.risk's nodes) with train.samples=8: CVaR's tail holds "
        "ceil(0.1 x 8) = 1 episode, the worst, so every (z - v) of eq. 9 is 0 and every robot's gradient is zero: "
        "theta never moves; use train.samples >= 21"
    ]


@pytest.mark.slow  # riskplan train in a subprocess
def test_train_warns_once_and_its_theta_indeed_never_moves(tmp_path):
    out = tmp_path / "run"
    result = train_cli([*TINY, "train.samples=5", "train.iterations=4"], out)
    assert result.returncode == 0, result.stderr
    assert [line for line in result.stderr.splitlines() if "CVaR's tail" in line] == [f"warning: {ZERO}"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["theta_final"] == [20.0, 20.0]


ONE = (
    "train.samples=1: one episode per iteration, and every gradient compares it with the iteration's others, so it is "
    "zero and theta never moves; use train.samples >= 2"
)


@pytest.mark.parametrize("measure", ["cvar", "neutral", "entropic", "wang", "mean_cvar"])
def test_one_sample_per_iteration_warns_that_theta_never_moves(measure):
    """W = 1: the mean's baseline is the episode itself, entropic's weight less 1/W is 0, a CVaR tail of one is the
    VaR: each gradient is zero, which trained nothing without a word."""
    assert all_warnings(f"risk={measure}", "train.samples=1").count(ONE) == 1


def test_one_sample_without_the_baseline_still_moves_theta_and_is_not_warned():
    assert ONE not in all_warnings("risk=neutral", "train.samples=1", "train.baseline=false")
    assert ONE not in all_warnings("train.samples=2", "risk=neutral")


def test_bad_input_is_one_line_with_no_warning_about_the_config_before_it(tmp_path):
    """The config's warnings (a one-episode tail, too few resamples) came before the error line: two lines or more.
    Bad input is now the error alone; a config that builds still gives its warnings."""
    result = run_cli(["check", "train.samples=5", "train.bootstrap=1", "team.robots=0"], tmp_path)
    assert result.returncode == 2 and result.stderr == (
        "error: team.robots: is 0; the number of robots must be an integer >= 1\n"
    ), result.stderr
    result = run_cli(["check", "train.samples=5"], tmp_path)
    assert result.returncode == 0 and f"warning: {ZERO}" in result.stderr
