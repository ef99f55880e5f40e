"""The one SLURM test cluster that test_slurm_cluster.py and test_slurm_sweeps.py share (package scope: started by
the first test that needs it, stopped after the last test of tests/clusters), and the environment riskplan's sweeps
run in on it."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from .common import alive, with_venv_on_path
from .slurm import ClusterUnavailable, SlurmCluster


@pytest.fixture(scope="package")
def slurm_cluster():
    """A one-node SLURM cluster (partition `debug`, task/affinity, accounting), up for the whole package."""
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
    assert not [pid for pid in daemons if alive(pid)], "a daemon outlived stop()"
    assert not cluster.leftovers, f"processes outlived the daemons and were killed: {cluster.leftovers}"


@pytest.fixture(scope="package")
def slurm_env(slurm_cluster, tmp_path_factory):
    """The cluster's client environment (SLURM_CONF) with this virtualenv first on PATH, as for a user whose venv is
    active: sbatch exports it to the jobs. Numba's cache is warmed first (the kernels a paper run uses), so that the
    first job does not spend half a minute compiling them in the middle of a test (measured: 34 s cold, 2 cores)."""
    env = with_venv_on_path(slurm_cluster.env)
    scratch = tmp_path_factory.mktemp("warm-up")
    warm = subprocess.run(
        [
            sys.executable,
            "-c",
            f"from riskplan.experiments.sweep_worker import warm_up; print(warm_up({str(scratch)!r})[1])",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert warm.returncode == 0, warm.stdout + warm.stderr
    print(f"numba cache warmed in {float(warm.stdout.split()[-1]):.1f} s")
    return env
