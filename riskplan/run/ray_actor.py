"""team.backend=ray, one robot in Ray, and Ray itself.

`RobotActor` (one per robot, a threaded Ray actor: max_concurrency = in-degree + 4, so receiving never waits for the
robot's loop) builds the world and kernel itself from the run's plain config (`build_setup`), and runs `RobotCore`
(`riskplan.run.ray_robot`), robot i's side of the algorithm without Ray: its loop (`run`) sends each round's message
to its out-neighbours fire-and-forget (`deliver`) and keeps each iteration's report until the driver's `drain`
acknowledges it.

Where it runs. team.address null: a local Ray instance (`ray.init` with num_cpus, no dashboard, a small object
store, no worker logs), shut down at the end; `auto` or host:port: an existing cluster (`ray.init(address=...)`
alone), the robots spread round robin over its nodes (`placements`: hard node affinity; no CPUs reserved: robots
share cores), the driver disconnecting at the end. A Ray this process has initialised already is used as it is,
whatever team.address says, and left up. A cluster that does not answer (a TCP check of host:port first, so nothing
hangs) is BadInput naming team.address, raised before anything is written. Ray is an optional extra
(`pip install 'riskplan[distributed]'`), imported only here and only when a run uses it.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import math
import os
import signal
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import numba

from riskplan.config.schema import TeamConf
from riskplan.run.build import build_setup
from riskplan.run.ray_robot import Message, RobotCore
from riskplan.util.errors import BadInput, first_line
from riskplan.version import __version__

EXTRA = "riskplan[distributed]"
OBJECT_STORE_BYTES = 100 * 1000 * 1000  # a local instance's object store (Ray's minimum is 75 MiB)
WAIT_SECONDS = 0.25  # a waiting robot looks at its stop flag this often
CONNECT_SECONDS = 5.0  # a cluster address that does not accept a TCP connection within this is unreachable


def import_ray():
    """Ray, or BadInput naming team.backend and the extra to install."""
    try:
        return importlib.import_module("ray")
    except ImportError:
        raise BadInput(
            "team.backend", f"is ray, but Ray is not installed here; pip install '{EXTRA}' (or team.backend=simulated)"
        ) from None


# --------------------------------------------------------------------------------------------- one robot, in Ray
class _Stopped(Exception):
    """The driver asked the robot to stop."""


class RobotActor:
    """One robot as a threaded Ray actor (`ray.remote(RobotActor)` in `_Team`): `run` is its loop; `deliver`,
    `drain` and `stop` run beside it on the actor's other threads."""

    def __init__(self, config: dict, robot: int, state: dict | None, threads: int):
        self.threads = int(threads)
        self.core = RobotCore(build_setup(config), robot, state)
        self.core.warm()
        self._lock = threading.Condition()
        self._stopping = threading.Event()
        self._reports: list[dict] = []
        self._peers: list[Any] = []

    def where(self) -> dict:
        """Where it runs: node id, ip, pid, riskplan's version."""
        import ray  # optional: the distributed extra; the actor runs only where Ray is

        return {
            "robot": self.core.i,
            "node_id": ray.get_runtime_context().get_node_id(),
            "ip": ray.util.get_node_ip_address(),
            "pid": os.getpid(),
            "version": __version__,
        }

    def connect(self, peers: list) -> None:
        """Its out-neighbours' actor handles."""
        self._peers = list(peers)

    def deliver(self, message: Message) -> None:
        """A neighbour's message (fire-and-forget)."""
        with self._lock:
            self.core.receive(message)
            self._lock.notify_all()

    def drain(self, after: int, wait: float) -> list[dict]:
        """Its reports of iterations `after` and later, once there is one (or after `wait` seconds, or on stop).
        The driver acknowledges the earlier ones by asking for these: they are dropped now, and a report handed
        over is kept until then, so a drain whose answer never arrives loses nothing."""
        with self._lock:
            self._reports = [r for r in self._reports if r["row"]["iteration"] >= after]
            self._lock.wait_for(lambda: self._reports or self._stopping.is_set(), timeout=wait)
            return list(self._reports)

    def stop(self) -> None:
        """Stop at the next chance (between steps, or while waiting)."""
        self._stopping.set()
        with self._lock:
            self._lock.notify_all()

    def run(self, total: int) -> dict:
        """Its iterations up to `total`; {"robot", "iteration", "stopped"}."""
        numba.set_num_threads(max(1, min(self.threads, numba.config.NUMBA_NUM_THREADS)))  # this thread's kernels
        try:
            while self.core.iteration < total:
                self._iteration(self.core.iteration)
        except _Stopped:
            return {"robot": self.core.i, "iteration": self.core.iteration, "stopped": True}
        return {"robot": self.core.i, "iteration": self.core.iteration, "stopped": False}

    def _iteration(self, l: int) -> None:
        core = self.core
        started = time.perf_counter()
        step = core.compute(l)
        compute = time.perf_counter() - started
        if core.speed > 1.0 and self._stopping.wait((core.speed - 1.0) * compute):
            raise _Stopped
        value, carried, eps = core.begin(step)
        worst, waited = math.nan, 0.0
        for r in range(core.rounds):
            with self._lock:
                message = core.send(l, r, value, carried)
            if message is not None:
                for peer in self._peers:
                    peer.deliver.remote(message)  # fire-and-forget: its result is never asked for
            since = time.perf_counter()
            with self._lock:
                while core.waiting_for(l, r):
                    if self._stopping.is_set():
                        raise _Stopped
                    self._lock.wait(WAIT_SECONDS)
                value, carried, staleness = core.mix(l, r, value, carried)
            waited += time.perf_counter() - since
            worst = _larger(worst, staleness)
        with self._lock:
            row = core.finish(step, value, carried, eps, worst, time.perf_counter() - started)
            self._reports.append(
                {"row": row, "z": step.z, "grad": step.grad, "state": core.state(), "compute": compute, "wait": waited}
            )
            self._lock.notify_all()
        if self._stopping.is_set():
            raise _Stopped


