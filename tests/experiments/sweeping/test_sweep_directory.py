"""A sweep goes on in its own directory only: re-run with the same configs it skips its finished jobs, but it never
writes over a run of another config, a run of riskplan train, files of some other kind or Hydra's .hydra folders.
Each refusal is one line, exit code 2, with every file left as it was."""

from __future__ import annotations

import json
import shutil

import pytest
from support import TINY, files
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.config.schema import CONF_DIR
from riskplan.experiments.sweep_worker import config_sha
from riskplan.run.compose import compose

pytestmark = pytest.mark.slow  # real sweeps, kept tiny
runner = CliRunner()


def sweep(*args: str):
    return runner.invoke(app, ["sweep", *TINY, *args])


def refused(result, *words: str) -> None:
    """One line on stderr, exit code 2, naming what it must."""
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert all(word in lines[0] for word in words), lines[0]


@pytest.fixture
def finished(tmp_path, monkeypatch):
    """A finished two-job sweep in tmp_path/s, and every file it wrote."""
    monkeypatch.chdir(tmp_path)
    assert sweep("seed=0,1", "hydra.sweep.dir=s").exit_code == 0
    return tmp_path / "s", files(tmp_path / "s")


def test_a_rerun_with_the_same_configs_skips_every_finished_job(finished):
    sweep_dir, before = finished
    result = sweep("seed=0,1", "hydra.sweep.dir=s")
    assert result.exit_code == 0 and "0 to run, 2 already finished" in result.stdout
    after = files(sweep_dir)
    assert {k: v for k, v in after.items() if "seed=" in k} == {k: v for k, v in before.items() if "seed=" in k}


@pytest.mark.parametrize("change", [["train.iterations=4"], ["risk.beta=0.2"]])
def test_a_rerun_with_another_config_never_writes_over_the_finished_jobs(finished, change):
    sweep_dir, before = finished
    result = sweep("seed=0,1", "hydra.sweep.dir=s", *change)
    refused(result, "s/seed=0", "holds a done run of another config", "and 1 more", "hydra.sweep.dir")
    assert files(sweep_dir) == before


def test_a_failed_job_of_another_config_is_replaced(finished):
    sweep_dir, _ = finished
    status = sweep_dir / "seed=0" / "status.json"
    status.write_text(json.dumps({**json.loads(status.read_text()), "status": "failed", "config_sha": "0" * 16}))
    (sweep_dir / "seed=1").rename(sweep_dir.parent / "kept")  # the one job this re-run has to do beside it
    result = sweep("seed=0,1", "hydra.sweep.dir=s")
    assert result.exit_code == 0, result.output
    assert json.loads(status.read_text())["status"] == "done"


def test_a_job_folder_of_someone_elses_files_is_left_alone(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "s" / "seed=0").mkdir(parents=True)
    (tmp_path / "s" / "seed=0" / "notes.txt").write_text("mine")
    (tmp_path / "s" / "sweep.log").write_text("")  # a sweep's directory, yet the folder is not a job's
    before = files(tmp_path)
    refused(sweep("seed=0,1", "hydra.sweep.dir=s"), "s/seed=0", "files that are not a sweep job's")
    assert files(tmp_path) == before


def test_a_directory_of_other_files_or_a_train_run_is_not_a_sweeps(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "summary.parquet").write_text("the user's own table")
    assert runner.invoke(app, ["train", *TINY, "hydra.run.dir=run"]).exit_code == 0
    before = files(tmp_path)
    refused(sweep("seed=0,1", "hydra.sweep.dir=mine"), "hydra.sweep.dir", "mine is not empty and holds no sweep")
    refused(sweep("seed=0,1", "hydra.sweep.dir=run"), "hydra.sweep.dir", "run holds a run of riskplan train")
    assert files(tmp_path) == before


@pytest.mark.parametrize("where", ["new/.hydra", "run/.hydra/jobs"])
def test_no_sweep_or_run_is_written_into_a_hydra_folder(tmp_path, monkeypatch, where):
    monkeypatch.chdir(tmp_path)
    assert runner.invoke(app, ["train", *TINY, "hydra.run.dir=run"]).exit_code == 0
    before = files(tmp_path)
    refused(sweep("seed=0,1", f"hydra.sweep.dir={where}"), "hydra.sweep.dir", "inside a .hydra folder")
    refused(runner.invoke(app, ["train", *TINY, f"hydra.run.dir={where}"]), "hydra.run.dir", "inside a .hydra folder")
    assert files(tmp_path) == before


@pytest.mark.parametrize("how", [[], ["--batch"]], ids=["jobs", "batch"])
def test_a_rerun_after_its_map_was_edited_never_takes_the_old_worlds_jobs_as_finished(tmp_path, monkeypatch, how):
    """The map's files are part of a job's fingerprint: edited in place, the config reads the same, but the jobs
    trained in the old world are not finished jobs of this sweep (before, they were skipped and the rest trained in
    the new world)."""
    monkeypatch.chdir(tmp_path)
    shutil.copytree(CONF_DIR / "maps", tmp_path / "maps")
    floor_plan = [*how, "experiment=floor_plan", "hydra.sweep.dir=s"]
    assert sweep("seed=0,1", *floor_plan).exit_code == 0
    status = json.loads((tmp_path / "s" / "seed=0" / "status.json").read_text())
    assert status["config_sha"] == config_sha(compose(["experiment=floor_plan", *TINY, "seed=0"]))
    mask = tmp_path / "maps" / "floor_plan_watched.pgm"
    mask.write_bytes(mask.read_bytes()[:-1] + b"\x00")  # one pixel of the watched corridor
    assert config_sha(compose(["experiment=floor_plan", *TINY, "seed=0"])) != status["config_sha"]
    before = files(tmp_path / "s")
    refused(sweep("seed=0,1", *floor_plan), "s/seed=0", "holds a done run of another config", "and 1 more")
    assert files(tmp_path / "s") == before
