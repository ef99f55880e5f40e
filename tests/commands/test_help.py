"""`riskplan --help` and every command's --help."""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from riskplan.cli import app

runner = CliRunner()
COMMANDS = [[], ["train"], ["check"], ["bench"], ["report"], ["sweep"], ["reproduce"], ["export"]]


@pytest.mark.parametrize("command", COMMANDS)
def test_help_explains_every_command(command):
    result = runner.invoke(app, [*command, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output


def _help_texts(command) -> list[str]:
    """The help a command's --help renders, as written in the source: its own and each parameter's."""
    return [command.help or "", *(getattr(param, "help", None) or "" for param in command.params)]


@pytest.mark.parametrize("command", COMMANDS)
def test_help_keeps_every_bracket(command):
    """Help texts are rich markup, where [optuna] reads as a style tag and vanishes: each bracketed word written in
    a help text (an extra of a pip install, hydra.searchpath=[file://DIR], world.size=[16,16]) shows as written."""
    group = typer.main.get_command(app)
    source = group if not command else group.commands[command[0]]
    written = " ".join(_help_texts(source)).replace("\\[", "[")  # "\[" is how a help text keeps its bracket
    words = re.findall(r"\S*\[[^\]\s]*\]\S*", written)
    shown = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "120"}).output
    assert [word for word in words if word not in shown] == []
    extras = re.findall(r"pip install '([^']*)'", written)
    assert all(re.fullmatch(r"riskplan\[\w+\]", extra) for extra in extras), extras
    if command == ["sweep"]:  # the one command whose help names an extra
        assert extras == ["riskplan[optuna]"] and "'riskplan[optuna]'" in shown


def test_the_command_list_gives_each_command_one_flowing_line():
    """Each command's summary is its docstring's first paragraph, its line breaks gone: rich markup kept them, and
    `reproduce` read "... beyond it, then the" / "report. It says ..." on a wide terminal."""
    shown = runner.invoke(app, ["--help"], env={"COLUMNS": "400"}).output
    group = typer.main.get_command(app)
    for name, command in group.commands.items():
        summary = " ".join(command.callback.__doc__.split("\n\n")[0].split())
        (line,) = [line for line in shown.splitlines() if re.match(rf"│ {name} ", line)]
        assert summary in line, (name, line)
