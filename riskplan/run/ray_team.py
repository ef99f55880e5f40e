"""team.backend=ray: each robot a Ray actor, and the asynchrony of paper eq. (14) real, bounded as Assumption 5 says.

The simulated backend (`riskplan.run.training`) steps every robot in lockstep and simulates delays and drops; here
each robot runs its own loop in its own process, on any node of a Ray cluster, and the wall clock decides which
neighbour values it mixes. Ray is an optional extra (`pip install 'riskplan[distributed]'`), imported only here and
only when a run uses it.

Robots. `RobotActor` (one per robot, a threaded Ray actor: max_concurrency = in-degree + 4, so receiving never waits
for the robot's loop) builds the world and kernel itself from the run's plain config (`build_setup`), and runs
`RobotCore`, robot i's side of the algorithm without Ray. Iteration l of robot i:
  1. W_l episodes at its own theta^i_l from its own stream (`rng.stream_key(seed, rng.TRAIN, l, i)`: the key the
     simulated team gives robot i, so its episodes do not depend on scheduling), and its gradient for its own risk
     node (team.risk): riskplan.engine.step's `rollouts` and `estimate` for robot i alone;
  2. a robot with team.speeds factor s > 1 sleeps (s - 1) x that compute time (uneven hardware);
  3. for each consensus round r: it sends its value (theta, or theta + eps Delta for adapt_then_combine; with
     gradient tracking also its running sums) to its out-neighbours, fire-and-forget (`deliver`), then waits until
     each in-neighbour's newest round-r message has iteration >= l - team.staleness, and mixes its own row;
  4. theta^i_{l+1} by team.order, exactly as `engine.step.consensus_step` composes it, and the step's checks; a report (its metrics row, its
     episodes' total rewards and gradient, its state after the iteration) waits for the driver.

Messages. `Message(sender, iteration, round, theta, sums)`: theta the value sent (what `faulty.sent_value` makes of
it for a robot of team.faults), sums the sender's running sums S^j = [sum of y, sum of v] of the round (gradient
tracking) or None. Calls to a threaded actor may run out of order; the stamps sort them out.

Mixing, one row (the rules of `engine.team.mixer.Mixer`, for robot i alone). Robot i keeps, per round and
in-neighbour j, the newest message received (`latest`), the newest one that arrived since its last mix
(`pending`, stale=arrival; a message no newer than one already mixed never replaces anything) and, for gradient
tracking, rho^{ij}, the newest S^j taken in. A link mixes its candidate (stale=arrival: pending; stale=latest:
latest) only if that message's iteration is >= l - team.staleness; a link with nothing to offer hands its weight
a^{ij} to robot i itself (`kernels.mix_numpy`'s rule); team.aggregate other than mean goes through
`resilience.aggregate_row` with the same own weight. Gradient tracking mixes a^{ii} [y, v] + sum_j a^{ij} (S^j -
rho^{ij}) over the links holding a newer S^j: late mass is never lost nor counted twice (`tracking_balance` checks
sum_i y^i + the mass in flight = sum_i Delta^i).

Waiting and staleness (Assumption 5 (3)-(4), enforced). Before mixing round r of iteration l, robot i waits until
every in-neighbour's newest round-r message has iteration >= l - team.staleness; a neighbour that crashes by
team.faults (kind=crash, from F) is not waited for once l - staleness >= F (it will never send again). Each robot
sends before it waits, so the robot furthest behind can always go on: no deadlock. The `staleness` column of
metrics.parquet is, per robot and iteration, the largest l - t over the messages it mixed (t their iterations; NaN
when it mixed none, negative when a neighbour was ahead), hence <= team.staleness in every row.

Rows and the log. The driver (this process) takes the reports (`drain(after, wait)`, a call that returns as soon as
a report of iteration `after` or later is there, or after a second; the robot keeps a report until a later drain
acknowledges it, so an answer the driver never reads loses nothing) and logs each robot's row to run.mcap as it
comes, with the wall-clock time it was logged
(consensus_error null: a team figure, not known yet). Once every robot has finished iteration l it logs the network
average row (robot -1: the healthy robots' pooled episodes, as in the simulated backend) and the iteration's
/consensus_error message, which marks it complete. metrics.parquet holds the same columns as the simulated
backend's, plus `staleness`; each robot row gets its iteration's consensus error there. summary.json says
`deterministic: false`, and the MCAP metadata "ray_team" where each robot ran (node id, ip, pid).

Checkpoints. Every report carries the robot's state after its iteration, so the driver holds a short history of
each. Every train.checkpoint_every team iterations (and at the end, on a signal, and on a failure) it writes the
newest consistent cut of them (`consistent_cut`: no robot holds a message from a neighbour's iteration after that
neighbour's own checkpoint) as one atomically replaced file (`checkpoint.save_team_checkpoint`), with the rows of
the iterations not every robot has finished. Resume starts every actor from its own checkpoint; the messages that
were in flight are lost, which the running sums of gradient tracking absorb and the waiting rule replaces.

A robot actor that dies (its process killed, its node lost) stops the whole run: the driver writes the last
consistent cut of every robot's state (the dead robot's last report included), stops the other actors and fails with
one line naming the robot (`TeamFailure`, exit 1); `riskplan train --resume` restarts all actors from their
checkpoints. Why not carry on without it, as a crash of team.faults: the dead robot took state nobody else has (its
share of the gradient-tracking mass, the messages it had received), so the survivors would run a different algorithm
than the config says, and the run could not be resumed to what it should have been; crashes as a studied fault are
what team.faults is for. Ctrl-C or SIGTERM: the driver stops the actors, writes the cut, and stops with
`Interrupted` (status interrupted, exit 130 or 143); Ctrl-C in a terminal also reaches the local Ray instance's own
processes (they share the driver's process group), and the actors that die of it then are part of the same stop.

Where it runs. team.address null: a local Ray instance (`ray.init` with num_cpus, no dashboard, a small object
store, no worker logs), shut down at the end; `auto` or host:port: an existing cluster (`ray.init(address=...)`
alone), the robots spread round robin over its nodes (`_placements`: hard node affinity; no CPUs reserved: robots
share cores), the driver disconnecting at the end. A Ray this process has initialised already is used as it is,
whatever team.address says, and left up. Every node needs riskplan (the same version: checked) installed. Each
robot's kernels use max(1, cluster CPUs // robots) numba threads. A cluster that does not answer (a TCP check of
host:port first, so nothing hangs) is BadInput naming team.address, raised before anything is written: the Python
API raises it, `riskplan train` reports it as a failed run in one line (exit 1). Whatever stops the run, every actor
it started is killed before it returns, and a local instance is shut down.
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
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numba
import numpy as np

from riskplan.config.schema import Aggregate, FaultKind, Order, Stale, TeamConf
from riskplan.engine.rollout import simulate
from riskplan.engine.schedules import step_size
from riskplan.engine.step import (
    NumericalTrouble,
    Setup,
    check_step,
    estimate,
    rollouts,
    starts,
    team_statistics,
)
from riskplan.engine.team import faulty, resilience
from riskplan.engine.team.convergence import consensus_error
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import State, TeamCheckpoint, load_team_checkpoint, save_team_checkpoint
from riskplan.run.columns import Columns, from_rows, sorted_by
from riskplan.run.evaluation import evaluate, robot_risks, sample_paths, summarize
from riskplan.run.record import AVERAGE, RunLog, average_row, metrics_row
from riskplan.run.run_directory import logged_rows, reopen_log, start_log, write_finished
from riskplan.run.run_files import has_finished
from riskplan.util.errors import BadInput
from riskplan.util.interrupt import Interrupted, StopSignals
from riskplan.version import __version__

EXTRA = "riskplan[distributed]"
OBJECT_STORE_BYTES = 100 * 1000 * 1000  # a local instance's object store (Ray's minimum is 75 MiB)
POLL_SECONDS = 0.2  # the driver looks at signals and finished actors this often
DRAIN_SECONDS = 1.0  # an actor's drain call returns after this long when it has nothing to report
WAIT_SECONDS = 0.25  # a waiting robot looks at its stop flag this often
START_SECONDS = 900.0  # actors that are not all up by then (a cluster without room for them) fail the run
STOP_SECONDS = 5.0  # after a stop, reports still arriving within this are taken
CONNECT_SECONDS = 5.0  # a cluster address that does not accept a TCP connection within this is unreachable
STATE_KEYS = (  # robot i's state: the checkpoint's arrays, in this order
    "iteration",  # () int: the next iteration it runs
    "theta",  # (M,)
    "latest_sent",  # (R, K) int: per round and in-neighbour, the iteration of the newest message received, -1: none
    "latest",  # (R, K, M): its theta
    "latest_sums",  # (R, K, 2M): its running sums (gradient tracking)
    "pending_sent",  # (R, K) int: the newest message that arrived since the last mix, -1: none (stale=arrival)
    "pending",  # (R, K, M)
    "mixed_sent",  # (R, K) int: the iteration of the last message mixed per link, -1: none
    "sums",  # (R, 2M): S^i, the running sums robot i has sent per round
    "seen_sums",  # (R, K, 2M): rho^{ij}, the newest S^j taken in
    "seen_sent",  # (R, K) int: its iteration, -1: none
    "tracker",  # (2M,): [z^i, v^i], the mixed tracker and push-sum weight
    "gradient",  # (M,): Delta^i of its last iteration
    "stuck_theta",  # (M,): what a stuck robot (team.faults) sends, once frozen
    "stuck_since",  # () int: the iteration it froze at, -1: not (yet)
)


class TeamFailure(NumericalTrouble):
    """The ray team stopped: a robot's actor died or failed. Every robot's last consistent state is checkpointed
    (a NumericalTrouble, so that every caller reports it in one line, exit 1, and keeps the checkpoint)."""


class Message(NamedTuple):
    """What robot `sender` sends in round `round` of its iteration `iteration`."""

    sender: int
    iteration: int
    round: int
    theta: np.ndarray  # (M,)
    sums: np.ndarray | None  # (2M,): S^sender of the round (gradient tracking), else None


class Step(NamedTuple):
    """A robot's rollouts and gradient at iteration l."""

    iteration: int
    z: np.ndarray  # (W,) total rewards
    grad: np.ndarray  # (M,)
    level: float  # beta_l
    stats: dict  # mean, cvar, value_at_risk, std, objective of its episodes
    samples: int


