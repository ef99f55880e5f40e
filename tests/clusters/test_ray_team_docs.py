"""The team.backend=ray commands of docs/clusters.md ("Robots as Ray actors"), run as written: on a local Ray
instance, and on a two-node Ray cluster with the environment a user on one of its nodes has (RAY_ADDRESS, its token).
Each run leaves the files of a simulated run, says deterministic: false, and keeps the staleness bound.

Needs `ray` (core) here: `pip install 'riskplan[distributed]'`; skipped without it. About two minutes on 2 cores."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("ray", reason="ray is not installed here (pip install 'riskplan[distributed]')")

from riskplan.run.log_reader import read_log

from .common import marked_blocks, run_block, with_venv_on_path
from .ray_cluster import RayCluster

pytestmark = [pytest.mark.slow, pytest.mark.cluster]
FILES = ("run.mcap", "metrics.parquet", "eval.parquet", "trajectories.parquet", "summary.json", "checkpoint")


def user_env(**extra: str) -> dict[str, str]:
    """A user's shell with this virtualenv active and no Ray address or token of another cluster (the suite's
    RAY_TMPDIR kept: where the local instances leave their session folders)."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("RAY_") or key == "RAY_TMPDIR"}
    env.update({"RAY_USAGE_STATS_ENABLED": "0", **extra})
    return with_venv_on_path(env)


def runs_of(cwd: Path) -> list[Path]:
    """The run directories the block's `riskplan train` commands made, oldest first."""
    return sorted((cwd / "outputs" / "runs").iterdir())


def check_run(run: Path) -> dict:
    """The files of a simulated run, deterministic: false, every mixed message within team.staleness."""
    for name in FILES:
        assert (run / name).is_file(), f"{run}: no {name}"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["deterministic"] is False
    config = read_log(run / "run.mcap").metadata["config"]
    staleness = pd.read_parquet(run / "metrics.parquet").staleness.dropna()
    assert staleness.max() <= config["team"]["staleness"]
    return summary


def test_the_docs_ray_team_commands_run_as_written_on_a_local_instance(tmp_path):
    (block,) = marked_blocks("ray-team")
    run_block(block, tmp_path, user_env(), timeout=900)
    three, sixteen = runs_of(tmp_path)
    assert check_run(three)["team_size"] == 3
    summary = check_run(sixteen)
    assert summary["team_size"] == 16
    assert pd.read_parquet(sixteen / "metrics.parquet").query("robot == 5").staleness.max() <= 2  # the slow one


def test_the_docs_ray_team_command_runs_on_an_existing_cluster(tmp_path):
    (block,) = marked_blocks("ray-team-cluster")
    with RayCluster(num_nodes=2, cpus_per_node=1) as cluster:
        run_block(block, tmp_path, user_env(**cluster.driver_env), timeout=900)
        (run,) = runs_of(tmp_path)
        check_run(run)
        places = read_log(run / "run.mcap").metadata["ray_team"]
        assert set(places["nodes"]) == {node["id"] for node in cluster.node_info}, places  # on both nodes
