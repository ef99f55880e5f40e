"""Sweeps on a real SLURM cluster: a one-node cluster (tests/clusters/slurm.py: munged, MariaDB, slurmdbd,
slurmctld, slurmd from Debian's packages) started once for this module, plain jobs and a requeue on it, then
`riskplan sweep hydra/launcher=submitit_slurm` as a user would run it: a sweep that finishes, a job requeued
mid-run that resumes from its checkpoint, and a job cancelled mid-run.

Needs root and Debian's packages (installed with apt-get when missing, about half a minute); skips with the reason
otherwise. The cluster starts in about 2 s on an idle 2-core machine (up to ~10 s under load).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .slurm import ClusterUnavailable, SlurmCluster

pytestmark = [pytest.mark.slow, pytest.mark.cluster]

# the fast run of tests/conftest.py's FAST, and the launcher's settings for this cluster
FAST = ["train.iterations=5", "train.samples=500", "train.eval_episodes=2000", "train.bootstrap=50", "train.paths=3"]
LAUNCHER = [
    "hydra/launcher=submitit_slurm",
    "hydra.launcher.partition=debug",
    "hydra.launcher.timeout_min=5",
    "hydra.launcher.cpus_per_task=1",
]
LONG = 10000  # train.iterations of a job that runs long enough (~10-20 s on 2 cores) to be requeued or cancelled


def _alive(pid: int) -> bool:
    """Whether pid is a live (not zombie) process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _wait_until(condition, timeout: float, what: str, every: float = 0.2) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)


def _riskplan() -> str:
    found = Path(sys.executable).with_name("riskplan")
    if found.is_file():
        return str(found)
    found = shutil.which("riskplan")
    if found is None:
        pytest.skip("the riskplan command is not installed next to this Python nor on PATH")
    return found


def _cluster_pids(cluster: SlurmCluster) -> list[int]:
    """Every live process whose environment holds this cluster's SLURM_CONF (slurmstepd, jobs)."""
    marker = f"SLURM_CONF={cluster.conf}".encode()
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                if marker in (proc / "environ").read_bytes().split(b"\0"):
                    pids.append(int(proc.name))
            except OSError:
                continue
    return pids


@pytest.fixture(scope="module")
def cluster():
    started = time.monotonic()
    cluster = SlurmCluster()
    try:
        cluster.start()
    except ClusterUnavailable as err:
        pytest.skip(f"no SLURM cluster on this machine: {err}")
    print(f"\nSLURM cluster up in {time.monotonic() - started:.1f} s ({cluster.timings}); pids {cluster.pids()}")
    daemons = list(cluster.pids().values())
    yield cluster
    cluster.stop()
    assert not [pid for pid in daemons if _alive(pid)], "a daemon outlived stop()"
    assert not cluster.leftovers, f"processes outlived the daemons and were killed: {cluster.leftovers}"


@pytest.fixture
def sweep_env(cluster):
    """The cluster's client environment with this virtualenv first on PATH (the jobs inherit it)."""
    env = dict(cluster.env)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    return env


