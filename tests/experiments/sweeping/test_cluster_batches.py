"""`riskplan sweep --batch` on a cluster launcher (riskplan.experiments.sweeping.cluster_batches): the sweep's runs
cut into tasks by what they share, the task's memory, half its time limit and --jobs; each task trains its chunk
as one batch, to the numbers of the runs alone, and a sweep killed mid-way (its local tasks with it) resumes to them. Here on submitit's local
executor (real processes, the same submitit code path as SLURM's); tests/clusters/test_slurm_sweeps.py runs it on
a real SLURM cluster."""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from support import FAST, assert_same_outputs, child_env, riskplan_cli, riskplan_command
from test_sweep_command import job_dirs
from typer.testing import CliRunner

from riskplan import compose, train
from riskplan.cli import app
from riskplan.experiments.sweeping import cluster_batches
from riskplan.experiments.sweeping.cluster_batches import TASK_SECONDS, TaskSize, task_chunks, task_size
from riskplan.run import cost
from riskplan.run.compose import parse_overrides
from riskplan.run.recorder import STOP_ENV
from riskplan.util.errors import BadInput

pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="the slurm extra (submitit) is not installed")


@pytest.fixture
def seconds_are_steps(monkeypatch):
    """A cost model where a run's estimated seconds are its steps (one step a second, no overhead)."""
    monkeypatch.setattr(cost, "model", lambda: cost.Model(rate=1.0, overhead=0.0, runs=1))


def jobs_of(*spec):
    """Planned jobs: (batch key, bytes, steps) each; an empty key cannot share a batch (the ray backend)."""
    return [SimpleNamespace(batch=b, memory=m, steps=s, shown=f"job{i}") for i, (b, m, s) in enumerate(spec)]


def shape(chunks) -> list[list[str]]:
    return [[job.shown for job in chunk] for chunk in chunks]


def size(memory=1e12, seconds=1e12, cores=1, tasks=None) -> TaskSize:
    return TaskSize(memory, "test", seconds, cores, tasks)


def test_tasks_hold_what_the_task_memory_allows(seconds_are_steps):
    jobs = jobs_of(*[("a", 4, 1)] * 5)
    assert shape(task_chunks(jobs, size(memory=10))) == [["job0", "job1"], ["job2", "job3"], ["job4"]]


def test_tasks_hold_half_their_time_limit_of_work_on_their_cores(seconds_are_steps):
    jobs = jobs_of(*[("a", 1, 8)] * 4)  # 8 s each on one core: 4 s on two
    assert shape(task_chunks(jobs, size(seconds=10))) == [["job0"], ["job1"], ["job2"], ["job3"]]
    assert shape(task_chunks(jobs, size(seconds=10, cores=2))) == [["job0", "job1"], ["job2", "job3"]]


def test_jobs_asks_for_at_least_that_many_tasks_each_of_one_world(seconds_are_steps):
    jobs = jobs_of(*[("a", 1, 1)] * 6, ("b", 1, 1), ("", 0, 1))
    chunks = task_chunks(jobs, size(tasks=4))
    # world a gets three of the four tasks, evenly; b one; the job that cannot share a batch one of its own
    assert shape(chunks) == [["job0", "job1"], ["job2", "job3"], ["job4", "job5"], ["job6"], ["job7"]]
    assert shape(task_chunks(jobs_of(*[("a", 1, 1)] * 7), size(tasks=3))) == [
        ["job0", "job1", "job2"],
        ["job3", "job4"],
        ["job5", "job6"],
    ]
    # never a task without a run, however many are asked for
    assert shape(task_chunks(jobs_of(*[("a", 1, 1)] * 3), size(tasks=10))) == [["job0"], ["job1"], ["job2"]]


def test_without_jobs_each_task_gets_about_task_seconds_of_work(seconds_are_steps):
    jobs = jobs_of(*[("a", 1, TASK_SECONDS / 10)] * 40)  # four tasks' worth
    chunks = task_chunks(jobs, size())
    assert len(chunks) == math.ceil(40 / 10) and all(len(chunk) == 10 for chunk in chunks)


def overrides(*items: str) -> dict:
    return {o.key_or_group: o for o in parse_overrides(list(items))}


