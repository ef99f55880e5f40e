"""Every `riskplan ...` line of the README's bash blocks is valid as written: the typer app parses it, and the
overrides of train, check and landscape compose and pass every check, while a sweep plans all its jobs. What each
command then does is tested under tests/commands and tests/e2e."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import click
import pytest
from typer.main import get_command

from riskplan.cli import app
from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.run.compose import compose

README = Path(__file__).resolve().parents[2] / "README.md"
COMPOSED = {"train", "check", "landscape"}  # commands whose overrides are one config


def readme_commands() -> list[list[str]]:
    """The arguments of each README line that starts with `riskplan ` inside a ```bash block (comments dropped)."""
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), re.S)
    lines = [line.strip() for block in blocks for line in block.splitlines()]
    return [shlex.split(line, comments=True)[1:] for line in lines if line.startswith("riskplan ")]


def parsed(args: list[str]) -> tuple[str, dict]:
    """The command's name and its parameters, as click parses them (nothing runs)."""
    group = get_command(app)
    context = group.make_context("riskplan", list(args))
    name, command, rest = group.resolve_command(context, [*context._protected_args, *context.args])
    return name, command.make_context(name, rest, parent=context).params


def test_the_readme_shows_every_command():
    assert {args[0] for args in readme_commands()} == set(get_command(app).commands)


@pytest.mark.parametrize("args", readme_commands(), ids=shlex.join)
@pytest.mark.slow  # 13 of the README's commands, each composed
def test_a_readme_command_is_valid_as_written(args, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        name, params = parsed(args)
    except click.UsageError as err:
        pytest.fail(f"riskplan {shlex.join(args)}: {err.format_message()}")
    overrides = list(params.get("overrides") or [])
    if name in COMPOSED:
        assert compose(overrides) is not None
    elif name == "sweep":
        plan = plan_sweep(overrides, params.get("jobs"), tmp_path / "sweep")
        assert len(plan.jobs) > 1
