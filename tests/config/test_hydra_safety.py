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


@pytest.mark.parametrize(
    "override, key",
    [
        ("hydra.job.name=../../escaped", "hydra.job.name"),
        ("hydra.job.name=/tmp/elsewhere", "hydra.job.name"),
        ("hydra.output_subdir=../config_elsewhere", "hydra.output_subdir"),
        ("hydra.job_logging.handlers.file.filename=/tmp/elsewhere.log", "hydra.job_logging.handlers.file.filename"),
    ],
)
@pytest.mark.parametrize("command", ["train", "sweep"])
@pytest.mark.slow  # 8 commands through the CLI
def test_hydra_settings_that_name_files_stay_inside_the_run(tmp_path, monkeypatch, override, key, command):
    """A value with path syntax in Hydra's file settings would write (or break) a file outside the run's directory:
    one line naming the key, exit code 2, and nothing written anywhere."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    dir_key = "hydra.run.dir" if command == "train" else "hydra.sweep.dir"
    args = [command, *TINY, f"{dir_key}=out", override, *(["seed=0,1"] if command == "sweep" else [])]
    result = runner.invoke(app, args)
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and f"key '{key}'" in lines[0], result.output
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["work"]


def test_a_plain_job_name_names_the_runs_log(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["train", *TINY, "hydra.run.dir=run", "hydra.job.name=my-run_1"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "run" / "my-run_1.log").is_file()


@pytest.mark.parametrize(
    "value, resolver",
    [
        ("seed=${now:%S}", "now"),
        ("seed=${oc.env:RISKPLAN_TEST_SEED}", "oc.env"),
        ("world.sources.0.name=${now:%Y}", "now"),
    ],
)
@pytest.mark.parametrize("command", ["check", "sweep"])
def test_a_value_that_can_change_between_reads_is_refused(tmp_path, monkeypatch, value, resolver, command):
    """A run keeps its config's text: a value read from the clock or the environment would be another value when it
    is resumed or reported. One line naming the key and the resolver, exit code 2, nothing written."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("RISKPLAN_TEST_SEED", "3")
    extra = ["train.iterations=2,3", "hydra.sweep.dir=s"] if command == "sweep" else []
    result = runner.invoke(app, [command, *TINY, value, *extra])
    lines = result.stderr.strip().splitlines()
    key = value.split("=", 1)[0]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"key '{key}'" in lines[0] and f"${{{resolver}:...}}" in lines[0], lines[0]
    assert list(tmp_path.iterdir()) == []


def test_interpolations_of_other_keys_and_positions_in_metres_are_kept(tmp_path, monkeypatch):
    """What depends on the config alone is fine: another key's value, ${metres:...}."""
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(
        app, ["check", "experiment=floor_plan", "train.eval_episodes=${train.samples}", "world.start=${metres:1.0,1.0}"]
    )
    assert result.exit_code == 0, result.output
