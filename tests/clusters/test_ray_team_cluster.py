"""team.backend=ray on a real two-node Ray cluster (tests/clusters/ray_cluster.py: a head on 127.0.0.2 and a node on
127.0.0.3, stopped by the fixture): the run connects with team.address, its robots scan on both nodes (the node id
of each is in run.mcap's "ray_team" metadata), the team converges, a robot four times slower stays within the
staleness bound, and no robot's actor outlives the run.

Needs `ray` (core) here: `pip install 'riskplan[distributed]'`; skipped without it. A few minutes on 2 cores (the
cluster starts in 6-18 s; 16 robots share the two cores)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed here (pip install 'riskplan[distributed]')")

import riskplan  # noqa: E402
from riskplan.run.log_reader import read_log  # noqa: E402

from .ray_cluster import RayCluster, _start_time  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.cluster]
RUN = ["train.eval_episodes=2000", "train.bootstrap=50", "train.paths=1"]


@pytest.fixture(scope="module")
def cluster():
    """Two nodes (1 CPU each); this process gets the cluster's token, and each run connects and disconnects."""
    with RayCluster(num_nodes=2, cpus_per_node=1) as running:
        saved = running.apply_driver_env()
        if ray.is_initialized():
            ray.shutdown()
        try:
            yield running
        finally:
            if ray.is_initialized():
                ray.shutdown()
            running.restore_env(saved)


def train_on(cluster, out: Path, *overrides: str):
    config = riskplan.compose(
        ["experiment=paper_team", "team.backend=ray", f"team.address={cluster.address}", *RUN, *overrides]
    )
    started = time.monotonic()
    run = riskplan.train(config, out, progress=False)
    return run, time.monotonic() - started


def actors_gone(where: list[dict], seconds: float = 30.0) -> bool:
    """Whether the robots' worker processes (all on this machine) have ended."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if all(_start_time(place["pid"]) is None for place in where):
            return True
        time.sleep(0.2)
    return False


def test_robots_spread_over_both_nodes_and_the_team_converges(cluster, tmp_path):
    run, seconds = train_on(cluster, tmp_path / "r", "train.iterations=60", "train.samples=1000")
    log = read_log(tmp_path / "r" / "run.mcap")
    where = log.metadata["ray_team"]["robots"]
    assert {place["node_id"] for place in where} == {node["id"] for node in cluster.node_info}  # both nodes
    assert {place["ip"] for place in where} == set(cluster.node_ips)
    metrics = run.metrics
    error = metrics[metrics.robot == -1].set_index("iteration").consensus_error
    assert error.iloc[-10:].mean() < 0.5 * error.iloc[1:20].max()
    assert metrics.staleness[metrics.robot >= 0].dropna().max() <= 2
    simulated = riskplan.train(
        riskplan.compose(["experiment=paper_team", *RUN, "train.iterations=60", "train.samples=1000"]),
        tmp_path / "sim",
        progress=False,
    )
    assert abs(run.summary["cvar"]["value"] / simulated.summary["cvar"]["value"] - 1) < 0.05
    assert run.summary["deterministic"] is False
    assert actors_gone(where)
    print(f"\n3 robots on 2 nodes: {seconds:.1f} s, CVaR {run.summary['cvar']['value']:.1f}")


def test_sixteen_robots_with_one_four_times_slower_stay_within_the_bound(cluster, tmp_path):
    speeds = [1.0] * 16
    speeds[5] = 4.0
    run, seconds = train_on(
        cluster,
        tmp_path / "r",
        "team.robots=16",
        "team.graph=ring",
        f"team.speeds=[{','.join(map(str, speeds))}]",
        "team.staleness=2",
        "train.iterations=40",
        "train.samples=200",
    )
    metrics = run.metrics
    robots = metrics[metrics.robot >= 0]
    assert len(robots) == 16 * 40
    assert robots.staleness.dropna().max() <= 2
    slow = robots[robots.robot == 5]
    assert slow.staleness.dropna().max() <= 2
    error = metrics[metrics.robot == -1].set_index("iteration").consensus_error
    assert error.iloc[-10:].mean() < error.iloc[1:20].max()
    where = read_log(tmp_path / "r" / "run.mcap").metadata["ray_team"]["robots"]
    assert len({place["node_id"] for place in where}) == 2
    assert actors_gone(where)
    print(
        f"\n16 robots on 2 nodes, robot 5 four times slower: {seconds:.1f} s, consensus error "
        f"{error.iloc[1:20].max():.2f} -> {error.iloc[-10:].mean():.2f}, slow robot's staleness <= "
        f"{slow.staleness.max():.0f}, CVaR {run.summary['cvar']['value']:.1f}"
    )
