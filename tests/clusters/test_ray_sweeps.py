"""The Ray commands of docs/clusters.md, run as written (common.py's marked blocks): on a local Ray instance the sweep
starts itself (`<!-- tested: ray-local -->`), and on an existing two-node Ray cluster (ray_cluster.py: head on
127.0.0.2, a second node on 127.0.0.3, one CPU each) started from this environment's `ray`
(`<!-- tested: ray-cluster -->`), where the jobs must run on both nodes.

Needs Hydra's Ray launcher, which pins cloudpickle<3 and so lives in a virtualenv of its own: `bash
tests/ray_check.sh` builds it and runs this file; the main suite skips it. The cluster command runs in the
environment a user on a node of the cluster has: their shell, with the virtualenv active, RAY_ADDRESS naming the
head (hydra/launcher=ray_cluster's `address: auto` reads it) and the cluster's token (Ray >= 2.5x authenticates
drivers). Which node ran a job comes from the Ray worker logs of each node, which are named after the worker's pid
(the job's status.json records it).

About 40 s on an idle 2-core machine: the local command ~15 s, the cluster's start ~10 s, its command ~10 s.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip(
    "hydra_plugins.hydra_ray_launcher",
    reason="the Ray launcher is not installed here; bash tests/ray_check.sh runs this test in its own venv",
)
pytest.importorskip("ray", reason="ray is not installed here")

from riskplan.run.recorder import STOP_ENV

from .common import (
    finished_jobs,
    marked_blocks,
    numbers,
    riskplan_exe,
    run_block,
    status,
    sweep_dirs,
    with_venv_on_path,
)
from .ray_cluster import RayCluster, _start_time

pytestmark = [pytest.mark.slow, pytest.mark.cluster]


def user_env() -> dict[str, str]:
    """A user's shell with this virtualenv active: no Ray address or token of some other cluster, no usage stats."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("RAY_")}
    env.update(RAY_USAGE_STATS_ENABLED="0", RAY_DISABLE_DOCKER_CPU_WARNING="1")
    return with_venv_on_path(env)


# the local instance first: it runs before the module's cluster starts, so the two never share the 2 cores


def test_the_docs_local_ray_command_runs_as_written(tmp_path):
    for block in marked_blocks("ray-local"):
        started = time.monotonic()
        result = run_block(block, tmp_path, user_env())
        found = sweep_dirs(result.stdout, tmp_path)
        assert found, result.stdout
        for sweep_dir in found:
            jobs = finished_jobs(sweep_dir)
            assert "Ray Launcher is launching" in (sweep_dir / "sweep.log").read_text()
            print(f"\n{block}: {len(jobs)} jobs in {time.monotonic() - started:.1f} s")
        assert "(ray)" in result.stdout, result.stdout


@pytest.fixture(scope="module")
def ray_cluster():
    """Two nodes of this environment's Ray, one CPU each."""
    with RayCluster(Path(sys.executable).with_name("ray"), num_nodes=2, cpus_per_node=1) as cluster:
        started = {pid: _start_time(pid) for pid in cluster.pids}
        print(f"\nRay cluster {cluster.address} ({cluster.ray_version}) up in {cluster.startup_seconds:.1f} s")
        yield cluster
    assert not [pid for pid, start in started.items() if _start_time(pid) == start], "a `ray start` outlived stop()"


def test_the_docs_ray_cluster_command_runs_on_both_nodes(ray_cluster, tmp_path):
    env = {**user_env(), **ray_cluster.driver_env}  # RAY_ADDRESS and the token, as on a node of the cluster
    assert env["RAY_ADDRESS"] == ray_cluster.address
    for block in marked_blocks("ray-cluster"):
        started = time.monotonic()
        result = run_block(block, tmp_path, env)
        found = sweep_dirs(result.stdout, tmp_path)
        assert found, result.stdout
        for sweep_dir in found:
            jobs = finished_jobs(sweep_dir)
            log = (sweep_dir / "sweep.log").read_text()
            assert f"Connecting to existing Ray cluster at address: {ray_cluster.address}" in log, log
            nodes = {name: ray_cluster.node_of_worker(status(path)["pid"]) for name, path in jobs.items()}
            print(f"\n{block}: {len(jobs)} jobs in {time.monotonic() - started:.1f} s, on {nodes}")
            assert None not in nodes.values(), (nodes, ray_cluster.logs(5))
            assert set(nodes.values()) == set(ray_cluster.node_ips), nodes
        assert "(ray_cluster)" in result.stdout, result.stdout


RUN = ["train.iterations=6", "train.checkpoint_every=2", "train.samples=500", "train.eval_episodes=2000"]
GRID = ["seed=range(0,4)", *RUN]


def _paused(sweep_dir: Path) -> dict[int, list[str]]:
    """The task processes that stopped themselves (STOP_ENV), each with the jobs it trains."""
    tasks: dict[int, list[str]] = {}
    for job in sorted(p for p in sweep_dir.glob("*") if (p / "status.json").is_file()):
        pid = status(job).get("pid")
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError, TypeError):
            continue
        if state == "T":
            tasks.setdefault(pid, []).append(job.name)
    return tasks


def test_a_batched_sweep_on_ray_is_a_task_per_chunk_and_a_killed_task_resumes(ray_cluster, tmp_path):
    """--batch on the two-node cluster: four runs as two Ray tasks (--jobs 2), one a node, each a batch of two. One
    task is killed (SIGKILL) after iteration 4, checkpointed: Ray runs it again, its two jobs resume from their
    checkpoints, and every job's numbers equal those of the same runs trained job by job in one local process."""
    env = {**user_env(), **ray_cluster.driver_env}
    stop = f"+hydra.launcher.ray.remote.runtime_env.env_vars.{STOP_ENV}='3'"  # each task pauses after iteration 4
    args = [*GRID, "--batch", "hydra/launcher=ray_cluster", "--jobs", "2", stop, "hydra.sweep.dir=b"]
    sweep = subprocess.Popen(
        [riskplan_exe(), "sweep", *args],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 180
        while len(paused := _paused(tmp_path / "b")) < 2 and sweep.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        if sweep.poll() is not None:
            raise AssertionError(f"the sweep ended before its tasks paused:\n{sweep.communicate()[0]}")
        assert len(paused) == 2 and sorted(map(len, paused.values())) == [2, 2], paused
        nodes = {ray_cluster.node_of_worker(pid) for pid in paused}
        killed, other = sorted(paused)
        os.kill(killed, signal.SIGKILL)  # a node's worker lost mid-run
        os.kill(other, signal.SIGCONT)
        output = sweep.communicate(timeout=300)[0]
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
    assert sweep.returncode == 0, output
    assert "batched on the cluster: 4 runs as 2 tasks of up to 2 runs" in output, output
    assert nodes == set(ray_cluster.node_ips), nodes  # a task on each node
    reference = subprocess.run(
        [riskplan_exe(), "sweep", *GRID, "hydra/launcher=basic", "hydra.sweep.dir=a"],
        cwd=tmp_path,
        env=user_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert reference.returncode == 0, reference.stdout + reference.stderr
    jobs = finished_jobs(tmp_path / "b")
    for name, job in jobs.items():
        assert (status(job).get("resumed") is True) == (name in paused[killed]), (name, status(job))
        assert "in a batch of 2" in (job / "job.log").read_text()
        assert numbers(job) == numbers(tmp_path / "a" / name), name