def import_ray():
    """Ray, or BadInput naming team.backend and the extra to install."""
    try:
        return importlib.import_module("ray")
    except ImportError:
        raise BadInput(
            "team.backend", f"is ray, but Ray is not installed here; pip install '{EXTRA}' (or team.backend=simulated)"
        ) from None


# --------------------------------------------------------------------------------------------- one robot, no Ray
def rounds_of(setup: Setup) -> int:
    """Consensus rounds per iteration: team.consensus_rounds in a team, none for a robot alone."""
    return setup.params.team.consensus_rounds if setup.team else 0


def in_neighbours(setup: Setup, robot: int) -> list[int]:
    """The robots j whose messages robot i mixes (adjacency[i, j]: j sends to i), in order of j."""
    return [int(j) for j in np.flatnonzero(setup.network.adjacency[robot])]


def out_neighbours(setup: Setup, robot: int) -> list[int]:
    """The robots k that mix robot i's messages."""
    return [int(k) for k in np.flatnonzero(setup.network.adjacency[:, robot])]


def initial_state(setup: Setup, robot: int) -> dict[str, np.ndarray]:
    """Robot i's state before its first iteration (also the shapes and dtypes its checkpoint must have)."""
    r, k, m = rounds_of(setup), len(in_neighbours(setup, robot)), setup.network.n_params
    none = np.full((r, k), -1, dtype=np.int64)
    return {
        "iteration": np.array(0, dtype=np.int64),
        "theta": np.array(setup.theta0, dtype=float),
        "latest_sent": none.copy(),
        "latest": np.zeros((r, k, m)),
        "latest_sums": np.zeros((r, k, 2 * m)),
        "pending_sent": none.copy(),
        "pending": np.zeros((r, k, m)),
        "mixed_sent": none.copy(),
        "sums": np.zeros((r, 2 * m)),
        "seen_sums": np.zeros((r, k, 2 * m)),
        "seen_sent": none.copy(),
        "tracker": np.concatenate([np.zeros(m), np.ones(m)]),
        "gradient": np.zeros(m),
        "stuck_theta": np.zeros(m),
        "stuck_since": np.array(-1, dtype=np.int64),
    }


