"""team.backend=ray, one robot without Ray: robot i's side of the algorithm (`RobotCore`), which its actor
(`riskplan.run.ray_actor.RobotActor`) runs under one lock, and tests drive by hand; the consistent cut of the
robots' states that the driver (`riskplan.run.ray_team`) checkpoints, and gradient tracking's invariant over it.

Iteration l of robot i:
  1. W_l episodes at its own theta^i_l from its own stream (`rng.stream_key(seed, rng.TRAIN, l, i)`: the key the
     simulated team gives robot i, so its episodes do not depend on scheduling), and its gradient for its own risk
     node (team.risk): riskplan.engine.step's `rollouts` and `estimate` for robot i alone;
  2. a robot with team.speeds factor s > 1 sleeps (s - 1) x that compute time (uneven hardware);
  3. for each consensus round r: it sends its value (theta, or theta + eps Delta for adapt_then_combine; with
     gradient tracking also its running sums) to its out-neighbours, fire-and-forget (`deliver`), then waits until
     each in-neighbour's newest round-r message has iteration >= l - team.staleness, and mixes its own row;
  4. theta^i_{l+1} by team.order, exactly as `engine.step.consensus_step` composes it, and the step's checks; a
     report (its metrics row, its episodes' total rewards and gradient, its state after the iteration) waits for
     the driver.

Messages. `Message(sender, iteration, round, theta, sums)`: theta the value sent (what `faulty.sent_value` makes of
it for a robot of team.faults), sums the sender's running sums S^j = [sum of y, sum of v] of the round (gradient
tracking) or None. Calls to a threaded actor may run out of order; the stamps sort them out.

Mixing, one row (the rules of `engine.team.mixer.Mixer`, for robot i alone). Robot i keeps, per round and
in-neighbour j, the newest message received (`latest`), the newest one that arrived since its last mix
(`pending`, stale=arrival; a message no newer than one already mixed never replaces anything) and, for gradient
tracking, rho^{ij}, the newest S^j taken in. A link mixes its candidate (stale=arrival: round r's pending;
stale=latest: the newest message of any round, stamped t R + r' as the Mixer's latest_stamp, so with R >= 2 rounds
round 1 of iteration l may mix round 0's message of l rather than round 1's of l - 1) only if that message's
iteration is >= l - team.staleness; a link with nothing to offer hands its weight
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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from riskplan.config.schema import Aggregate, FaultKind, Order, Stale, TeamConf
from riskplan.engine.rollout import simulate
from riskplan.engine.schedules import step_size
from riskplan.engine.step import RunSetup, check_step, estimate, rollouts, starts
from riskplan.engine.team import faulty, resilience
from riskplan.run.evaluation import robot_risks
from riskplan.run.metrics_rows import metrics_row

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


# --------------------------------------------------------------------------------------------- one robot, no Ray
def rounds_of(setup: RunSetup) -> int:
    """Consensus rounds per iteration: team.consensus_rounds in a team, none for a robot alone."""
    return setup.params.team.consensus_rounds if setup.team else 0


def in_neighbours(setup: RunSetup, robot: int) -> list[int]:
    """The robots j whose messages robot i mixes (adjacency[i, j]: j sends to i), in order of j."""
    return [int(j) for j in np.flatnonzero(setup.network.adjacency[robot])]


def out_neighbours(setup: RunSetup, robot: int) -> list[int]:
    """The robots k that mix robot i's messages."""
    return [int(k) for k in np.flatnonzero(setup.network.adjacency[:, robot])]


def initial_state(setup: RunSetup, robot: int) -> dict[str, np.ndarray]:
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

    def __init__(self, setup: RunSetup, robot: int, state: dict[str, np.ndarray] | None = None):
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
        faults = setup.mixer.faults
        self.aggregate = Aggregate(team.aggregate)
        self.trim = resilience.rule_f(self.aggregate, team.trim, network.adjacency, faults)  # median: from faults
        self.own_weight = np.array(network.weights[robot, robot], dtype=float)  # (M,) a^{ii}
        self.in_weights = np.array(network.weights[robot, self.ins], dtype=float).reshape(len(self.ins), self.m)
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
        if self.latest_rule:  # per link, the newest message of any round, by its slot stamp t R + r' (as the Mixer)
            slots = s["latest_sent"] * self.rounds + np.arange(self.rounds)[:, None]
            stamps = np.where(s["latest_sent"] >= 0, slots, -1)
            newest = stamps.argmax(axis=0)  # (K,): the round of each link's newest message
            links = np.arange(len(self.ins))
            sent, values = s["latest_sent"][newest, links], s["latest"][newest, links]
        else:
            sent, values = np.array(s["pending_sent"][r]), s["pending"][r]  # a copy: cleared below
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


def tracking_balance(setup: RunSetup, states: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
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


__all__ = [
    "STATE_KEYS",
    "Message",
    "RobotCore",
    "Step",
    "consistent_cut",
    "in_neighbours",
    "initial_state",
    "out_neighbours",
    "rounds_of",
    "tracking_balance",
]
