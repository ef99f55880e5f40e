"""Launcher settings the SLURM test cluster refuses (or could never meet) are bad input at plan time: `riskplan
sweep` exits 2 with one line naming the hydra.launcher key and sbatch's reason, writes no sweep directory and
submits nothing (sbatch --test-only, cluster_batches.check_sbatch). Before, each gave exit 1 with multirun.yaml,
summary.parquet, .submitit/ and the jobs' .hydra/ written; cpus_per_task=64 pended for ever (PartitionConfig)."""

from __future__ import annotations

import subprocess

import pytest

from .common import riskplan_exe
from .slurm import PARTITION

pytestmark = [pytest.mark.slow, pytest.mark.cluster]

CASES = [  # (setting, the key named, a piece of sbatch's reason)
    ("hydra.launcher.partition=nosuch", "hydra.launcher.partition", "invalid partition specified: nosuch"),
    ("hydra.launcher.gres=gpu:1", "hydra.launcher.gres", "Invalid generic resource (gres) specification"),
    ("hydra.launcher.constraint=nosuch", "hydra.launcher.constraint", "Invalid feature specification"),
    ("hydra.launcher.mem_gb=100000", "hydra.launcher.mem_gb", "Requested node configuration is not available"),
    ("hydra.launcher.nodes=0", "hydra.launcher.nodes", "Node count specification invalid"),
    ("hydra.launcher.signal_delay_s=-1", "hydra.launcher.signal_delay_s", "Invalid --signal specification"),
    ("+hydra.launcher.additional_parameters={foo:bar}", "hydra.launcher.additional_parameters", "'--foo=bar'"),
    ("hydra.launcher.cpus_per_task=64", "hydra.launcher.cpus_per_task", "Requested node configuration"),
]


@pytest.mark.parametrize("batch", [[], ["--batch"]], ids=["jobs", "batch"])
@pytest.mark.parametrize(("setting", "key", "reason"), CASES, ids=[case[1].rsplit(".", 1)[1] for case in CASES])
def test_a_setting_slurm_refuses_is_bad_input_before_anything_is_written(
    slurm_cluster, slurm_env, tmp_path, setting, key, reason, batch
):
    sweep_dir = tmp_path / "sweep"
    args = ["seed=0,1", "hydra/launcher=submitit_slurm", f"hydra.launcher.partition={PARTITION}"]
    args += ["hydra.launcher.timeout_min=10", setting, f"hydra.sweep.dir={sweep_dir}", *batch]
    before = slurm_cluster.run("sacct", "-X", "-n", "-P", "-o", "JobID").stdout.split()
    done = subprocess.run(
        [riskplan_exe(), "sweep", *args], env=slurm_env, capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert done.returncode == 2, done.stdout + done.stderr
    line = done.stderr.strip()
    assert "\n" not in line and "Traceback" not in line, line
    assert line.startswith(f"error: {key}: sbatch refuses it: "), line
    assert reason in line, line
    assert not sweep_dir.exists()
    assert slurm_cluster.run("sacct", "-X", "-n", "-P", "-o", "JobID").stdout.split() == before  # nothing submitted
