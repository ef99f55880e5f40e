"""riskplan on a real SLURM cluster, as a user runs it: `riskplan sweep hydra/launcher=submitit_slurm` on the one-node
test cluster of conftest.py (`slurm_cluster`: partition `debug`, task/affinity, accounting through slurmdbd).

- A job requeued mid-run by `scontrol requeue` (what preemption with PreemptMode=REQUEUE does: SIGTERM, then the
  job runs again) resumes from its checkpoint, and every job's numbers equal those of the same sweep run
  uninterrupted in one local process (riskplan's results do not depend on the launcher).
- The same for submitit's own checkpoint-and-requeue (SIGUSR2, what `--signal=USR2@N` sends before a time limit).
- Re-running a finished sweep submits nothing to SLURM.
- A job cancelled mid-run is named, with its overrides and CANCELLED, in the sweep's error line.
- Without CPU binding (TaskPlugin=task/none, a second small cluster) a job runs numba on the CPUs SLURM granted it
  (SLURM_CPUS_PER_TASK), not on every core of the node.
- --batch: the two jobs as one task, cancelled mid-run (both runs checkpointed, both jobs named) or sent SIGUSR2
  (requeued by submitit), resume to the uninterrupted numbers.
- Every SLURM block of docs/clusters.md (`<!-- tested: slurm -->`) runs as written, and the per-job overhead is
  measured on its sweep (printed; see the docs' "Overhead per job").

Interruptions happen at a known point, without timing: every job of an interrupted sweep gets riskplan's test hook
RISKPLAN_TEST_STOP_AFTER_ITERATION, so it stops itself (SIGSTOP) after iteration 104 of the paper's 200 (checkpoints
every 10); the test then acts on the stopped job through SLURM (scontrol requeue, scancel --signal=USR2, scancel)
and lets it go on. A job that resumed from an earlier checkpoint stops there again and is simply let go on.

These tests found three riskplan bugs, since fixed: submitit's SIGUSR2 requeue could not pickle the job (the Hydra
task was copied by value with the job's open stdout), the cancelled-job line did not name the job, and a relative
hydra.sweep.dir broke on a Ray cluster.

Times measured on a 2-core machine that other test suites kept busy (load 5-12), besides the cluster's start
(~3-5 s, shared with test_slurm_cluster.py) and numba's cache warm-up (~2-3 s warm, ~35 s cold): the requeue
fixture 20-40 s (its SLURM sweep 18-30 s, the local reference 14 s), re-run 3-4 s, submitit's requeue ~20 s, cancel 26-27 s (submitit waits 15 s for the result of a job that ended without one),
threads 7-10 s, the docs' commands 12-20 s: about 2 minutes with test_slurm_cluster.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from riskplan.run.recorder import STOP_ENV

from .common import (
    alive,
    finished_jobs,
    marked_blocks,
    numbers,
    riskplan_exe,
    run_block,
    status,
    sweep_dirs,
    wait_until,
    with_venv_on_path,
)
from .slurm import PARTITION, SlurmCluster

pytestmark = [pytest.mark.slow, pytest.mark.cluster]

STOP_AFTER = 104  # every interrupted sweep's jobs stop themselves after this iteration (of 200; checkpoints every 10)
ITERATIONS = 200  # the paper's default training (conf/experiment/paper_single.yaml), ~2 s per job here
SEEDS = "seed=0,1"
LAUNCHER = [
    "hydra/launcher=submitit_slurm",
    f"hydra.launcher.partition={PARTITION}",
    "hydra.launcher.timeout_min=10",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.max_num_timeout=3",  # submitit requeues a job on SIGUSR2 only while this is above 0
]


# ------------------------------------------------------------------------------------------------- driving


def _proc_state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return ""


def _slurm_id(pid: int) -> str | None:
    """The SLURM id of the job a process belongs to (<array job>_<index> for an array task), from its environment."""
    try:
        items = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return None
    env = dict(item.decode(errors="replace").split("=", 1) for item in items if b"=" in item)
    if env.get("SLURM_ARRAY_JOB_ID") and env.get("SLURM_ARRAY_TASK_ID"):
        return f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}"
    return env.get("SLURM_JOB_ID")


# What the test does, through SLURM, to a job that has stopped itself, before it lets the job go on (SIGCONT)
ACTIONS = {
    "continue": [],
    "requeue": [["scontrol", "requeue", "{id}"]],  # SLURM: SIGCONT + SIGTERM to the job, then it runs again
    "timeout": [["scancel", "--signal=USR2", "{id}"]],  # submitit's handler: checkpoint(), scontrol requeue, exit
    "cancel": [["scancel", "{id}"]],  # SIGCONT + SIGTERM, then SIGKILL after KillWait; state CANCELLED
}


@dataclass
class Sweep:
    """A `riskplan sweep` run to its end, its jobs acted on as they stopped themselves."""

    args: list[str]
    sweep_dir: Path
    returncode: int = -1
    output: str = ""
    lines: list[str] = field(default_factory=list)  # its output, read as it came
    acted: dict[str, list[str]] = field(default_factory=dict)  # job folder -> what was done, in order
    slurm_ids: dict[str, str] = field(default_factory=dict)  # job folder -> its SLURM id

    def explain(self, cluster: SlurmCluster) -> str:
        parts = [f"riskplan sweep {' '.join(self.args)}\nexit {self.returncode}\n{self.output[-4000:]}"]
        parts.append(f"acted: {self.acted}, SLURM ids: {self.slurm_ids}")
        log = self.sweep_dir / "sweep.log"
        if log.exists():
            parts.append(f"--- {log}\n{log.read_text(errors='replace')[-3000:]}")
        for job_log in sorted(self.sweep_dir.glob("*/job.log")):
            parts.append(f"--- {job_log}\n{job_log.read_text(errors='replace')[-2000:]}")
        parts.append(cluster.logs(10))
        return "\n".join(parts)


def run_sweep(
    cluster: SlurmCluster,
    env: dict[str, str],
    sweep_dir: Path,
    args: list[str],
    actions: dict[str, str] | None = None,
    timeout: float = 600,
) -> Sweep:
    """Run `riskplan sweep args hydra.sweep.dir=sweep_dir`. With `actions` ({job folder: ACTIONS key}), every job
    stops itself after iteration STOP_AFTER; the first time a job stops, its action is taken, then it is let go on;
    jobs without an action, and any later stop of a job, are let go on at once."""
    args = [*args, f"hydra.sweep.dir={sweep_dir}"]
    run = Sweep(args, sweep_dir)
    if actions is not None:
        env = {**env, STOP_ENV: str(STOP_AFTER)}
    sweep = subprocess.Popen(
        [riskplan_exe(), "sweep", *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )

    def read() -> None:
        for line in sweep.stdout:
            run.lines.append(line.rstrip("\n"))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    seen: set[int] = set()
    deadline = time.monotonic() + timeout
    try:
        while sweep.poll() is None:
            if time.monotonic() > deadline:
                raise AssertionError(f"riskplan sweep still running after {timeout:.0f} s\n{run.explain(cluster)}")
            if actions is not None and sweep_dir.is_dir():
                for job in sorted(p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith(".")):
                    pid = status(job).get("pid")
                    if not pid or pid in seen or status(job).get("status") != "running" or _proc_state(pid) != "T":
                        continue
                    seen.add(pid)
                    job_id = _slurm_id(pid)
                    assert job_id, f"no SLURM id in the environment of {job.name}'s process {pid}"
                    run.slurm_ids[job.name] = job_id
                    action = actions.get(job.name, "continue") if job.name not in run.acted else "continue"
                    run.acted.setdefault(job.name, []).append(action)
                    for command in ACTIONS[action]:
                        cluster.run(*[part.format(id=job_id) for part in command])
                    if action != "cancel":  # scancel sends SIGCONT itself
                        cluster.run("scancel", "--signal=CONT", job_id, check=False)
            time.sleep(0.2)
    finally:
        if sweep.poll() is None:
            sweep.kill()  # this test's own child, by its pid
        sweep.wait()
        reader.join(timeout=30)
        queued = cluster.queue()
        if queued and sweep.returncode == 0:  # a finished sweep's last job may still be exiting: let it end
            with contextlib.suppress(AssertionError):
                wait_until(lambda: not cluster.queue(), 60, "the sweep's jobs to end")
            queued = cluster.queue()
        if queued:  # jobs outlive a failed sweep (as SLURM jobs should): end them here
            cluster.run("scancel", *queued, check=False)
            wait_until(lambda: not cluster.queue(), 60, "an empty queue")
    run.returncode = sweep.returncode
    run.output = "\n".join(run.lines)
    return run


def sacct_states(cluster: SlurmCluster, job_id: str) -> list[str]:
    """Every state sacct recorded for the job's allocation, oldest first (-D: a requeued job's earlier runs too),
    once the last is final: slurmdbd records a job's end a moment after it."""
    states: list[str] = []

    def final() -> bool:
        out = cluster.run("sacct", "-D", "-X", "-n", "-P", "-o", "State", "-j", job_id).stdout
        states[:] = [line.split()[0] for line in out.splitlines() if line.strip()]
        return bool(states) and states[-1] not in UNFINISHED

    wait_until(final, 60, f"the final state of job {job_id} in sacct")
    return states