class RobotCore:
    """Robot i's side of the algorithm, without Ray or threads: its rollouts and gradient, what it sends, what it
    takes in, whether it may mix, its row of the mix, its step, and its state (`state`, `initial_state`).
    `RobotActor` calls it under one lock; tests may drive it by hand."""

    def __init__(self, setup: Setup, robot: int, state: dict[str, np.ndarray] | None = None):
        self.setup, self.i = setup, int(robot)
        params, network = setup.params, setup.network
        team: TeamConf = params.team
        self.m = network.n_params
        self.ins = in_neighbours(setup, robot)
        self.slot = {j: k for k, j in enumerate(self.ins)}
        self.rounds = rounds_of(setup)
        self.order = Order(team.order)
        self.latest_rule = team.stale == Stale.latest
        self.staleness = int(team.staleness)
        self.aggregate, self.trim = Aggregate(team.aggregate), int(team.trim)
        self.own_weight = np.array(network.weights[robot, robot], dtype=float)  # (M,) a^{ii}
        self.in_weights = np.array(network.weights[robot, self.ins], dtype=float).reshape(len(self.ins), self.m)
        faults = setup.mixer.faults
        self.fault = next((f for f in faults if f.robot == robot), None)
        self.crash_from = {f.robot: f.start for f in faults if f.kind == FaultKind.crash and f.robot in self.slot}
        self.risk = robot_risks(params)[robot]
        self.start = np.asarray(starts(setup)[robot : robot + 1])
        self.speed = float(team.speeds[robot]) if team.speeds else 1.0
        self.seed = setup.mixer.seed
        base = initial_state(setup, robot)
        self.s = base if state is None else {k: np.array(state[k], dtype=v.dtype, copy=True) for k, v in base.items()}
        self._direction: np.ndarray | None = None

    @property
    def iteration(self) -> int:
        """The next iteration it runs."""
        return int(self.s["iteration"])

    @property
    def theta(self) -> np.ndarray:
        return self.s["theta"]

    def state(self) -> dict[str, np.ndarray]:
        """A copy of its state (a checkpoint's arrays)."""
        return {k: np.array(v, copy=True) for k, v in self.s.items()}

    def warm(self) -> None:
        """Load the episode kernel from numba's cache (one episode, a throwaway key): the actor does it while it
        starts, so that its first iteration's time is the iteration's own (as `training.load_kernels`)."""
        simulate(self.setup.world, self.setup.kernel, self.theta[None], self.start, np.zeros(1, dtype=np.uint64), 1)

    # -- step 1: rollouts and gradient
    def compute(self, l: int) -> Step:
        """W_l episodes at its theta from its own stream, and its gradient for its own risk node: steps 1-3 of
        riskplan.engine.step for robot i alone."""
        z, scores = rollouts(self.setup, l, self.theta[None], robots=[self.i])
        own = estimate(self.setup, l, z, scores, robots=[self.i], where=f"robot {self.i}")
        stats = {k: float(v[0]) for k, v in own.stats.items()}
        return Step(l, own.z[0], own.grads[0], float(own.levels[0]), stats, own.episodes)

    # -- step 3: the consensus rounds
    def begin(self, step: Step) -> tuple[np.ndarray, np.ndarray | None, float]:
        """The value its first round sends and the tracker it carries (gradient tracking), and eps_l."""
        eps = step_size(step.iteration, self.setup.params.train.step_size)
        theta = self.theta.copy()
        if self.rounds == 0:  # alone: eq. (11)
            self._direction = step.grad
            return theta, None, eps
        if self.order == Order.adapt_then_combine:
            self._direction = None
            return theta + eps * step.grad, None, eps
        if self.order == Order.gradient_tracking:
            m = self.m
            tracker = self.s["tracker"][:m] + (step.grad - self.s["gradient"])
            mass = self.s["tracker"][m:]
            self._direction = tracker / mass  # y_l / v_l: the direction of the step (Mixer.track)
            return theta, np.concatenate([tracker, mass]), eps
        self._direction = step.grad
        return theta, None, eps

    def send(self, l: int, r: int, value: np.ndarray, carried: np.ndarray | None) -> Message | None:
        """The message of round r (None when it sends nothing: a crashed robot of team.faults); its running sums
        grow by what it carries."""
        frozen = None
        fault = self.fault
        if fault is not None and fault.kind == FaultKind.stuck and l >= fault.start:
            if int(self.s["stuck_since"]) < 0:  # its first send since the fault started: frozen here
                self.s["stuck_theta"][:] = value
                self.s["stuck_since"] = np.array(l, dtype=np.int64)
            frozen = self.s["stuck_theta"]
        sent = faulty.sent_value(fault, value, self.seed, l, r, frozen)
        sums = None
        if carried is not None:
            self.s["sums"][r] += carried
            sums = self.s["sums"][r].copy()
        if sent is None:
            return None
        return Message(self.i, int(l), int(r), np.array(sent, dtype=float, copy=True), sums)

    def receive(self, message: Message) -> None:
        """Take in a neighbour's message: the link's newest, and (stale=arrival) its newest arrival since the last
        mix unless a message at least as new was mixed already."""
        k = self.slot.get(int(message.sender))
        if k is None or not 0 <= message.round < self.rounds:
            return
        r, t = int(message.round), int(message.iteration)
        s = self.s
        if t > s["latest_sent"][r, k]:
            s["latest_sent"][r, k] = t
            s["latest"][r, k] = message.theta
            if message.sums is not None:
                s["latest_sums"][r, k] = message.sums
        if t > max(s["pending_sent"][r, k], s["mixed_sent"][r, k]):
            s["pending_sent"][r, k] = t
            s["pending"][r, k] = message.theta

    def waiting_for(self, l: int, r: int) -> list[int]:
        """The in-neighbours whose newest round-r message is older than l - team.staleness (none: it may mix).
        A neighbour that crashes by team.faults from F is not waited for once l - staleness >= F."""
        floor = l - self.staleness
        if floor < 0:
            return []
        newest = self.s["latest_sent"][r]
        return [
            j
            for k, j in enumerate(self.ins)
            if newest[k] < floor and not (j in self.crash_from and floor >= self.crash_from[j])
        ]

    def mix(self, l: int, r: int, value: np.ndarray, carried: np.ndarray | None):
        """Its row of round r: (mixed value, mixed tracker or None, the largest staleness l - t it mixed or NaN)."""
        s = self.s
        floor = l - self.staleness
        sent = np.array(s["latest_sent"][r] if self.latest_rule else s["pending_sent"][r])  # a copy: cleared below
        values = s["latest"][r] if self.latest_rule else s["pending"][r]
        use = (sent >= 0) & (sent >= floor)
        own_weight = self.own_weight + self.in_weights[~use].sum(axis=0)  # idle links' weights go to robot i
        if self.aggregate == Aggregate.mean:
            mixed = own_weight * value + (self.in_weights[use] * values[use]).sum(axis=0)
        else:
            mixed = resilience.aggregate_row(
                self.aggregate, value, values[use], self.in_weights[use], own_weight, self.trim
            )
        if not self.latest_rule:  # what arrived is used up (too old or not)
            s["mixed_sent"][r] = np.where(use, sent, s["mixed_sent"][r])
            s["pending_sent"][r] = -1
        staleness = float((l - sent[use]).max()) if use.any() else math.nan
        if carried is not None:
            carried = self._mix_sums(r, carried)
        return mixed, carried, staleness

    def _mix_sums(self, r: int, carried: np.ndarray) -> np.ndarray:
        """a^{ii} [y, v] + sum_j a^{ij} (S^j - rho^{ij}) over the links whose newest S^j is newer than rho^{ij}."""
        s = self.s
        fresh = s["latest_sent"][r] > s["seen_sent"][r]
        increment = np.where(fresh[:, None], s["latest_sums"][r] - s["seen_sums"][r], 0.0)
        s["seen_sums"][r][fresh] = s["latest_sums"][r][fresh]
        s["seen_sent"][r] = np.where(fresh, s["latest_sent"][r], s["seen_sent"][r])
        weights = np.concatenate([self.in_weights, self.in_weights], axis=1)
        return np.concatenate([self.own_weight] * 2) * carried + (weights * increment).sum(axis=0)

    # -- step 4: the step
    def finish(
        self, step: Step, value: np.ndarray, carried: np.ndarray | None, eps: float, staleness: float, seconds: float
    ) -> dict:
        """theta_{l+1} from the mixed value (team.order), the state moved to iteration l + 1; its metrics row."""
        l = step.iteration
        theta = self.theta.copy()
        new = value if self._direction is None else value + eps * self._direction
        check_step(self.setup, l, theta, step.grad, new, who=f"robot {self.i}")
        if carried is not None:
            self.s["tracker"] = np.array(carried, dtype=float)
            self.s["gradient"] = np.array(step.grad, dtype=float)
        self.s["theta"] = np.array(new, dtype=float)
        self.s["iteration"] = np.array(l + 1, dtype=np.int64)
        healthy = bool(self.setup.mixer.healthy(l)[self.i])
        return metrics_row(
            l,
            self.i,
            step.stats,
            theta,
            step.grad,
            eps,
            math.nan,
            step.samples,
            seconds,
            step.level,
            healthy,
            staleness=float(staleness),
        )


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