def test_task_size_reads_the_launcher_keys():
    got = task_size(
        overrides("hydra.launcher.mem_gb=4", "hydra.launcher.timeout_min=10", "hydra.launcher.cpus_per_task=3"), 7
    )
    assert got == TaskSize(0.8 * 4e9, "80% of hydra.launcher.mem_gb=4", 300.0, 3, 7)
    default = task_size({}, None)
    assert (default.seconds, default.cores, default.tasks) == (30 * 60.0, 1, None)
    for bad in ("hydra.launcher.mem_gb=0", "hydra.launcher.cpus_per_task=-1", "hydra.launcher.timeout_min=1.5"):
        with pytest.raises(BadInput, match=bad.split("=")[0]):
            task_size(overrides(bad), None)
    # Ray: its remote options size the task (fractional CPUs allowed), and there is no time limit
    ray = task_size(
        overrides("hydra.launcher.ray.remote.num_cpus=2.5", "hydra.launcher.ray.remote.memory=1000"), 3, "ray"
    )
    assert ray == TaskSize(800.0, "80% of hydra.launcher.ray.remote.memory=1000", math.inf, 2, 3)
    # the same given as the mapping Hydra takes too (it was read as no options at all: 1 CPU, this machine's memory)
    assert task_size(overrides("hydra.launcher.ray.remote={num_cpus:2.5,memory:1000}"), 3, "ray") == ray
    for bad in (
        "hydra.launcher.ray.remote.num_cpus=0",
        "hydra.launcher.ray.remote.memory=0.5",
        "hydra.launcher.ray.remote={num_cpus:0}",
    ):
        with pytest.raises(BadInput, match=bad.split("=")[0]):
            task_size(overrides(bad), None, "ray_cluster")


@pytest.mark.parametrize(
    ("extra", "names"),
    [
        (["hydra/launcher=joblib"], "--batch"),
        (["hydra/launcher=submitit_local", "hydra.launcher.mem_gb=0"], "hydra.launcher.mem_gb"),
        (["--jobs", "2"], "--jobs"),
    ],
)
def test_bad_cluster_batches_are_one_line(tmp_path, monkeypatch, extra, names):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["sweep", "seed=0,1", *FAST, "--batch", *extra])
    assert result.exit_code == 2, result.output
    assert len(result.stderr.strip().splitlines()) == 1 and names in result.stderr
    assert not (tmp_path / "outputs").exists()


RUN = [*FAST, "train.iterations=6", "train.checkpoint_every=2"]
SWEEP = ["sweep", "seed=0,1", "risk.beta=0.1,0.2", *RUN, "--batch", "hydra/launcher=submitit_local", "--jobs", "2"]


def tasks_submitted(sweep) -> list[str]:
    return sorted(p.name for p in (sweep / ".submitit").iterdir() if p.name.isdigit())


def paused_tasks(sweep) -> set[int]:
    """The pids of the tasks that stopped themselves (STOP_ENV), as the jobs' status.json name them."""
    pids = set()
    for status_file in sweep.glob("*/status.json"):
        pid = json.loads(status_file.read_text()).get("pid")
        with contextlib.suppress(OSError, IndexError):
            if pid and Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T":
                pids.add(pid)
    return pids


@pytest.mark.slow
def test_each_task_trains_its_chunk_to_the_numbers_of_the_runs_alone_and_resumes_after_a_kill(tmp_path):
    reference = {}
    for seed in (0, 1):
        for beta in (0.1, 0.2):
            reference[seed, beta] = tmp_path / "alone" / f"{seed},{beta}"
            train(compose([*RUN, f"seed={seed}", f"risk.beta={beta}"]), reference[seed, beta])

    # both tasks stop themselves after iteration 4 (checkpointed); the sweep is killed there (SIGKILL), and its
    # local tasks end with it
    sweep = tmp_path / "s"
    driver = subprocess.Popen(
        [*riskplan_command(), *SWEEP, f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path,
        env=child_env(**{STOP_ENV: "3"}),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while len(paused := paused_tasks(sweep)) < 2 and driver.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(paused) == 2, f"two tasks, each a batch of two jobs, should have paused: {paused}"
        driver.kill()
        output = driver.communicate(timeout=60)[0]
    finally:
        if driver.poll() is None:
            driver.kill()
            driver.wait()
    assert "batched on the cluster: 4 runs as 2 tasks of up to 2 runs" in output, output
    deadline = time.monotonic() + 30
    while any(Path(f"/proc/{pid}").exists() for pid in paused) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(Path(f"/proc/{pid}").exists() for pid in paused), "the tasks outlived their sweep"
    assert len(tasks_submitted(sweep)) == 2  # two tasks for four jobs
    assert [json.loads(p.read_text())["status"] for p in sweep.glob("*/status.json")] == ["running"] * 4

    resumed = riskplan_cli(tmp_path, *SWEEP, "hydra.sweep.dir=s")
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert len(tasks_submitted(sweep)) == 4
    jobs = job_dirs(sweep)
    assert len(jobs) == 4
    for job in jobs:
        status = json.loads((job / "status.json").read_text())
        assert status["status"] == "done" and status["resumed"] is True
        assert "in a batch of 2" in (job / "job.log").read_text()
        config = yaml.safe_load((job / ".hydra" / "config.yaml").read_text())
        assert_same_outputs(job, reference[config["seed"], config["risk"]["beta"]])
    assert not (sweep / cluster_batches.TASKS).exists()

    again = riskplan_cli(tmp_path, *SWEEP, "hydra.sweep.dir=s")
    assert again.returncode == 0 and "4 jobs: 0 to run, 4 already finished" in again.stdout
    assert len(tasks_submitted(sweep)) == 4  # nothing submitted
