"""The README's figures and file links point at files that are in the repository."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import typer

ROOT = Path(__file__).resolve().parents[1]


def test_every_image_and_relative_link_in_the_readme_exists():
    text = (ROOT / "README.md").read_text()
    targets = re.findall(r"!?\[[^\]]*\]\(([^)#\s]+)\)", text)
    local = [t for t in targets if not re.match(r"[a-z]+:", t)]
    assert any(t.startswith("docs/figures/") for t in local)  # the regenerated figures are shown
    missing = [t for t in local if not (ROOT / t).is_file()]
    assert not missing, missing


@pytest.mark.parametrize("page", ["README.md", "docs/cli.md"])
def test_the_command_table_shows_every_command_with_its_real_options(page):
    """Each row `riskplan NAME [--option ...]` of the page's command table: every command has one, its options are
    exactly the command's (no stale one, none left out) and export's --to lists exactly its targets."""
    from riskplan.cli import app
    from riskplan.experiments.export_destinations import TARGETS

    rows = dict(re.findall(r"^\| `riskplan (\w+)([^`]*)` \|", (ROOT / page).read_text(), flags=re.M))
    commands = typer.main.get_command(app).commands
    assert sorted(rows) == sorted(commands)
    for name, command in commands.items():
        options = {opt for param in command.params for opt in param.opts if opt.startswith("--")} - {"--help"}
        assert set(re.findall(r"--[a-z][a-z-]*", rows[name])) == options, name
    (targets,) = re.findall(r"--to ([\w\\|]+)", rows["export"])
    assert targets.split("\\|") == list(TARGETS)