# --------------------------------------------------------------------------------------------- the team, from here
def consistent_cut(histories: list[list[dict]], ins: list[list[int]]) -> list[int] | None:
    """Per robot, the index of its newest state in `histories` (each oldest first) such that no robot holds a
    message of a neighbour's iteration after that neighbour's chosen state (its `latest_sent` <= the sender's
    iteration - 1): the greatest consistent cut. None when the histories hold none."""
    index = [len(h) - 1 for h in histories]
    changed = True
    while changed:
        changed = False
        for i, senders in enumerate(ins):
            while True:
                state = histories[i][index[i]]
                heard = state["latest_sent"].max(axis=0) if state["latest_sent"].size else []
                if all(heard[k] <= int(histories[j][index[j]]["iteration"]) - 1 for k, j in enumerate(senders)):
                    break
                if index[i] == 0:
                    return None
                index[i] -= 1
                changed = True
    return index


def tracking_balance(setup: Setup, states: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Gradient tracking's invariant over a consistent cut of the robots' states: (sum_i [y^i, v^i] + the mass in
    flight sum_{r, i, j} a^{ij} (S^j_r - rho^{ij}_r), [sum_i Delta^i, N]); equal up to rounding."""
    m, weights = setup.network.n_params, setup.network.weights
    held = sum(np.asarray(state["tracker"], dtype=float) for state in states)
    for i, state in enumerate(states):
        for k, j in enumerate(in_neighbours(setup, i)):
            owed = states[j]["sums"] - state["seen_sums"][:, k]  # (R, 2M)
            held = held + (np.concatenate([weights[i, j]] * 2)[None] * owed).sum(axis=0)
    want = np.concatenate(
        [sum(np.asarray(state["gradient"], dtype=float) for state in states), np.full(m, len(states))]
    )
    return held, want


class _RobotDied(Exception):
    def __init__(self, robot: int, detail: str):
        self.robot, self.detail = robot, detail


class _RobotFailed(Exception):
    def __init__(self, robot: int, cause: BaseException):
        self.robot, self.cause = robot, cause


class _Team:
    """The driver's side: the actors, their reports, the log, the checkpoints."""

    def __init__(self, ray, setup: Setup, out: Path, log: RunLog, states: list[dict], pending: list[dict], rows):
        self.ray, self.setup, self.out, self.log = ray, setup, out, log
        self.n = setup.robots
        self.ins = [in_neighbours(setup, i) for i in range(self.n)]
        self.history: list[list[dict]] = [[state] for state in states]
        self.reached = [int(state["iteration"]) for state in states]  # per robot: its next iteration, as reported
        self.partial: dict[int, dict[int, dict]] = {}  # iteration -> robot -> report (row, z, grad)
        self.rows: list[dict] = list(rows)
        self.actors: list = []
        self.where: list[dict] = []
        self.timing = [{"iterations": 0, "compute": 0.0, "wait": 0.0, "seconds": 0.0} for _ in range(self.n)]
        self.balance = 0.0  # gradient tracking: the largest |residual| of the invariant over the cuts written
        self.every = setup.params.train.checkpoint_every
        self.next_checkpoint = (min(self.reached) // self.every + 1) * self.every
        self.progress: Callable | None = None
        self.cut = [h[0] for h in self.history]  # the last consistent cut written (at first: where it starts)
        self.started = time.perf_counter()  # when the actors were all up (start)
        self.startup = 0.0  # seconds from creating the actors to all of them up and connected
        for entry in pending:
            row = entry["row"]
            log.rows([row])
            self.rows.append(row)
            self.partial.setdefault(int(row["iteration"]), {})[int(row["robot"])] = entry

    # -- the actors
    def start(self, stop: StopSignals) -> None:
        """One actor per robot (spread over the nodes, no CPUs reserved), connected to its out-neighbours."""
        ray, setup = self.ray, self.setup
        began = time.perf_counter()
        actor = ray.remote(RobotActor)
        cpus = int(ray.cluster_resources().get("CPU", 1)) or 1
        threads = max(1, cpus // self.n)
        places = _placements(ray, self.n)
        for i in range(self.n):
            self.actors.append(
                actor.options(
                    num_cpus=0,
                    max_concurrency=len(self.ins[i]) + 4,
                    scheduling_strategy=places[i],
                    max_restarts=0,
                    max_task_retries=0,
                ).remote(setup.config, i, self.history[i][-1], threads)
            )
        self.where = self._get([a.where.remote() for a in self.actors], stop, START_SECONDS)
        for place in self.where:
            if place["version"] != __version__:
                raise BadInput(
                    "team.address",
                    f"robot {place['robot']} runs on {place['ip']} with riskplan {place['version']}, this driver has "
                    f"{__version__}; install the same riskplan on every node",
                )
        peers = [[self.actors[k] for k in out_neighbours(setup, i)] for i in range(self.n)]
        self._get([a.connect.remote(p) for a, p in zip(self.actors, peers)], stop, START_SECONDS)
        self.startup = time.perf_counter() - began
        speeds = setup.params.team.speeds
        self.log.metadata(
            "ray_team",
            {
                "robots": [
                    {**place, "speed": float(speeds[place["robot"]]) if speeds else 1.0, "threads": threads}
                    for place in self.where
                ],
                "nodes": sorted({place["node_id"] for place in self.where}),
                "staleness": setup.params.team.staleness,
                "ray": ray.__version__,
            },
        )

    def _get(self, refs: list, stop: StopSignals, seconds: float) -> list:
        """ray.get of refs made of actor calls, a few at a time so that a signal is seen; a dead actor is
        _RobotDied."""
        deadline = time.monotonic() + seconds
        waiting = list(refs)
        while waiting:
            if stop.received is not None:
                raise _Interrupt
            if time.monotonic() > deadline:
                raise TeamFailure(
                    f"the {self.n} robot actors did not all start within {seconds:.0f} s; is there room for them "
                    f"on the Ray cluster?"
                )
            _, waiting = self.ray.wait(waiting, num_returns=len(waiting), timeout=POLL_SECONDS)
        return [self._result(ref, i) for i, ref in enumerate(refs)]

    def run(self, stop: StopSignals, total: int) -> None:
        """Every robot's iterations up to `total`, their reports logged and checkpointed as they come."""
        ray = self.ray
        calls = {a.run.remote(total): ("run", i) for i, a in enumerate(self.actors)}
        calls |= {a.drain.remote(self.reached[i], DRAIN_SECONDS): ("drain", i) for i, a in enumerate(self.actors)}
        running = set(range(self.n))
        while running:
            if stop.received is not None:
                raise _Interrupt
            ready, _ = ray.wait(list(calls), num_returns=len(calls), timeout=POLL_SECONDS)
            for ref in ready:
                kind, i = calls.pop(ref)
                value = self._result(ref, i)
                if kind == "run":
                    running.discard(i)
                    continue
                self.take(i, value)
                if i in running:
                    calls[self.actors[i].drain.remote(self.reached[i], DRAIN_SECONDS)] = ("drain", i)
            if min(self.reached) >= self.next_checkpoint:
                self.checkpoint()
        for ref, (_, i) in calls.items():  # every robot has finished: the drains still out, then one more each
            self.take(i, self._result(ref, i))
        last = [a.drain.remote(self.reached[i], 0.0) for i, a in enumerate(self.actors)]
        for i, ref in enumerate(last):
            self.take(i, self._result(ref, i))

    def _result(self, ref, i: int):
        """ray.get of robot i's call: _RobotDied when its actor died, _RobotFailed when the call raised."""
        try:
            return self.ray.get(ref)
        except self.ray.exceptions.RayActorError as err:
            raise _RobotDied(i, _first_line(err)) from None
        except self.ray.exceptions.RayTaskError as err:
            raise _RobotFailed(i, getattr(err, "cause", err)) from None

    def collect(self, seconds: float) -> None:
        """The reports the actors still hold (after a stop): whatever arrives within `seconds`."""
        ray = self.ray
        calls = {a.drain.remote(self.reached[i], 0.0): i for i, a in enumerate(self.actors)}
        ready, _ = ray.wait(list(calls), num_returns=len(calls), timeout=seconds)
        for ref in ready:
            with contextlib.suppress(Exception):
                self.take(calls[ref], ray.get(ref))

    def kill(self) -> None:
        """Kill every actor it started, whatever it is doing."""
        for a in self.actors:
            with contextlib.suppress(Exception):
                self.ray.kill(a, no_restart=True)
        self.actors = []

    # -- reports, rows, checkpoints
    def take(self, i: int, reports: list[dict]) -> None:
        """Robot i's reports: its rows logged, its states kept, the iterations every robot finished completed."""
        for report in reports:
            row = report["row"]
            l = int(row["iteration"])
            if l < self.reached[i]:  # already taken (a report seen twice)
                continue
            if l > self.reached[i]:  # drains hand reports over until they are acknowledged: never a gap
                raise RuntimeError(f"robot {i} reported iteration {l} before {self.reached[i]}")
            self.log.rows([row])
            self.rows.append(row)
            self.history[i].append(report["state"])
            self.reached[i] = l + 1
            timing = self.timing[i]
            timing["iterations"] += 1
            timing["compute"] += report["compute"]
            timing["wait"] += report["wait"]
            timing["seconds"] += row["seconds"]
            self.partial.setdefault(l, {})[i] = {"row": row, "z": report["z"], "grad": report["grad"]}
            if len(self.partial[l]) == self.n:
                self.complete(l)

    def complete(self, l: int) -> None:
        """Iteration l, which every robot has finished: its network average row (a team) and its mark."""
        setup, params = self.setup, self.setup.params
        entries = [self.partial[l][i] for i in range(self.n)]
        healthy = setup.mixer.healthy(l)
        ok = [i for i in range(self.n) if healthy[i]]
        thetas = np.array([[e["row"][f"theta_{j}"] for j in range(setup.network.n_params)] for e in entries])
        error = consensus_error(thetas[ok]) if setup.team else math.nan
        rows = []
        if setup.team:
            objectives = np.array([e["row"]["objective"] for e in entries])
            team = team_statistics(setup, l, np.stack([e["z"] for e in entries]), objectives)
            levels = np.array([e["row"]["beta_l"] for e in entries])
            grads = np.array([e["grad"] for e in entries])
            stale = [e["row"]["staleness"] for e in entries if not math.isnan(e["row"]["staleness"])]
            first, seconds = entries[0]["row"], max(e["row"]["seconds"] for e in entries)
            rows.append(
                average_row(
                    l,
                    team,
                    thetas,
                    grads,
                    levels,
                    healthy,
                    first["step_size"],
                    error,
                    first["samples"],
                    seconds,
                    staleness=float(max(stale)) if stale else math.nan,
                )
            )
        self.log.rows(rows, (l, error))
        self.rows.extend(rows)
        if self.progress is not None:
            self.progress(l + 1, params.train.iterations, rows[-1] if rows else entries[0]["row"])

    def checkpoint(self) -> None:
        """The newest consistent cut of the robots' states, with the rows of the iterations not every robot of it
        has finished, written atomically after the log is synced."""
        index = consistent_cut(self.history, self.ins)
        if index is None:  # cannot happen: the oldest states kept are the last cut written
            return
        cut = [h[k] for h, k in zip(self.history, index)]
        self.history = [h[k:] for h, k in zip(self.history, index)]
        reached = [int(state["iteration"]) for state in cut]
        low = min(reached)
        pending = [
            entry
            for l, robots in sorted(self.partial.items())
            if l >= low
            for i, entry in sorted(robots.items())
            if l < reached[i]
        ]
        if self.setup.params.team.order == Order.gradient_tracking and self.setup.team:
            held, want = tracking_balance(self.setup, cut)
            self.balance = max(self.balance, float(np.max(np.abs(held - want))))
        self.log.sync()
        save_team_checkpoint(self.out, cut, pending)
        self.partial = {l: robots for l, robots in self.partial.items() if l >= low}
        self.next_checkpoint = (low // self.every + 1) * self.every
        self.cut = cut

    def final_thetas(self) -> np.ndarray:
        return np.array([h[-1]["theta"] for h in self.history])


def _placements(ray, robots: int) -> list:
    """Where each robot's actor goes: round robin over the cluster's alive nodes that offer CPUs (all alive nodes
    when none does), as a hard node affinity; a single node gets SPREAD. Ray's own SPREAD strategy spreads actors
    that reserve no CPU only as a best effort (three robots on two nodes may all land on one), and a soft affinity
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


class _Interrupt(Exception):
    """A signal arrived while the team ran."""


def _larger(a: float, b: float) -> float:
    """The larger of two numbers of which either may be NaN (none)."""
    return b if math.isnan(a) else a if math.isnan(b) else max(a, b)


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0][:200] if text else type(err).__name__


# --------------------------------------------------------------------------------------------- Ray itself
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
                f"is auto, but no running Ray cluster was found ({_first_line(err)}); start one (ray start --head) "
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
                    f"got {team.address}: cannot connect to a Ray cluster there ({_first_line(err)})",
                ) from None
    try:
        yield ray
    finally:
        if owned:
            ray.shutdown()
        if handler is not None:
            signal.signal(signal.SIGTERM, handler)


# --------------------------------------------------------------------------------------------- the run
def train_ray(setup: Setup, out: Path, resume: bool, progress) -> dict:
    """`training.train_summary` for team.backend=ray, under the run directory's lock: the same files, written the
    same way, from a team of Ray actors (see the module docstring); returns the summary."""
    total = setup.params.train.iterations
    expected = [initial_state(setup, i) for i in range(setup.robots)]
    checkpoint = load_team_checkpoint(out, setup, expected) if resume else None
    with contextlib.ExitStack() as ray_up:
        idle = checkpoint is not None and checkpoint.iteration >= total  # every robot is done: evaluation only
        # First Ray (an unreachable cluster writes nothing), unless no robot has an iteration left to run
        ray = ray_up.enter_context(contextlib.nullcontext() if idle else ray_runtime(setup.params.team))
        if checkpoint is not None:
            log, rows = reopen_log(out, setup, checkpoint.iteration)
            states, pending = checkpoint.robots, checkpoint.pending
        else:
            log = start_log(out, setup)
            states, pending, rows = expected, [], []
        with log, StopSignals() as stop:
            team = _Team(ray, setup, out, log, states, pending, rows)
            team.progress = progress
            _run_team(team, stop, total, out)
            train_seconds = time.perf_counter() - team.started
            ray_up.close()  # every actor is gone: Ray's own processes (a local instance) go too, before evaluating
            log.metadata("ray_team_end", _end_record(team, train_seconds))
            thetas = team.final_thetas()
            metrics = _metrics_table(team.rows)
            evaluation = evaluate(setup, thetas)
            trajectories = sample_paths(setup, thetas)
            summary = summarize(setup, State(total, thetas, {}, []), evaluation, metrics, train_seconds)
            stop.check(total)  # before the final files: a resumed run evaluates again
            log.trajectories(trajectories)
            log.evaluation(evaluation)
            log.summary(summary)
    write_finished(out, setup, metrics, evaluation, trajectories, summary)
    return summary


def _run_team(team: _Team, stop: StopSignals, total: int, out: Path) -> None:
    """The team's iterations up to `total` and its final checkpoint; whatever stops it, its actors are killed and
    the last consistent cut is written first (a signal: Interrupted; a dead or failed robot: TeamFailure or
    NumericalTrouble)."""
    try:
        if min(team.reached) < total:
            team.start(stop)
            team.started = time.perf_counter()  # the training time counts from here (as the simulated loop's)
            team.run(stop, total)
        team.checkpoint()  # every robot at train.iterations: the final states
    except _Interrupt:
        _stop_team(team)
        raise Interrupted(stop.received, min(int(s["iteration"]) for s in team.cut)) from None
    except _RobotDied as died:
        _stop_team(team)
        if stop.received is not None:  # Ctrl-C in a terminal reaches Ray's processes too: a stop, not a failure
            raise Interrupted(stop.received, min(int(s["iteration"]) for s in team.cut)) from None
        place = team.where[died.robot] if died.robot < len(team.where) else None
        at = f"pid {place['pid']} on {place['ip']}, " if place else ""
        raise TeamFailure(
            f"robot {died.robot}'s Ray actor died ({at}at its iteration {team.reached[died.robot]}: {died.detail}); "
            f"every robot's last state is checkpointed: resume with riskplan train --resume {out}"
        ) from None
    except _RobotFailed as failed:
        _stop_team(team)
        if isinstance(failed.cause, NumericalTrouble):
            raise NumericalTrouble(str(failed.cause)) from None
        raise TeamFailure(
            f"robot {failed.robot} failed ({type(failed.cause).__name__}: {_first_line(failed.cause)}); every "
            f"robot's last state is checkpointed: resume with riskplan train --resume {out}"
        ) from None
    finally:
        team.kill()


def _end_record(team: _Team, train_seconds: float) -> dict:
    """The MCAP metadata "ray_team_end": each robot's iterations and seconds (computing, waiting, in all), the
    largest gradient-tracking residual over the checkpoints and the largest staleness mixed."""
    stale = [r["staleness"] for r in team.rows if r["robot"] >= 0 and not math.isnan(r.get("staleness", math.nan))]
    return {
        "robots": [{"robot": i, **timing} for i, timing in enumerate(team.timing)],
        "tracking_residual": team.balance,
        "max_staleness": max(stale) if stale else None,
        "train_seconds": train_seconds,
        "startup_seconds": team.startup,
    }


def _stop_team(team: _Team) -> None:
    """After a signal or a failure: the actors stopped, their last reports taken, the last consistent cut written,
    the actors killed."""
    for a in team.actors:
        with contextlib.suppress(Exception):
            a.stop.remote()
    if team.actors:
        with contextlib.suppress(Exception):  # Ray itself may be going down (a signal to the whole group)
            team.collect(STOP_SECONDS)
    team.kill()
    team.checkpoint()


def _metrics_table(rows: list[dict]) -> Columns:
    """metrics.parquet: every row, sorted; each robot row with its iteration's consensus error (the team's)."""
    metrics = sorted_by(from_rows(rows), "iteration", "robot")
    average = metrics["robot"] == AVERAGE
    if average.any():
        team = dict(zip(metrics["iteration"][average].tolist(), metrics["consensus_error"][average].tolist()))
        metrics["consensus_error"] = np.array([team.get(i, np.nan) for i in metrics["iteration"].tolist()], dtype=float)
    return metrics


def prepare_ray_resume(setup: Setup, out: Path) -> bool:
    """Every check of a ray run's checkpoint and log before it resumes (nothing is written); whether it is
    finished already."""
    expected = [initial_state(setup, i) for i in range(setup.robots)]
    checkpoint = load_team_checkpoint(out, setup, expected)
    logged_rows(out / "run.mcap", checkpoint.iteration, setup.robots)
    return min(checkpoint.iterations) == setup.params.train.iterations and has_finished(out)


__all__ = [
    "Message",
    "RobotActor",
    "RobotCore",
    "TeamCheckpoint",
    "TeamFailure",
    "consistent_cut",
    "initial_state",
    "prepare_ray_resume",
    "ray_runtime",
    "tracking_balance",
    "train_ray",
]
