"""A mistyped choice or key: its one bad-input line lists the valid ones and, when one is close, ends with "did you
mean '...'?" (difflib), for a config group's options, a key's choices (a schema Enum), an unknown key (also one
inside a list's mapping), a risk measure's name and export's --to; a value close to none of them gets no guess."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.util.errors import did_you_mean

runner = CliRunner()


@pytest.mark.parametrize(
    ("argv", "line", "closest"),
    [
        (
            ["check", "experiment=paper_sngle"],
            r"key 'experiment': no option 'paper_sngle'; available: .*",
            "paper_single",
        ),
        (["check", "risk=nutral"], r"key 'risk': no option 'nutral'; available: cvar, .*, neutral, wang", "neutral"),
        (["check", "hydra/launcher=jobib"], r"key 'hydra/launcher': no option 'jobib'; available: basic, .*", "joblib"),
        (["check", "team.backend=ry"], r"team\.backend: got 'ry'; expected one of simulated, ray", "ray"),
        (["check", "risk.schedule=linaer"], r"risk\.schedule\.kind: got 'linaer'; expected one of none, .*", "linear"),
        (
            ["check", "risk.bta=0.1"],
            r"key 'risk\.bta': unknown key 'bta'; valid keys under 'risk': measure, .*",
            "beta",
        ),
        (["check", "wrld.size=[3,3]"], r"key 'wrld': unknown key 'wrld'; valid keys under 'top level': .*", "world"),
        (
            ["check", "world.regions=[{nme:a}]"],  # OmegaConf names a list's mapping's key without the list
            r"key 'world\.regions\.0\.nme': unknown key 'nme'; valid keys under 'world\.regions': name, .*",
            "name",
        ),
        (
            ["check", "team.robots=2", "team.risk=[{measure: cvar, beta: 0.1}, {betta: 0.3}]"],  # its item's index
            r"key 'team\.risk\.1\.betta': unknown key 'betta'; valid keys under 'team\.risk': measure, .*",
            "beta",
        ),
        (["check", "risk.measure=cvr"], r"risk\.measure: got 'cvr'; expected a built-in measure \(cvar, .*\)", "cvar"),
        (
            ["export", "outputs", "--to", "mlfow"],
            r"--to: got 'mlfow'; expected one of mlflow, tensorboard, .*",
            "mlflow",
        ),
    ],
)
@pytest.mark.slow  # 11 commands through the CLI
def test_a_mistyped_choice_or_key_suggests_the_closest(argv, line, closest, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # export checks its --to before it reads anything; nothing is written anywhere
    result = runner.invoke(app, argv)
    assert result.exit_code == 2 and result.stderr.splitlines() == [result.stderr.strip()]
    assert re.fullmatch(rf"error: {line}; did you mean '{closest}'\?", result.stderr.strip()), result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (
            ["check", "risk.schedule=cosine"],
            "error: risk.schedule.kind: got 'cosine'; expected one of none, linear, exponential",
        ),
        (["check", "+train.lr=0.1"], "error: key 'train.lr': unknown key 'lr'; valid keys under 'train': iterations, "),
    ],
)
def test_a_value_close_to_no_choice_gets_no_guess(argv, line):
    result = runner.invoke(app, argv)
    assert result.exit_code == 2 and result.stderr.startswith(line) and "did you mean" not in result.stderr


def test_did_you_mean_names_the_closest_option_or_nothing():
    assert did_you_mean("paper_sngle", ["floor_plan", "paper_single", "paper_team"]) == "; did you mean 'paper_single'?"
    assert did_you_mean("bta", ["measure", "beta", "eta"]) == "; did you mean 'beta'?"  # the closer of two close
    assert did_you_mean("cosine", ["none", "linear", "exponential"]) == ""  # 'none' is 0.6 alike: not close
    assert did_you_mean("x", []) == ""
