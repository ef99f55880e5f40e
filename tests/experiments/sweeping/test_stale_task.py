"""A job that reaches a folder the sweep's plan could not check (another process held it then: a SLURM task of an
earlier launch, say) applies the plan's rule under the folder's lock: a run of another config that did not fail is
left as it is, every file byte for byte, and the job fails alone with one line naming the folder and the sweep's
remedy, never `riskplan train --resume`. A failed run of another config is still replaced."""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
from support import TINY, files, held_by_another_process
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.experiments.sweep_worker import begin_job, config_sha, foreign_run, read_status, sweep_job
from riskplan.experiments.sweeping import batched, execute
from riskplan.experiments.sweeping.batched import prepare_job
from riskplan.experiments.sweeping.cluster_batches import ChunkTask, _pending
from riskplan.experiments.sweeping.jobs import Job, check_job_folders
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput
from riskplan.util.lock import LOCK

runner = CliRunner()
A, B = [*TINY, "seed=1"], [*TINY, "seed=1", "train.iterations=4"]  # one job folder's two configs


def finished_run(out: Path, overrides: list[str], status: str = "done", sha: str | None = None) -> dict[str, bytes]:
    """A folder as a finished sweep job of `overrides` leaves it (its files stand in for the real ones: the check
    comes before anything is read but status.json); every file with its bytes."""
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "config.yaml").write_text("seed: 1  # the other run's\n")
    (out / ".hydra" / "overrides.yaml").write_text("- seed=1\n")
    for name in ("run.mcap", "metrics.parquet", "eval.parquet", "trajectories.parquet", "summary.json", "checkpoint"):
        (out / name).write_bytes(b"the other run's " + name.encode())
    (out / "job.log").write_text("=== riskplan sweep job started\n=== done\n")
    (out / LOCK).write_bytes(b"")  # left behind by the run that held it
    record = {"status": status, "error": None, "config_sha": sha or config_sha(compose(overrides)), "cvar": 1.0}
    (out / "status.json").write_text(json.dumps(record))
    return files(out)


def test_the_rule_names_what_the_folder_holds_with_its_article(tmp_path):
    (tmp_path / "job.log").write_text("")
    assert foreign_run(tmp_path, "b", None) is None  # only a job's own files: a launch killed early
    assert foreign_run(tmp_path, "b", {"status": "interrupted", "config_sha": "a"}) == (
        "holds an interrupted run of another config"
    )
    assert foreign_run(tmp_path, "b", {"status": "done", "config_sha": "a"}) == "holds a done run of another config"
    assert foreign_run(tmp_path, "b", {"status": "done"}) == "holds a done run of another config"  # riskplan train's
    assert foreign_run(tmp_path, "b", {"status": "failed", "config_sha": "a"}) is None  # replaced
    assert foreign_run(tmp_path, "a", {"status": "done", "config_sha": "a"}) is None  # its own
    (tmp_path / "notes.txt").write_text("mine")
    assert foreign_run(tmp_path, "b", None) == "holds files that are not a sweep job's"


@pytest.mark.parametrize("status", ["done", "interrupted", "running"])
def test_a_job_leaves_another_configs_run_byte_for_byte_and_fails_alone(tmp_path, capfd, status):
    out = tmp_path / "seed=1"
    before = finished_run(out, A, status)
    assert sweep_job(compose(B), out) is None
    assert files(out) == before
    line = capfd.readouterr().err.strip()
    assert line.startswith(f"error: {out} holds a") and f"{status} run of another config" in line, line
    assert "hydra.sweep.dir" in line and "--resume" not in line


def test_the_mirrored_case_an_older_launchs_job_meets_the_newer_configs_run(tmp_path, capfd):
    out = tmp_path / "seed=1"
    before = finished_run(out, B)  # the later launch finished first; the earlier launch's task starts now
    assert sweep_job(compose(A), out) is None
    assert files(out) == before
    assert "holds a done run of another config" in capfd.readouterr().err


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
def test_a_batched_job_leaves_it_too_and_lets_its_lock_go(tmp_path, capfd):
    out = tmp_path / "seed=1"
    before = finished_run(out, A)
    cfg = compose(B)
    with contextlib.ExitStack() as held:
        prepared = prepare_job(cfg, cfg, out, held)
        assert prepared.start is None and prepared.setup is None and prepared.value is None
        assert not held._exit_callbacks  # not held for the rest of the launch: the folder is not this job's
    assert files(out) == before
    assert f"{out} holds a done run of another config" in capfd.readouterr().err
    assert begin_job(cfg, out).refused is not None and files(out) == before


def test_a_cluster_task_of_an_earlier_launch_leaves_it(tmp_path, capfd):
    """The probe's case: task _1 of the first launch, held pending, released after a re-run with another config
    finished the folder's job."""
    out = tmp_path / "seed=1"
    before = finished_run(out, B)
    cfg = compose(A)
    job = _pending(cfg, None, out)
    assert ChunkTask()([job], str(tmp_path / ".batch_progress.0"), 3, 1) == [None]
    assert files(out) == before
    assert "holds a done run of another config" in capfd.readouterr().err