UNFINISHED = ("PENDING", "RUNNING", "COMPLETING", "REQUEUED", "SUSPENDED", "RESIZING")


def all_slurm_jobs(cluster: SlurmCluster) -> list[str]:
    """Every job this cluster's accounting knows of."""
    out = cluster.run("sacct", "-a", "-X", "-n", "-P", "-S", "2000-01-01", "-o", "JobID").stdout
    return sorted(line for line in out.splitlines() if line.strip())


# ------------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def reference(slurm_env, tmp_path_factory) -> Path:
    """The same two jobs, uninterrupted, in one local process (Hydra's basic launcher: riskplan's numbers do not
    depend on the launcher, nor on the threads a job has)."""
    sweep_dir = tmp_path_factory.mktemp("reference") / "sweep"
    started = time.monotonic()
    result = subprocess.run(
        [riskplan_exe(), "sweep", SEEDS, "hydra/launcher=basic", f"hydra.sweep.dir={sweep_dir}"],
        env=slurm_env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    finished_jobs(sweep_dir)
    print(f"\nreference sweep (basic launcher, one local process): {time.monotonic() - started:.1f} s")
    return sweep_dir


@pytest.fixture(scope="module")
def requeued(slurm_cluster, slurm_env, tmp_path_factory) -> Sweep:
    """The two jobs on SLURM, seed=0 requeued (scontrol requeue) after iteration 104, seed=1 let run."""
    sweep_dir = tmp_path_factory.mktemp("requeued") / "sweep"
    started = time.monotonic()
    run = run_sweep(
        slurm_cluster, slurm_env, sweep_dir, [SEEDS, *LAUNCHER, "--jobs", "2"], actions={"seed=0": "requeue"}
    )
    print(f"\nSLURM sweep with seed=0 requeued: {time.monotonic() - started:.1f} s")
    return run


# ------------------------------------------------------------------------------------------------- tests


def _interrupted_at(job_log: str) -> int:
    match = re.search(r"=== interrupted by SIGTERM after (\d+) iterations, all checkpointed", job_log)
    assert match, job_log
    return int(match.group(1))


def test_a_requeued_job_resumes_with_the_uninterrupted_numbers(requeued, reference, slurm_cluster):
    run = requeued
    assert run.returncode == 0, run.explain(slurm_cluster)
    assert run.acted == {"seed=0": ["requeue"], "seed=1": ["continue"]}, run.explain(slurm_cluster)
    jobs = finished_jobs(run.sweep_dir)
    assert sorted(jobs) == ["seed=0", "seed=1"]

    log = (jobs["seed=0"] / "job.log").read_text()
    stopped_at = _interrupted_at(log)  # SIGTERM: riskplan checkpointed the iteration in progress and ended
    assert STOP_AFTER < stopped_at < ITERATIONS, log
    assert "riskplan sweep job resumed at" in log, log
    assert status(jobs["seed=0"]).get("resumed") is True
    assert sacct_states(slurm_cluster, run.slurm_ids["seed=0"]) == ["REQUEUED", "COMPLETED"]

    assert "interrupted" not in (jobs["seed=1"] / "job.log").read_text()
    assert status(jobs["seed=1"]).get("resumed") is False
    assert sacct_states(slurm_cluster, run.slurm_ids["seed=1"]) == ["COMPLETED"]

    for name, job in jobs.items():  # identical, not close: the resumed run is the same computation
        assert numbers(job) == numbers(reference / name), name


def test_rerunning_a_finished_sweep_submits_nothing(requeued, slurm_cluster, slurm_env):
    assert requeued.returncode == 0, requeued.explain(slurm_cluster)
    before = all_slurm_jobs(slurm_cluster)
    folders = sorted(p.name for p in (requeued.sweep_dir / ".submitit").iterdir())
    again = run_sweep(slurm_cluster, slurm_env, requeued.sweep_dir, requeued.args[:-1])
    assert again.returncode == 0, again.explain(slurm_cluster)
    assert "2 jobs: 0 to run, 2 already finished" in again.output, again.output
    assert all_slurm_jobs(slurm_cluster) == before  # nothing submitted: no new job in accounting
    assert slurm_cluster.queue() == []
    assert sorted(p.name for p in (requeued.sweep_dir / ".submitit").iterdir()) == folders


def test_submitit_timeout_requeue_resumes_with_the_uninterrupted_numbers(slurm_cluster, slurm_env, reference, tmp_path):
    """SIGUSR2 is what SLURM sends `hydra.launcher.signal_delay_s` before a job's time limit (`--signal=USR2@N`);
    submitit's handler calls the launcher's checkpoint() (a DelayedSubmission of the same job), requeues the job
    and exits. With timeout_min=10, submitit counts any SIGUSR2 as a timeout (it guarantees min(80%, limit - 10
    min) of the limit), so it requeues only while max_num_timeout allows: set here to 3."""
    run = run_sweep(slurm_cluster, slurm_env, tmp_path / "sweep", [SEEDS, *LAUNCHER], actions={"seed=1": "timeout"})
    assert run.acted.get("seed=1", [None])[0] == "timeout", run.explain(slurm_cluster)
    job = run.sweep_dir / "seed=1"
    log = (job / "job.log").read_text()
    assert "Caught signal SIGUSR2" in log, log
    assert run.returncode == 0, run.explain(slurm_cluster)
    jobs = finished_jobs(run.sweep_dir)
    assert "Requeued job" in log and "riskplan sweep job resumed at" in log, log
    assert status(job).get("resumed") is True
    assert sacct_states(slurm_cluster, run.slurm_ids["seed=1"]) == ["REQUEUED", "COMPLETED"]
    for name, path in jobs.items():
        assert numbers(path) == numbers(reference / name), name


def test_a_cancelled_job_is_named_with_its_overrides(slurm_cluster, slurm_env, tmp_path):
    """scancel of a running job: riskplan checkpoints it (SIGTERM) and it ends CANCELLED without a result; the other
    job finishes; the sweep exits 1 with one error line naming the cancelled job (SLURM id, overrides, state)."""
    run = run_sweep(slurm_cluster, slurm_env, tmp_path / "sweep", [SEEDS, *LAUNCHER], actions={"seed=1": "cancel"})
    assert run.returncode == 1, run.explain(slurm_cluster)
    assert run.acted["seed=1"] == ["cancel"], run.explain(slurm_cluster)
    job_id = run.slurm_ids["seed=1"]
    assert slurm_cluster.wait_for(job_id, timeout=60) == "CANCELLED"
    cancelled = status(run.sweep_dir / "seed=1")
    assert cancelled.get("status") == "interrupted", cancelled  # checkpointed on the way out
    assert status(run.sweep_dir / "seed=0").get("status") == "done"
    errors = [line for line in run.output.splitlines() if line.startswith("error: the launcher stopped:")]
    assert len(errors) == 1, run.output
    line = errors[0]
    print(f"\n{line}")
    assert f"SLURM job {job_id} (seed=1) ended CANCELLED without a result" in line, line


BATCHED = [SEEDS, *LAUNCHER, "--batch"]  # the two jobs as one batch: one array task


def submitted_tasks(sweep_dir: Path) -> list[str]:
    """The SLURM ids of the tasks submitit submitted for a sweep (each has a folder with its pickled task; an
    array's own folder holds only its batch script)."""
    return sorted(p.name for p in (sweep_dir / ".submitit").iterdir() if any(p.glob("*_submitted.pkl")))


def test_a_batched_sweep_is_one_task_and_a_cancelled_task_resumes_with_the_uninterrupted_numbers(
    slurm_cluster, slurm_env, reference, tmp_path
):
    """--batch on SLURM: the two jobs train as one batch in one task. scancel of that task mid-run checkpoints both
    runs (SIGTERM) and ends it CANCELLED; the sweep's error line names both jobs. The next run of the sweep submits
    one task again, and both jobs resume to the numbers of the uninterrupted sweep."""
    before = all_slurm_jobs(slurm_cluster)
    run = run_sweep(slurm_cluster, slurm_env, tmp_path / "sweep", BATCHED, actions={"seed=0": "cancel"})
    assert run.returncode == 1, run.explain(slurm_cluster)
    assert "batched on the cluster: 2 runs as 1 task of up to 2 runs" in run.output, run.output
    assert run.acted == {"seed=0": ["cancel"]}, run.explain(slurm_cluster)  # one process holds both jobs
    job_id = run.slurm_ids["seed=0"]
    assert slurm_cluster.wait_for(job_id, timeout=60) == "CANCELLED"
    for name in ("seed=0", "seed=1"):
        job = run.sweep_dir / name
        assert status(job).get("status") == "interrupted", status(job)
        assert STOP_AFTER < _interrupted_at((job / "job.log").read_text()) < ITERATIONS
    errors = [line for line in run.output.splitlines() if line.startswith("error: the launcher stopped:")]
    assert len(errors) == 1 and f"SLURM job {job_id} (seed=0; seed=1) ended CANCELLED" in errors[0], run.output

    resumed = run_sweep(slurm_cluster, slurm_env, run.sweep_dir, BATCHED)
    assert resumed.returncode == 0, resumed.explain(slurm_cluster)
    submitted = submitted_tasks(run.sweep_dir)
    assert len(submitted) == 2, submitted  # a task per launch, not a job per run
    wait_until(lambda: len(all_slurm_jobs(slurm_cluster)) >= len(before) + 2, 60, "both tasks in sacct")
    assert all_slurm_jobs(slurm_cluster) == sorted([*before, *submitted])
    jobs = finished_jobs(run.sweep_dir)
    assert sorted(jobs) == ["seed=0", "seed=1"]
    for name, job in jobs.items():
        assert status(job).get("resumed") is True
        assert "in a batch of 2" in (job / "job.log").read_text()
        assert numbers(job) == numbers(reference / name), name


def test_a_batched_task_near_its_time_limit_is_requeued_and_resumes(slurm_cluster, slurm_env, reference, tmp_path):
    """SIGUSR2 to a batched task: riskplan checkpoints both runs, then submitit's handler requeues the same chunk
    (ChunkTask.checkpoint), and the task's next run resumes both to the uninterrupted numbers."""
    run = run_sweep(slurm_cluster, slurm_env, tmp_path / "sweep", BATCHED, actions={"seed=0": "timeout"})
    assert run.returncode == 0, run.explain(slurm_cluster)
    assert run.acted.get("seed=0", [None])[0] == "timeout", run.explain(slurm_cluster)
    assert sacct_states(slurm_cluster, run.slurm_ids["seed=0"]) == ["REQUEUED", "COMPLETED"]
    for name, job in finished_jobs(run.sweep_dir).items():
        log = (job / "job.log").read_text()
        assert "=== interrupted by SIGUSR2 after" in log and "riskplan sweep job resumed at" in log, log
        assert status(job).get("resumed") is True
        assert numbers(job) == numbers(reference / name), name


PROBE = '''"""Test probe (tests/clusters/test_slurm_sweeps.py): when a SLURM job step's Python exits, record the numba
threads its main thread ran with, the CPUs SLURM granted and the CPUs the process could run on."""
import atexit, json, os, sys

_out = os.environ.get("RISKPLAN_TEST_THREADS_DIR")
if _out and os.environ.get("SLURM_STEP_ID") is not None:

    def _record():
        numba = sys.modules.get("numba")
        if numba is None:
            return
        record = {
            "job": os.environ.get("SLURM_JOB_ID"),
            "numba_threads": numba.get_num_threads(),
            "numba_max": numba.config.NUMBA_NUM_THREADS,
            "cpus_per_task": os.environ.get("SLURM_CPUS_PER_TASK"),
            "affinity": len(os.sched_getaffinity(0)),
        }
        with open(os.path.join(_out, f"{os.getpid()}.json"), "w") as f:
            json.dump(record, f)

    atexit.register(_record)
'''


def test_without_cpu_binding_a_job_uses_the_cpus_slurm_granted(slurm_cluster, slurm_env, tmp_path):
    """TaskPlugin=task/none: the job may run on every core of the node, and numba would start a thread per core;
    riskplan's sweep job takes SLURM_CPUS_PER_TASK instead. riskplan records the thread count nowhere, so a probe
    (a sitecustomize on PYTHONPATH) records numba.get_num_threads() when the job's Python exits."""
    cores = len(os.sched_getaffinity(0))
    if cores < 2:
        pytest.skip("needs 2 or more cores to tell 1 thread from all of them")
    other = SlurmCluster(accounting=False, task_plugin="task/none", install=False).start()
    try:
        probe, records = tmp_path / "probe", tmp_path / "records"
        probe.mkdir()
        records.mkdir()
        (probe / "sitecustomize.py").write_text(PROBE)
        env = {
            **with_venv_on_path(other.env),
            "PYTHONPATH": str(probe),
            "RISKPLAN_TEST_THREADS_DIR": str(records),
        }
        run = run_sweep(other, env, tmp_path / "sweep", ["seed=0", "train.iterations=20", *LAUNCHER])
        assert run.returncode == 0, run.explain(other)
        finished_jobs(run.sweep_dir)
        found = [json.loads(path.read_text()) for path in records.glob("*.json")]
        assert len(found) == 1, found
        record = found[0]
        print(f"\ntask/none, cpus_per_task=1 on {cores} cores: {record}")
        assert record["affinity"] == cores  # not bound: the job could run on every core
        assert record["numba_max"] > 1
        assert record["cpus_per_task"] == "1"
        assert record["numba_threads"] == 1  # riskplan took SLURM's grant
    finally:
        daemons = list(other.pids().values())
        other.stop()
    assert not [pid for pid in daemons if alive(pid)]


# ------------------------------------------------------------------------------------------------- the docs


def _log_time(text: str) -> float:
    """Epoch seconds of a log timestamp `2026-11-23 22:11:42,747` (local time, as Hydra and submitit write it)."""
    return datetime.strptime(text, "%Y-%m-%d %H:%M:%S,%f").timestamp()


def _training_start(job: Path) -> float:
    """When the training loop started: the first record of run.mcap (written as the loop begins)."""
    from mcap.reader import make_reader

    with open(job / "run.mcap", "rb") as f:
        for _, _, message in make_reader(f).iter_messages():
            return message.log_time / 1e9
    raise AssertionError(f"{job / 'run.mcap'} holds no message")


def overheads(sweep_dir: Path, command_ended: float) -> list[dict]:
    """Where each job's time went, from the files the sweep left: submission (Hydra's log line just before submitit
    submits the array) -> job start (submitit's first log line in the job's Python) -> training start (run.mcap's
    first record) -> training end (+ summary.json's wall_time) -> job end (status.json's finished) -> the
    command's exit (the last job's end to the driver noticing, summarising and exiting)."""
    log = (sweep_dir / "sweep.log").read_text()
    submitted = _log_time(
        re.search(r"^\[([\d\- :,]+)\]\[[^\]]*submitit_launcher\]\[INFO\] Submitit 'slurm'", log, re.M)[1]
    )
    rows = []
    for job in sorted(p for p in sweep_dir.iterdir() if (p / "status.json").is_file()):
        job_id = str(OmegaConf.load(job / ".hydra" / "hydra.yaml").hydra.job.id)
        out = (sweep_dir / ".submitit" / job_id / f"{job_id}_0_log.out").read_text()
        started = _log_time(re.search(r"\(([\d\- :,]+)\) - Starting with JobEnvironment", out)[1])
        training = _training_start(job)
        train_time = json.loads((job / "summary.json").read_text())["wall_time"]
        finished = status(job)["finished"]
        rows.append(
            {
                "job": job.name,
                "slurm": job_id,
                "queued": started - submitted,
                "setup": training - started,
                "training": train_time,
                "after": finished - training - train_time,
                "finished": finished,
            }
        )
    last = max(row["finished"] for row in rows)
    for row in rows:
        row["exit"] = command_ended - last
    return rows


def test_the_docs_slurm_commands_run_as_written(slurm_cluster, slurm_env, tmp_path):
    """Every `<!-- tested: slurm -->` block of docs/clusters.md, in order, in one working directory, with the
    cluster's environment (SLURM_CONF) and the venv active: each exits 0, and every sweep it started ran all its
    jobs on SLURM (COMPLETED in sacct) to the end."""
    work = tmp_path / "project"
    work.mkdir()
    submitted = 0
    for block in marked_blocks("slurm"):
        started = time.time()
        result = run_block(block, work, slurm_env)
        ended = time.time()
        for sweep_dir in sweep_dirs(result.stdout, work):
            jobs = finished_jobs(sweep_dir)
            if "batched on the cluster:" in result.stdout:  # --batch: a SLURM task per chunk of jobs, COMPLETED
                tasks = submitted_tasks(sweep_dir)
                assert 0 < len(tasks) < len(jobs), (str(block), tasks)
                for task in tasks:
                    assert slurm_cluster.wait_for(task, timeout=60) == "COMPLETED", (str(block), task)
                print(f"\n{block}: {len(jobs)} jobs as {len(tasks)} tasks in {ended - started:.1f} s")
                submitted += 1
                continue
            for name, job in jobs.items():  # each ran as a SLURM job (its id is Hydra's hydra.job.id), COMPLETED
                job_id = str(OmegaConf.load(job / ".hydra" / "hydra.yaml").hydra.job.id)
                # slurmctld hands a finished job to slurmdbd a moment later: sacct may not know it yet
                assert slurm_cluster.wait_for(job_id, timeout=60) == "COMPLETED", (str(block), name, job_id)
            counts = re.search(r"^(\d+) jobs?: (\d+) to run", result.stdout, re.M)
            if counts is None or counts[2] == "0":
                continue  # a re-run that found every job finished
            submitted += 1
            rows = overheads(sweep_dir, ended)
            print(f"\n{block}: {len(jobs)} jobs in {ended - started:.1f} s (seconds per job:)")
            for row in rows:
                print(
                    "  {job:24s} {slurm:6s} submission to job start {queued:5.2f}, job start to training "
                    "{setup:5.2f}, training {training:5.2f}, after training {after:5.2f}".format(**row)
                )
            print(f"  the last job's end to the command's exit: {rows[0]['exit']:.2f} s")
    assert submitted, "no tested SLURM block of docs/clusters.md submitted a sweep"
