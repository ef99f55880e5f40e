"""`riskplan --help` and every command's --help."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from riskplan.cli import app

runner = CliRunner()


@pytest.mark.parametrize(
    "command", [[], ["train"], ["check"], ["bench"], ["report"], ["sweep"], ["reproduce"], ["export"]]
)
def test_help_explains_every_command(command):
    result = runner.invoke(app, [*command, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output
