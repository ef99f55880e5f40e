"""Researchers' own experiment files: `--config-dir DIR` / `-cd DIR` on train, check, sweep and landscape (the
same as hydra.searchpath), and values that Hydra's grammar takes only quoted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.commands.common import with_config_dirs

runner = CliRunner()
MINE = """# @package _global_
defaults:
  - override /risk: neutral
experiment: mine
world:
  horizon: 24
train:
  iterations: 3
  samples: 200
  eval_episodes: 300
  bootstrap: 40
  paths: 2
"""


@pytest.fixture
def config_dir(tmp_path) -> Path:
    folder = tmp_path / "my configs"  # a space: the path is quoted in the override it becomes
    (folder / "experiment").mkdir(parents=True)
    (folder / "experiment" / "mine.yaml").write_text(MINE)
    return folder


def test_config_dir_becomes_a_searchpath_after_the_users_own(config_dir, tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    assert with_config_dirs(["-cd", str(config_dir), "seed=1"]) == [
        "seed=1",
        f"hydra.searchpath=['file://{config_dir}']",
    ]
    merged = with_config_dirs([f"--config-dir={config_dir}", f"hydra.searchpath=['file://{other}']"])
    assert merged == [f"hydra.searchpath=['file://{other}', 'file://{config_dir}']"]


@pytest.mark.parametrize("flag", ["-cd", "--config-dir"])
def test_check_finds_an_experiment_in_the_users_folder(config_dir, flag):
    result = runner.invoke(app, ["check", flag, str(config_dir), "experiment=mine"])
    assert result.exit_code == 0, result.output
    assert "experiment: mine" in result.stdout and "measure: neutral" in result.stdout
    assert "horizon K=24" in result.stdout


def test_train_runs_the_users_experiment(config_dir, tmp_path):
    out = tmp_path / "run"
    result = runner.invoke(app, ["train", "-cd", str(config_dir), "experiment=mine", f"hydra.run.dir={out}"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["experiment"], summary["risk"], summary["iterations"]) == ("mine", "neutral", 3)


@pytest.mark.slow
def test_sweep_runs_the_users_experiment_in_every_job(config_dir, tmp_path):
    out = tmp_path / "sweep"
    result = runner.invoke(
        app, ["sweep", "-cd", str(config_dir), "experiment=mine", "seed=0,1", f"hydra.sweep.dir={out}"]
    )
    assert result.exit_code == 0, result.output
    summaries = sorted(out.glob("*/summary.json"))
    assert len(summaries) == 2
    assert {json.loads(s.read_text())["experiment"] for s in summaries} == {"mine"}


def test_a_missing_config_dir_is_one_line_and_exit_2(tmp_path):
    result = runner.invoke(app, ["check", "-cd", str(tmp_path / "nope"), "experiment=mine"])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1 and "is not a directory" in result.stderr


def test_a_value_hydra_takes_only_quoted_names_the_characters_and_the_quoted_form_works():
    bad = runner.invoke(app, ["check", "world.sources.0.name=Quelle ☢ 源"])
    assert bad.exit_code == 2
    assert "'☢', '源'" in bad.stderr and "world.sources.0.name='Quelle ☢ 源'" in bad.stderr
    good = runner.invoke(app, ["check", "world.sources.0.name='Quelle ☢ 源'"])
    assert good.exit_code == 0 and "source 0 'Quelle ☢ 源'" in good.stdout


@pytest.mark.parametrize(
    "name",
    ["../../outside", "a/b/c", "line\nbreak", "nul\x00x", "x" * 65, ".."],
)
@pytest.mark.slow  # check and train through the CLI, per name
def test_an_experiment_name_with_path_syntax_is_one_line_and_writes_nothing(config_dir, tmp_path, monkeypatch, name):
    """`experiment:` names the run directory (outputs/runs/<time>_<experiment>): a name with path syntax would put
    the run outside outputs/ (the probe's ../../outside), or fail on a NUL with a traceback."""
    (config_dir / "experiment" / "odd.yaml").write_text(MINE.replace("experiment: mine", f"experiment: {name!r}"))
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    for command in ("check", "train"):
        result = runner.invoke(app, [command, "-cd", str(config_dir), "experiment=odd"])
        assert result.exit_code == 2, result.output
        assert result.stderr.startswith("error: experiment: got ") and result.stderr.count("\n") == 1
        assert "give a plain name of at most 64 letters, digits" in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no outputs/ and no run anywhere


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("# @package hydra\njob:\n  name: ../../evil\n", "hydra.job.name"),
        (
            "# @package _global_\nhydra:\n  job_logging:\n    handlers:\n      file:\n        filename: /tmp/evil.log\n",
            "hydra.job_logging.handlers.file.filename",
        ),
        ("# @package _global_\nhydra:\n  output_subdir: ../elsewhere\n", "hydra.output_subdir"),
    ],
)
@pytest.mark.slow  # a CLI run per config file
def test_hydra_file_settings_in_a_config_file_are_held_to_the_command_lines_rule(tmp_path, monkeypatch, text, key):
    """A `-cd` file sets Hydra's file settings as an override would: its run's log went to ../../evil.log and
    /tmp/evil.log, and its .hydra folder outside the run. Each is refused as the override is (rows 47, 248, 249)."""
    folder = tmp_path / "mine"
    (folder / "experiment").mkdir(parents=True)
    (folder / "experiment" / "odd.yaml").write_text(text)
    monkeypatch.chdir(tmp_path)
    for command in (["train", f"hydra.run.dir={tmp_path / 'run'}"], ["sweep", "seed=0,1", "hydra.sweep.dir=s"]):
        result = runner.invoke(app, [command[0], "-cd", str(folder), "experiment=odd", *command[1:]])
        assert result.exit_code == 2, result.output
        assert result.stderr.startswith(f"error: key '{key}': got ") and result.stderr.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]


