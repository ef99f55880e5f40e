"""A two-node Ray cluster on this machine (tests/clusters/ray_cluster.py): a driver connects, sees both nodes, and
work pinned to each node runs there. The ground for `team.backend=ray` (one Ray actor per robot, Ray core only).

Needs `ray` (core) in this environment: `pip install 'ray>=2.9,<3'`; skipped without it. About 20 s on 2 cores
(the cluster starts in 6-18 s)."""

from __future__ import annotations

import os

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed here (pip install 'ray>=2.9,<3')")
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy  # noqa: E402

from .ray_cluster import RayCluster, _start_time  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.cluster]


@pytest.fixture(scope="module")
def cluster():
    """Two nodes (1 CPU each), and this process connected to them as the driver."""
    with RayCluster(num_nodes=2, cpus_per_node=1) as running:
        started = {pid: _start_time(pid) for pid in running.pids}
        saved = running.apply_driver_env()  # the cluster's token, for ray.init in this process
        if ray.is_initialized():
            ray.shutdown()
        try:
            ray.init(address=running.address, logging_level="ERROR", log_to_driver=False)
            yield running
        finally:
            ray.shutdown()
            running.restore_env(saved)
    # the cluster has stopped: none of the `ray start` processes it started is left
    assert not [pid for pid, start in started.items() if _start_time(pid) == start]


def alive_nodes() -> list[dict]:
    return [node for node in ray.nodes() if node["Alive"]]


@ray.remote(num_cpus=1)
class Robot:
    """A stand-in for one robot of a team: state that lives on one node, and a step that changes it."""

    def __init__(self, index: int):
        self.index, self.theta = index, 0.0

    def step(self, gradient: float) -> dict:
        self.theta += gradient
        return {
            "index": self.index,
            "theta": self.theta,
            "node": ray.get_runtime_context().get_node_id(),
            "ip": ray.util.get_node_ip_address(),
            "pid": os.getpid(),
        }


def test_the_driver_sees_two_alive_nodes_with_one_cpu_each(cluster):
    nodes = alive_nodes()
    assert len(nodes) == 2
    assert sorted(node["NodeManagerAddress"] for node in nodes) == sorted(cluster.node_ips)
    assert [node["Resources"]["CPU"] for node in nodes] == [1.0, 1.0]
    assert ray.cluster_resources()["CPU"] == 2.0


def test_an_actor_pinned_to_each_node_runs_on_that_node(cluster):
    nodes = alive_nodes()
    robots = [
        Robot.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False)).remote(i)
        for i, node in enumerate(nodes)
    ]
    first = ray.get([robot.step.remote(0.5) for robot in robots], timeout=120)
    second = ray.get([robot.step.remote(0.25) for robot in robots], timeout=120)
    assert [r["node"] for r in first] == [node["NodeID"] for node in nodes]  # each where it was pinned
    assert [r["ip"] for r in first] == [node["NodeManagerAddress"] for node in nodes]
    assert [r["theta"] for r in second] == [0.75, 0.75]  # actor state kept between calls
    assert len({r["pid"] for r in first}) == 2
    for robot in robots:
        ray.kill(robot)


def test_spread_robots_land_on_both_nodes_and_objects_cross_between_them(cluster):
    import numpy as np

    robots = [Robot.options(scheduling_strategy="SPREAD").remote(i) for i in range(2)]
    where = ray.get([robot.step.remote(0.0) for robot in robots], timeout=120)
    assert {r["node"] for r in where} == {node["NodeID"] for node in alive_nodes()}

    @ray.remote(num_cpus=0)
    def make(n: int) -> np.ndarray:  # on the worker node: a 16 MB object in that node's object store
        return np.arange(n, dtype=np.float64)

    @ray.remote(num_cpus=0)
    def total(values: np.ndarray) -> tuple[float, str]:  # on the head: the object is pulled across
        return float(values.sum()), ray.util.get_node_ip_address()

    head, other = cluster.node_ips
    ref = make.options(resources={f"node:{other}": 0.01}).remote(2_000_000)
    value, ip = ray.get(total.options(resources={f"node:{head}": 0.01}).remote(ref), timeout=120)
    assert ip == head and value == 2_000_000 * 1_999_999 / 2
    for robot in robots:
        ray.kill(robot)
