"""`riskplan report` and `export` (which collect runs the same way) on run folders that are not what they seem: a
.hydra/config.yaml edited or damaged since its run.mcap recorded the run's config (a β=0.1 run reported as β=0.3, a
seed changed past the duplicate check), one left empty by a run that never started, a run.mcap that links to a
device, an input that is a symbolic link in a loop, and a sweep's job cut short (its remedy is its sweep, not
`riskplan train --resume`). Each is skipped, or refused, in one line; a finished run's run.mcap cut short since is
reported from its tables, with a warning. run.mcap's config is read through its
summary's metadata index: a few small reads, the last config record (an extended run's) included."""

from __future__ import annotations

import importlib
import json
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest
from support import TINY, files
from typer.testing import CliRunner

from riskplan import compose, train
from riskplan.cli import app
from riskplan.run.results import find_runs, logged_config
from riskplan.util.errors import BadInput

collect_module = importlib.import_module("riskplan.experiments.reporting.collect")  # the package's collect() hides it

pytestmark = pytest.mark.slow  # two TINY runs, then reports

runner = CliRunner()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Two finished TINY runs, seeds 0 and 1."""
    root = tmp_path_factory.mktemp("collect") / "runs"
    for seed in (0, 1):
        train(compose([*TINY, f"seed={seed}"]), root / f"seed={seed}", progress=False)
    return root


@pytest.fixture
def mine(runs, tmp_path) -> Path:
    shutil.copytree(runs, tmp_path / "runs")
    return tmp_path / "runs"


def report(*args: str):
    result = runner.invoke(app, ["report", *args, "--format", "png"])
    assert "Traceback" not in result.output, result.output
    return result


def edit(run: Path, old: str, new: str) -> None:
    config = run / ".hydra" / "config.yaml"
    text = config.read_text()
    assert old in text
    config.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize(
    "old, new, key, values",
    [
        ("  beta: 0.1\n", "  beta: 0.3\n", "risk.beta", "(0.3 here, 0.1 recorded)"),
        ("seed: 0\n", "seed: 1\n", "seed", "(1 here, 0 recorded)"),
    ],
)
def test_a_config_edited_since_its_run_is_skipped_naming_the_file_and_the_key(mine, tmp_path, old, new, key, values):
    edit(mine / "seed=0", old, new)
    result = report(str(mine), "--out", str(tmp_path / "report"))
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines() == [
        f"skipped {mine / 'seed=0'}: .hydra/config.yaml: differs from the config run.mcap recorded for this run in "
        f"{key} {values}; restore it, or train a new run"
    ]  # a seed edited to repeat seed=1's is not taken for a duplicate either: the run is not used at all
    assert result.stdout.splitlines()[0] == "1 run(s) in 1 group(s), 0 landscape(s), 1 skipped; 4 figures"
    exported = runner.invoke(app, ["export", str(mine), "--to", "foxglove"])
    assert exported.exit_code == 0 and exported.stderr.splitlines() == result.stderr.splitlines()


def test_an_empty_config_says_the_run_never_started(mine, tmp_path):
    (mine / "seed=0" / ".hydra" / "config.yaml").write_text("")
    result = report(str(mine), "--out", str(tmp_path / "report"))
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines() == [
        f"skipped {mine / 'seed=0'}: .hydra/config.yaml: is empty: the run never started; remove the directory and "
        f"train again"
    ]
    (broken,) = collect_module.collect([mine / "seed=0"]).broken
    assert broken.remedy == ""  # the reason says what to do: resuming it cannot help


def test_a_run_log_that_links_to_a_device_is_named_as_one(mine, tmp_path):
    for name in ("summary.json", "run.mcap"):
        (mine / "seed=0" / name).unlink()
    os.symlink("/dev/zero", mine / "seed=0" / "run.mcap")
    result = report(str(mine), "--out", str(tmp_path / "report"))
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines() == [
        f"skipped {mine / 'seed=0'}: run.mcap: is a symbolic link to /dev/zero, a character device; a run's log is a "
        f"regular file"
    ]


def test_an_input_that_is_a_symbolic_link_in_a_loop_is_named_as_one(tmp_path):
    os.symlink(tmp_path / "loopB", tmp_path / "loopA")
    os.symlink(tmp_path / "loopA", tmp_path / "loopB")
    os.symlink(tmp_path / "gone", tmp_path / "dangling")
    with pytest.raises(BadInput) as err:
        find_runs([tmp_path / "loopA"])
    assert (
        str(err.value)
        == f"{tmp_path / 'loopA'}: is a symbolic link in a loop; give a run, sweep or reproduce directory"
    )
    with pytest.raises(BadInput) as err:
        find_runs([tmp_path / "dangling" / "run"])
    assert str(err.value) == (
        f"{tmp_path / 'dangling' / 'run'}: passes through {tmp_path / 'dangling'}, a symbolic link to "
        f"{tmp_path / 'gone'}, which does not exist; give a run, sweep or reproduce directory"
    )
    before = files(tmp_path)
    result = report(str(tmp_path / "loopA"), "--out", str(tmp_path / "report"))
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"error: {tmp_path / 'loopA'}: is a symbolic link in a loop; give a run, sweep or reproduce directory"
    ]
    assert files(tmp_path) == before


def cut_short(run: Path) -> None:
    """run.mcap as a kill mid-way leaves it: no footer, the finished tables gone."""
    log = run / "run.mcap"
    log.write_bytes(log.read_bytes()[: log.stat().st_size // 2])
    for name in ("summary.json", "metrics.parquet", "eval.parquet", "trajectories.parquet"):
        (run / name).unlink()


def test_a_sweep_job_cut_short_is_resumed_by_its_sweep_and_a_run_by_train_resume(mine):
    cut_short(mine / "seed=0")
    cut_short(mine / "seed=1")
    (mine / "seed=0" / "status.json").write_text(json.dumps({"status": "running", "config_sha": "0123"}))
    by_path = {b.path: b for b in collect_module.collect([mine]).broken}
    assert by_path[mine / "seed=0"].remedy == (
        f"let its sweep finish, or run the sweep again with hydra.sweep.dir={mine} (it resumes its jobs)"
    )
    assert by_path[mine / "seed=1"].remedy == "resume it (riskplan train --resume DIR) or let it finish"
    assert logged_config(mine / "seed=1" / "run.mcap") is None  # no footer, no index: read_log reads it whole


def test_the_config_read_from_the_log_is_its_last_record(mine):
    run = mine / "seed=0"
    assert logged_config(run / "run.mcap")["train"]["iterations"] == 3
    extended = runner.invoke(app, ["train", "--resume", str(run), "train.iterations=4"])
    assert extended.exit_code == 0, extended.output
    assert logged_config(run / "run.mcap")["train"]["iterations"] == 4  # the extension re-recorded it
    (listed,) = collect_module.collect([run]).runs
    assert listed.config["train"]["iterations"] == 4
    assert not listed.log_cut  # the extension closed its log as a first run does


def test_a_finished_runs_log_cut_short_since_is_reported_from_its_tables_with_a_warning(mine, tmp_path):
    log = mine / "seed=1" / "run.mcap"
    log.write_bytes(log.read_bytes()[:-100])  # a copy or a disk that failed: the tables are whole
    result = report(str(mine), "--out", str(tmp_path / "report"))
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines() == [
        f"warning: {log} is cut short (it lacks the end every finished log has); the run is reported from its "
        f"tables, but Foxglove cannot open the log whole"
    ]
    notes = pd.read_csv(tmp_path / "report" / "runs.csv").set_index("path").note.fillna("")
    assert notes.to_dict() == {str(mine / "seed=0"): "", str(mine / "seed=1"): "run.mcap cut short"}
