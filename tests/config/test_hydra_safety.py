"""Config strings are never code (riskplan.config.hydra_safety): a callback target outside the allow-list is refused
before anything is imported or written; Hydra's own callbacks are let through."""

from __future__ import annotations

import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan.cli import app

runner = CliRunner()


def test_a_callback_target_is_never_imported_or_called(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "pwned"
    result = runner.invoke(
        app, ["train", *TINY, "+hydra.callbacks.x._target_=os.makedirs", f"+hydra.callbacks.x.name={marker}"]
    )
    assert result.exit_code == 2 and "config strings are never code" in result.stderr
    assert not marker.exists() and not (tmp_path / "outputs").exists()


@pytest.mark.slow  # a whole run through the CLI
def test_hydra_and_riskplan_classes_are_allowed(tmp_path, monkeypatch):
    """The allow-list lets Hydra's own callbacks through: the run finishes and the callback ran."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "run"
    result = runner.invoke(
        app,
        [
            "train",
            *TINY,
            f"hydra.run.dir={out}",
            "+hydra.callbacks.pickle._target_=hydra.experimental.callbacks.PickleJobInfoCallback",
        ],
    )
    assert result.exit_code == 0, result.output
    assert (out / ".hydra" / "job_return.pickle").is_file()
