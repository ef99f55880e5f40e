"""The Ray launcher runs a sweep on a local Ray instance (needs `riskplan[ray]`; tests/ray_check.sh makes that
environment, since hydra-ray-launcher pins cloudpickle<3, which joblib 1.6 does not accept)."""

from __future__ import annotations

import os
import subprocess

import pandas as pd
import pytest
from support import CLI, FAST, assert_same_outputs

pytest.importorskip(
    "hydra_plugins.hydra_ray_launcher",
    reason="the Ray launcher is not installed here; bash tests/ray_check.sh runs this test in its own venv",
)

pytestmark = pytest.mark.slow

# a local instance only: no usage statistics sent anywhere, no dashboard
ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_DISABLE_DOCKER_CPU_WARNING": "1"}


def test_ray_launcher_runs_a_two_job_sweep_on_a_local_ray_instance(tmp_path):
    """Its own instance even where RAY_ADDRESS names a cluster (ray.init(address=None) would join it, and refuse the
    launcher's object-store size): riskplan passes address=local."""
    result = subprocess.run(
        [
            *CLI,
            "sweep",
            "seed=0,1",
            *FAST,
            "hydra/launcher=ray",
            "hydra.sweep.dir=s",
            "+hydra.launcher.ray.init.include_dashboard=false",
            "+hydra.launcher.ray.init.num_cpus=2",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, **ENV, "RAY_ADDRESS": "127.0.0.1:1"},
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "(ray)" in result.stdout
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    assert sorted(summary.seed) == [0, 1] and (summary.status == "done").all()
    assert "Ray" in (tmp_path / "s" / "sweep.log").read_text()  # it went through the Ray launcher


def test_a_batched_sweep_on_ray_trains_a_chunk_per_task_to_the_numbers_of_the_runs_alone(tmp_path):
    """--batch with the Ray launcher: four runs as two Ray tasks (--jobs 2), each a batch of two; every file's
    numbers those of the same sweep run job by job."""
    grid = ["seed=0,1", "risk.beta=0.1,0.2", *FAST]
    ray = ["+hydra.launcher.ray.init.include_dashboard=false", "+hydra.launcher.ray.init.num_cpus=2"]

    def sweep(folder: str, *extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*CLI, "sweep", *grid, f"hydra.sweep.dir={folder}", *extra],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
            env={**os.environ, **ENV},
        )

    batched = sweep("b", "hydra/launcher=ray", *ray, "--batch", "--jobs", "2")
    assert batched.returncode == 0, batched.stdout + batched.stderr
    assert "batched on the cluster: 4 runs as 2 tasks of up to 2 runs" in batched.stdout, batched.stdout
    alone = sweep("a", "hydra/launcher=basic")
    assert alone.returncode == 0, alone.stdout + alone.stderr
    jobs = sorted(p for p in (tmp_path / "b").iterdir() if (p / "status.json").is_file())
    assert len(jobs) == 4
    for job in jobs:
        assert "in a batch of 2" in (job / "job.log").read_text()
        assert_same_outputs(job, tmp_path / "a" / job.name)