def _larger(a: float, b: float) -> float:
    """The larger of two numbers of which either may be NaN (none)."""
    return b if math.isnan(a) else a if math.isnan(b) else max(a, b)


# --------------------------------------------------------------------------------------------- Ray itself
def placements(ray, robots: int) -> list:
    """Where each robot's actor goes: round robin over the cluster's alive nodes that offer CPUs (all alive nodes
    when none does), as a hard node affinity; a single node gets SPREAD. Ray's own SPREAD strategy spreads actors
    that reserve no CPU only as a best effort (three robots on two nodes may all scan on one), and a soft affinity
    was seen to put them on the wrong node (Ray 2.60: all on the head, or each on the other node), so the spread is
    made explicit. An actor needs no resources, so it fits any alive node; a node that dies before its actor starts
    fails the start with one line."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy  # optional: the distributed extra

    alive = [node for node in ray.nodes() if node.get("Alive")]
    working = [node for node in alive if node.get("Resources", {}).get("CPU", 0) > 0] or alive
    nodes = sorted(node["NodeID"] for node in working)
    if len(nodes) < 2:
        return ["SPREAD"] * robots
    return [NodeAffinitySchedulingStrategy(nodes[i % len(nodes)], soft=False) for i in range(robots)]


def _reachable(address: str) -> str:
    """The address a driver would connect to (auto: the one Ray finds), after a TCP check; BadInput otherwise."""
    resolved = address
    if address == "auto":
        try:
            from ray._private.services import get_ray_address_from_environment  # optional: the distributed extra

            resolved = get_ray_address_from_environment("auto", None)
        except Exception as err:  # Ray's own words: no running cluster found
            raise BadInput(
                "team.address",
                f"is auto, but no running Ray cluster was found ({first_line(err)}); start one (ray start --head) "
                f"or give team.address=null for a local Ray instance",
            ) from None
    if resolved.startswith("ray://") or resolved == "auto":
        return resolved
    host, _, port = resolved.rpartition(":")
    if not host or not port.isdigit():
        raise BadInput("team.address", f"got {address!r}; expected auto or host:port of a Ray cluster's head")
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_SECONDS):
            pass
    except OSError as err:
        raise BadInput(
            "team.address",
            f"got {address}: no Ray cluster answers at {resolved} ({err.strerror or type(err).__name__}); start one "
            f"(ray start --head) or give team.address=null for a local Ray instance",
        ) from None
    return resolved


@contextlib.contextmanager
def ray_runtime(team: TeamConf) -> Iterator[Any]:
    """Ray, initialised for this run: a local instance (team.address null) or a connection to a cluster, shut down
    (or disconnected) on the way out; a Ray this process had initialised already is used as it is and left up."""
    ray = import_ray()
    owned = not ray.is_initialized()
    # ray.init makes SIGTERM call sys.exit and leaves it so after shutdown; this process's handler comes back
    handler = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    if owned:
        if team.address is None:
            ray.init(
                address="local",
                num_cpus=os.cpu_count() or 1,
                include_dashboard=False,
                object_store_memory=OBJECT_STORE_BYTES,
                log_to_driver=False,
                logging_level=logging.ERROR,
                ignore_reinit_error=True,
            )
        else:
            _reachable(team.address)
            try:
                ray.init(address=team.address)
            except (ConnectionError, RuntimeError, ValueError, TimeoutError) as err:
                raise BadInput(
                    "team.address",
                    f"got {team.address}: cannot connect to a Ray cluster there ({first_line(err)})",
                ) from None
    try:
        yield ray
    finally:
        if owned:
            ray.shutdown()
        if handler is not None:
            signal.signal(signal.SIGTERM, handler)


__all__ = ["RobotActor", "import_ray", "placements", "ray_runtime"]