def test_a_failed_run_of_another_config_is_still_replaced(tmp_path):
    out = tmp_path / "seed=1"
    finished_run(out, A, "failed")
    start = begin_job(compose(B), out)
    assert start.refused is None and not start.finished
    assert not (out / "run.mcap").exists() and read_status(out)["status"] == "running"


def test_the_plans_check_says_an_interrupted_run(tmp_path):
    out = tmp_path / "s" / "seed=1"
    finished_run(out, A, "interrupted")
    with pytest.raises(BadInput, match="holds an interrupted run of another config"):
        check_job_folders(tmp_path / "s", [Job(["seed=1"], config_sha(compose(B)), path=out)])


# ------------------------------------------------------------------------------------------- whole sweeps
def sweep(*args: str):
    return runner.invoke(app, ["sweep", *TINY, *args])


def first_launch(tmp_path: Path, *how: str) -> None:
    """seed=0 finished by a first launch (its config: TINY); seed=1's folder not there yet."""
    assert sweep("seed=0,1", "hydra.sweep.dir=s", *how).exit_code == 0
    shutil.rmtree(tmp_path / "s" / "seed=1")


def plan_while_seed_0_is_held(monkeypatch) -> None:
    """The plan's check as it runs while another process holds seed=0's folder before its status.json is written (or
    when a task of an earlier launch starts after the plan): it skips that folder."""
    check = execute.check_job_folders
    monkeypatch.setattr(
        execute,
        "check_job_folders",
        lambda sweep_dir, jobs: check(sweep_dir, [j for j in jobs if j.folder != "seed=0"]),
    )


CALLBACK = "+hydra.callbacks.log_return._target_=hydra.experimental.callbacks.LogJobReturnCallback"


@pytest.mark.slow
@pytest.mark.parametrize(
    "how",
    [
        [],
        [CALLBACK],  # a callback of the user's: the batched jobs are set up through Hydra's run_job
        ["--jobs", "1"],  # Hydra writes no .hydra/ in the worker: the job does, once the folder is its own
    ],
    ids=["batched", "batched through run_job", "job by job"],
)
def test_a_sweep_whose_plan_skipped_a_held_folder_leaves_its_run_as_it_was(tmp_path, monkeypatch, how):
    monkeypatch.chdir(tmp_path)
    first_launch(tmp_path, *how)
    before = files(tmp_path / "s" / "seed=0")
    plan_while_seed_0_is_held(monkeypatch)

    result = sweep("seed=0,1", "hydra.sweep.dir=s", "train.iterations=4", *how)

    assert files(tmp_path / "s" / "seed=0") == before
    assert result.exit_code == 1, result.output
    assert "train.iterations=4" in (tmp_path / "s" / "seed=1" / ".hydra" / "overrides.yaml").read_text()  # its own
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet").set_index("job")
    assert summary.loc["seed=1", "status"] == "done" and summary.loc["seed=0", "status"] == "failed"
    assert "seed=0 holds a done run of another config; the job left it as it was" in summary.loc["seed=0", "error"]
    assert "seed=0" in result.stderr and "--resume" not in result.stderr


@pytest.mark.slow  # a job through Hydra's run_job
def test_a_batched_job_set_up_through_run_job_has_hydra_write_no_files_over_another_run(tmp_path):
    """_run_job's check before Hydra's run_job writes .hydra/: the folder it would set the job up in, by the sweep's
    keys, holds a run of another config (Hydra is then told hydra.output_subdir=null)."""
    keys = [f"hydra.sweep.dir={tmp_path / 's'}", "hydra.sweep.subdir=job"]
    assert batched._holds_another_run(compose([*B, *keys], with_hydra=True)) is False  # no folder yet
    finished_run(tmp_path / "s" / "job", A)
    assert batched._holds_another_run(compose([*B, *keys], with_hydra=True)) is True
    assert batched._holds_another_run(compose([*A, *keys], with_hydra=True)) is False  # its own run


@pytest.mark.slow
def test_a_held_folder_whose_status_names_another_config_is_refused_by_the_plan(tmp_path, monkeypatch):
    """A task of an earlier launch still training (it holds the folder; its status.json names its config): the
    re-run with other configs is refused at once, as for a folder no one holds, and nothing is written."""
    monkeypatch.chdir(tmp_path)
    first_launch(tmp_path)
    before = files(tmp_path / "s")
    with held_by_another_process(tmp_path / "s" / "seed=0"):
        result = sweep("seed=0,1", "hydra.sweep.dir=s", "train.iterations=4")
    assert result.exit_code == 2, result.output
    assert result.stderr.splitlines() == [
        "error: s/seed=0: holds a done run of another config; a sweep goes on in its directory only with the same "
        "configs: give a new hydra.sweep.dir, or remove what is there"
    ]
    assert files(tmp_path / "s") == before
