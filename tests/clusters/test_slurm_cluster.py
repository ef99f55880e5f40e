"""The SLURM test cluster itself (tests/clusters/slurm.py: munged, MariaDB, slurmdbd, slurmctld, slurmd from
Debian's packages; shared with test_slurm_sweeps.py through conftest.py's `slurm_cluster`): a batch job completes,
a requeued job runs again, and stopping a second cluster ends exactly what it started. riskplan's sweeps on it are
in test_slurm_sweeps.py.

Needs root and Debian's packages (installed with apt-get when missing, about half a minute); skips with the reason
otherwise. The cluster starts in about 2-5 s on an idle 2-core machine (up to ~10 s under load); these tests take
about 13 s after that.
"""

from __future__ import annotations

import pytest

from .common import alive, cluster_pids, wait_until
from .slurm import SlurmCluster

pytestmark = [pytest.mark.slow, pytest.mark.cluster]


@pytest.fixture
def cluster(slurm_cluster):
    return slurm_cluster


# ----------------------------------------------------------------------------------------------- plain SLURM


def test_batch_job_runs_to_completed(cluster, tmp_path):
    out = tmp_path / "hello.txt"
    job = cluster.submit("-o", str(tmp_path / "slurm-%j.out"), "--wrap", f"echo hello from $SLURM_JOB_ID > {out}")
    assert cluster.wait_for(job, timeout=60) == "COMPLETED", cluster.logs()
    assert out.read_text().strip() == f"hello from {job}"
    wait_until(lambda: job not in cluster.queue(), 30, f"job {job} to leave squeue")
    assert cluster.queue() == []


def test_requeued_job_runs_again(cluster, tmp_path):
    starts = tmp_path / "starts.txt"
    script = tmp_path / "requeue.sh"
    script.write_text(f'#!/bin/bash\necho "start ${{SLURM_RESTART_COUNT:-0}}" >> {starts}\nsleep 300\n')
    job = cluster.submit("-o", "/dev/null", str(script))
    wait_until(lambda: starts.exists() and len(starts.read_text().splitlines()) == 1, 60, "the job's first start")
    assert cluster.wait_for(job, {"RUNNING"}, timeout=30) == "RUNNING"
    cluster.run("scontrol", "requeue", job)
    # a requeued job waits AuthInfo's cred_expire (5 s here; 120 s by default) before it may start again
    wait_until(lambda: len(starts.read_text().splitlines()) >= 2, 90, "the requeued job to start again")
    assert starts.read_text().splitlines() == ["start 0", "start 1"]
    cluster.run("scancel", job)
    assert cluster.wait_for(job, timeout=60) == "CANCELLED"
    wait_until(lambda: not cluster.queue(), 30, "an empty queue")


def test_stop_ends_exactly_what_it_started(cluster, tmp_path):
    """A second cluster beside the module's (its own ports, socket and files): stop() with a job still running
    ends its daemons and the job's processes, and leaves the module's cluster alone."""
    other = SlurmCluster(accounting=False, install=False).start()
    try:
        started = tmp_path / "started"
        other.submit("-o", "/dev/null", "--wrap", f"touch {started}; sleep 300")
        wait_until(started.exists, 60, "the job to start")
        job_pids = cluster_pids(other.conf)
        assert job_pids, "no process of the running job found"
        daemons = list(other.pids().values())
        root = other.root
    finally:
        other.stop()
    assert not [pid for pid in daemons + job_pids if alive(pid)]
    assert not root.exists()
    assert all(alive(pid) for pid in cluster.pids().values())
    assert cluster.run("sinfo", "-h", "-o", "%T").stdout.strip() == "idle"