@pytest.mark.slow  # four commands composing a config each: over a second
@pytest.mark.parametrize(("section", "key"), [("run", "hydra.run.dir"), ("sweep", "hydra.sweep.dir")])
def test_a_run_or_sweep_directory_set_in_a_config_file_is_refused_not_ignored(tmp_path, monkeypatch, section, key):
    """riskplan claims a fresh folder under outputs/ itself, or takes the one typed on the command line; a file's
    hydra.run.dir (even '/') or hydra.sweep.dir was silently ignored. It is refused, before anything is made, and
    the same directory typed on the command line is taken."""
    folder = tmp_path / "mine"
    (folder / "experiment").mkdir(parents=True)
    (folder / "experiment" / "odd.yaml").write_text(
        f"# @package _global_\ndefaults:\n  - paper_single\nhydra:\n  {section}:\n    dir: {tmp_path / 'chosen'}\n"
    )
    monkeypatch.chdir(tmp_path)
    expected = (
        f"error: key '{key}': got '{tmp_path / 'chosen'}' from a config file; riskplan chooses where a run or sweep "
        f"goes (a fresh folder under outputs/): drop it from the file, or give it on the command line, {key}=DIR\n"
    )
    for command in (["check"], ["train"], ["sweep", "seed=0,1"]):
        result = runner.invoke(app, [command[0], "-cd", str(folder), "experiment=odd", *command[1:]])
        assert (result.exit_code, result.stderr) == (2, expected), result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]
    typed = ["-cd", str(folder), "experiment=odd", f"{key}={tmp_path / 'chosen'}"]
    assert runner.invoke(app, ["check", *typed]).exit_code == 0


def test_landscape_evaluates_the_users_experiment(config_dir, tmp_path):
    out = tmp_path / "landscape"
    args = ["landscape", "-cd", str(config_dir), "experiment=mine", "--points", "2", "--episodes", "10"]
    result = runner.invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "summary.json").read_text())["experiment"] == "mine"
    assert "horizon: 24" in (out / ".hydra" / "config.yaml").read_text()
