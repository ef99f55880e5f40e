"""riskplan's Hydra plugins and app glue: the grid sweeper launches exactly the planned jobs, in order; a SLURM job
that ended without a result is named by its overrides; no module patches Hydra."""

from __future__ import annotations

import json

import pytest
from hydra.errors import HydraException
from omegaconf import OmegaConf

from hydra_plugins.riskplan_sweeper.plan_sweeper import RiskplanSweeper, planned_jobs
from riskplan.experiments.sweeping.jobs import TASKS
from riskplan.experiments.sweeping.launch import _launcher_error, _task_names


class Result:
    def __init__(self, value):
        self.value = value

    @property
    def return_value(self):
        if isinstance(self.value, Exception):
            raise self.value
        return self.value


class RecordingLauncher:
    """A launcher that records what it is handed and returns one result per job."""

    def __init__(self, outcome=0.0):
        self.calls, self.outcome = [], outcome

    def launch(self, job_overrides, initial_job_idx):
        self.calls.append(([list(job) for job in job_overrides], initial_job_idx))
        return [Result(self.outcome) for _ in job_overrides]


def sweeper_for(tmp_path, jobs, launcher):
    listed = tmp_path / "jobs.json"
    listed.write_text(json.dumps(jobs))
    sweeper = RiskplanSweeper(jobs=str(listed))
    sweeper.config = OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path / "sweep")}}, "seed": 0})
    sweeper.launcher = launcher
    return sweeper


def test_the_grid_sweeper_launches_exactly_the_planned_jobs_in_order(tmp_path):
    jobs = [["risk.beta=0.2", "seed=1"], ["risk.beta=0.1", "seed=0"], ["seed=3"]]
    launcher = RecordingLauncher()
    returns = sweeper_for(tmp_path, jobs, launcher).sweep(["risk.beta=0.1,0.2", "seed=range(0,4)"])
    # the command line's sweep is not expanded again: only the planner's list, as one batch from job 0
    assert launcher.calls == [(jobs, 0)]
    assert [len(batch) for batch in returns] == [3]
    assert OmegaConf.load(tmp_path / "sweep" / "multirun.yaml").seed == 0


def test_the_grid_sweeper_launches_nothing_when_every_job_finished(tmp_path):
    launcher = RecordingLauncher()
    assert sweeper_for(tmp_path, [], launcher).sweep(["seed=0,1"]) == []
    assert launcher.calls == [] and (tmp_path / "sweep" / "multirun.yaml").is_file()


def test_a_failed_job_raises_from_the_sweep_as_under_hydras_basic_sweeper(tmp_path):
    launcher = RecordingLauncher(outcome=ValueError("job 0 failed"))
    with pytest.raises(ValueError, match="job 0 failed"):
        sweeper_for(tmp_path, [["seed=0"]], launcher).sweep([])


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "run `riskplan sweep`"),
        ('{"seed": 0}', "does not hold a list of override lists"),
        ('[["seed=0"], "seed=1"]', "does not hold a list of override lists"),
        ("[[0]]", "does not hold a list of override lists"),
    ],
)
def test_the_grid_sweeper_refuses_a_missing_or_malformed_job_list(tmp_path, content, message):
    path = ""
    if content is not None:
        path = str(tmp_path / "jobs.json")
        (tmp_path / "jobs.json").write_text(content)
    with pytest.raises(HydraException, match=message):
        planned_jobs(path)


def test_a_slurm_job_without_a_result_is_named_by_its_overrides(tmp_path):
    log = tmp_path / "sweep.log"
    log.write_text(
        "Error executing job with overrides: []\n"
        "submitit.core.utils.UncompletedJobError: Job 4242_1 (task: 0) with path /x has not produced any output "
        "(state: TIMEOUT)\n"
    )
    error = _launcher_error(log, _task_names(tmp_path, [["seed=0"], ["risk.beta=0.2", "seed=1"]]))
    assert "SLURM job 4242_1 (risk.beta=0.2,seed=1) ended TIMEOUT" in error
    # a batched sweep on the cluster: task 1 trained a chunk of jobs, all of them named
    (tmp_path / TASKS).write_text(json.dumps({"tasks": [[0], [1, 2]], "names": ["seed=0", "seed=1; seed=2"]}))
    error = _launcher_error(log, _task_names(tmp_path, [["seed=0"], ["seed=1"], ["seed=2"]]))
    assert "SLURM job 4242_1 (seed=1; seed=2) ended TIMEOUT" in error