def _sweep(args: list[str], sweep_dir: Path, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [_riskplan(), "sweep", *args, *LAUNCHER, f"hydra.sweep.dir={sweep_dir}"],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _explain(result: subprocess.CompletedProcess | None, sweep_dir: Path, cluster: SlurmCluster) -> str:
    parts = []
    if result is not None:
        parts.append(
            f"exit {result.returncode}\n--- stdout\n{result.stdout[-3000:]}\n--- stderr\n{result.stderr[-3000:]}"
        )
    log = sweep_dir / "sweep.log"
    if log.exists():
        parts.append(f"--- {log}\n{log.read_text(errors='replace')[-3000:]}")
    for job_log in sorted(sweep_dir.glob("*/job.log")):
        parts.append(f"--- {job_log}\n{job_log.read_text(errors='replace')[-1500:]}")
    parts.append(cluster.logs(10))
    return "\n".join(parts)


def _still_running(sweep: subprocess.Popen, args: list[str], sweep_dir: Path, cluster: SlurmCluster) -> None:
    """Fail with the sweep's output if it has already exited."""
    if sweep.poll() is not None:
        out, _ = sweep.communicate()
        raise AssertionError(
            "riskplan sweep exited early\n"
            + _explain(subprocess.CompletedProcess(args, sweep.returncode, out, ""), sweep_dir, cluster)
        )


def _array_task(sweep_dir: Path, task: int) -> str:
    """The SLURM id (<array>_<task>) of a submitit array task, from its folder under .submitit."""
    folders = sorted(p.name for p in (sweep_dir / ".submitit").glob(f"*_{task}") if p.is_dir())
    assert folders, f"no submitit folder for task {task} in {sweep_dir / '.submitit'}"
    return folders[-1]


def _status(job_dir: Path) -> dict:
    try:
        return json.loads((job_dir / "status.json").read_text())
    except (OSError, ValueError):
        return {}


# ----------------------------------------------------------------------------------------------- plain SLURM


def test_batch_job_runs_to_completed(cluster, tmp_path):
    out = tmp_path / "hello.txt"
    job = cluster.submit("-o", str(tmp_path / "slurm-%j.out"), "--wrap", f"echo hello from $SLURM_JOB_ID > {out}")
    assert cluster.wait_for(job, timeout=60) == "COMPLETED", cluster.logs()
    assert out.read_text().strip() == f"hello from {job}"
    _wait_until(lambda: job not in cluster.queue(), 30, f"job {job} to leave squeue")
    assert cluster.queue() == []


def test_requeued_job_runs_again(cluster, tmp_path):
    starts = tmp_path / "starts.txt"
    script = tmp_path / "requeue.sh"
    script.write_text(f'#!/bin/bash\necho "start ${{SLURM_RESTART_COUNT:-0}}" >> {starts}\nsleep 300\n')
    job = cluster.submit("-o", "/dev/null", str(script))
    _wait_until(lambda: starts.exists() and len(starts.read_text().splitlines()) == 1, 60, "the job's first start")
    assert cluster.wait_for(job, {"RUNNING"}, timeout=30) == "RUNNING"
    cluster.run("scontrol", "requeue", job)
    # a requeued job waits AuthInfo's cred_expire (5 s here; 120 s by default) before it may start again
    _wait_until(lambda: len(starts.read_text().splitlines()) >= 2, 90, "the requeued job to start again")
    assert starts.read_text().splitlines() == ["start 0", "start 1"]
    cluster.run("scancel", job)
    assert cluster.wait_for(job, timeout=60) == "CANCELLED"
    _wait_until(lambda: not cluster.queue(), 30, "an empty queue")


def test_stop_ends_exactly_what_it_started(cluster, tmp_path):
    """A second cluster beside the module's (its own ports, socket and files): stop() with a job still running
    ends its daemons and the job's processes, and leaves the module's cluster alone."""
    other = SlurmCluster(accounting=False, install=False).start()
    try:
        started = tmp_path / "started"
        other.submit("-o", "/dev/null", "--wrap", f"touch {started}; sleep 300")
        _wait_until(started.exists, 60, "the job to start")
        job_pids = _cluster_pids(other)
        assert job_pids, "no process of the running job found"
        daemons = list(other.pids().values())
        root = other.root
    finally:
        other.stop()
    assert not [pid for pid in daemons + job_pids if _alive(pid)]
    assert not root.exists()
    assert all(_alive(pid) for pid in cluster.pids().values())
    assert cluster.run("sinfo", "-h", "-o", "%T").stdout.strip() == "idle"


# ------------------------------------------------------------------------------------------- riskplan sweep


def test_riskplan_sweep_runs_on_slurm(cluster, sweep_env, tmp_path):
    sweep_dir = tmp_path / "sweep"
    started = time.monotonic()
    result = _sweep(["seed=0,1", *FAST], sweep_dir, sweep_env)
    seconds = time.monotonic() - started
    assert result.returncode == 0, _explain(result, sweep_dir, cluster)
    print(f"\n2-job riskplan sweep on SLURM: {seconds:.1f} s")
    for seed in (0, 1):
        job = sweep_dir / f"seed={seed}"
        assert (job / "summary.json").is_file(), _explain(result, sweep_dir, cluster)
        assert _status(job).get("status") == "done"
    for task in (0, 1):  # they ran as SLURM jobs, and sacct (what submitit polls) saw them finish
        assert cluster.state(_array_task(sweep_dir, task)) == "COMPLETED"


def test_riskplan_job_requeued_mid_run_resumes(cluster, sweep_env, tmp_path):
    """`scontrol requeue` (what preemption does) kills a job mid-run and starts it again: it resumes from its
    checkpoint and the sweep finishes as if nothing happened."""
    sweep_dir = tmp_path / "sweep"
    args = [
        _riskplan(),
        "sweep",
        "seed=0,1",
        f"train.iterations={LONG}",
        *FAST[1:],
        *LAUNCHER,
        f"hydra.sweep.dir={sweep_dir}",
    ]
    sweep = subprocess.Popen(args, env=sweep_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        job = sweep_dir / "seed=0"
        _wait_until(
            lambda: (
                (_status(job).get("status") == "running" and (job / "checkpoint").is_file()) or sweep.poll() is not None
            ),
            120,
            "seed=0 to run and write a checkpoint",
        )
        _still_running(sweep, args, sweep_dir, cluster)
        task = _array_task(sweep_dir, 0)
        cluster.run("scontrol", "requeue", task)
        out, _ = sweep.communicate(timeout=600)
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
    result = subprocess.CompletedProcess(args, sweep.returncode, out, "")
    assert sweep.returncode == 0, _explain(result, sweep_dir, cluster)
    status = _status(job)
    assert status.get("status") == "done" and status.get("resumed") is True, (
        status,
        _explain(result, sweep_dir, cluster),
    )
    assert "resumed at" in (job / "job.log").read_text()
    assert cluster.state(task) == "COMPLETED"


def test_riskplan_job_cancelled_mid_run(cluster, sweep_env, tmp_path):
    """`scancel` of one job: submitit sees CANCELLED through sacct (without accounting it would wait for ever),
    the launcher stops, and `riskplan sweep` exits 1 naming the job as interrupted; the other job runs on."""
    import pandas as pd

    sweep_dir = tmp_path / "sweep"
    args = [
        _riskplan(),
        "sweep",
        "seed=0,1",
        f"train.iterations={LONG}",
        *FAST[1:],
        *LAUNCHER,
        f"hydra.sweep.dir={sweep_dir}",
    ]
    sweep = subprocess.Popen(args, env=sweep_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        _wait_until(
            lambda: _status(sweep_dir / "seed=0").get("status") == "running" or sweep.poll() is not None,
            120,
            "seed=0 to run",
        )
        _still_running(sweep, args, sweep_dir, cluster)
        task = _array_task(sweep_dir, 0)
        cancelled = time.monotonic()
        cluster.run("scancel", task)
        out, _ = sweep.communicate(timeout=300)
        noticed = time.monotonic() - cancelled
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
        queued = cluster.queue()  # the other job outlives the sweep (as SLURM jobs should): end it here
        if queued:
            cluster.run("scancel", *queued, check=False)
    print(f"\nriskplan sweep after scancel of {task} (exit {sweep.returncode} {noticed:.1f} s later):\n{out}")
    result = subprocess.CompletedProcess(args, sweep.returncode, out, "")
    assert sweep.returncode == 1, _explain(result, sweep_dir, cluster)
    assert cluster.state(task) == "CANCELLED"
    assert "CANCELLED" in (sweep_dir / "sweep.log").read_text(), _explain(result, sweep_dir, cluster)
    summary = pd.read_parquet(sweep_dir / "summary.parquet")
    row = summary[summary["job"] == "seed=0"].iloc[0]
    assert row["status"] != "done", summary
    _wait_until(lambda: not cluster.queue(), 60, "an empty queue")
