"""The consensus rounds of paper eq. (14) under delays, drops and switching links (Assumption 5 (3)-(4)), faulty
robots (team.faults) and resilient aggregation (team.aggregate), and gradient tracking: the Mixer and its typed state.

Timing: a call ``mix(thetas, l, r)`` is slot (l, r). Every robot j sends thetas[j] on each outgoing link
that is up; the message is dropped with probability ``team.drop`` and otherwise arrives in slot (l + D, r),
D uniform on 0..B0 (``team.delay.max``). Assumption 5 (3) is enforced on the sending side: if a link has
had no delivered (undropped) send for B = ``team.max_gap`` iterations, the current send is forced through
(even over a switched-off link), so deliveries are at most B iterations apart and arrivals at most B + B0.
Switching (``team.switching``): each link is up with probability ``up`` per iteration (both directions of
an undirected link together), and is forced up when it has been down for ``window`` iterations, so every
link, hence a strongly connected graph, is up within any ``window`` consecutive iterations.

Faults (``team.faults``, `riskplan.engine.team.faulty`) change only what robots send: from iteration `from` on a
crashed robot's links deliver nothing (and are never forced), a stuck robot sends the theta it sent first at or
after `from` (kept in the Buffers), a byzantine one sends `value` or its theta plus seeded noise. `Mixer.healthy(l)`
says which robots have not failed by iteration l. Aggregation (``team.aggregate``,
`riskplan.engine.team.resilience`): mean is eq. (14); trimmed_mean, median and wmsr aggregate, per robot and
coordinate, its own value and the values its links would mix under the rules above, dropped links' weights
going to the robot itself.

Synchronous teams (no delays, drops or switching; not gradient tracking; no faults; aggregate=mean): every
message arrives in its own slot, so `Mixer._sync_round` mixes sum_j a^{ij} theta^j directly and defers what the rounds
did to the Buffers; the store writes it in when something reads them. Faults and the resilient aggregates always
take the general rules.

Every random draw comes from a generator keyed by (seed, stream, iteration[, round]), so a resumed run redraws
exactly what an uninterrupted one would have drawn.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from riskplan.config.faults import Fault, check_value_size, faults_of
from riskplan.config.schema import Aggregate, FaultKind, Order, Stale, SwitchingConf, TeamConf
from riskplan.engine.team import faulty, kernels, resilience
from riskplan.engine.team import tracking as gradient_tracking
from riskplan.engine.team.network import Network
from riskplan.engine.team.tracking import Tracking
from riskplan.util.errors import BadInput

MIX_STREAM = 7919  # delays and drops: default_rng([seed, 7919, iteration, round])
SWITCH_STREAM = 7927  # switching links: default_rng([seed, 7927, iteration])
MASK = (1 << 64) - 1
INT64_MAX = (1 << 63) - 1


@dataclass
class Stuck:
    """The values stuck robots send (team.faults kind=stuck), frozen at their first send at or after `from`."""

    stuck_theta: np.ndarray  # (N, M): robot j's frozen theta (rows of robots not stuck, or not yet: zeros)
    stuck_since: np.ndarray  # (N,) int: the iteration it was frozen at, -1 = not (yet)


@dataclass
class Buffers:
    """A Mixer's state: the messages in flight and what each link last did. `as_arrays` gives the checkpoint's
    arrays (these field names, the tracking and stuck ones merged in), `from_arrays` reads them back."""

    pending: np.ndarray  # (B0+1, R, N, N, M): per arrival slot (iteration mod B0+1), round and link, theta^j sent
    pending_sent: np.ndarray  # (B0+1, R, N, N) int: its send iteration, -1 = none
    pending_due: np.ndarray  # (B0+1, R, N, N) int: its arrival iteration, -1 = consumed or none
    latest: np.ndarray  # (N, N, M): the newest value received per link (stale=latest)
    latest_stamp: np.ndarray  # (N, N) int: its send slot l R + r, -1 = nothing yet
    last_delivered: np.ndarray  # (N, N) int: iteration of the last undropped send
    last_up: np.ndarray  # (N, N) int: iteration the link was last up (switching)
    up: np.ndarray  # (N, N) bool: links up at iteration up_iteration
    up_iteration: int
    started: bool  # whether any round was mixed (gaps are counted from just before the first)
    delivered: np.ndarray  # (N, N) bool, last round: links whose send got through
    forced: np.ndarray  # (N, N) bool, last round: sends forced through by max_gap
    used_sent: np.ndarray  # (N, N) int, last round: send iteration of the value mixed, -1 = none
    tracking: Tracking | None = None
    stuck: Stuck | None = None  # only for a team with a stuck robot

    @classmethod
    def empty(cls, robots: int, params: int, slots: int, rounds: int, tracking: bool, stuck: bool = False) -> Buffers:
        """The state of a Mixer that has mixed nothing yet."""
        n, m = robots, params
        return cls(
            pending=np.zeros((slots, rounds, n, n, m)),
            pending_sent=np.full((slots, rounds, n, n), -1, dtype=np.int64),
            pending_due=np.full((slots, rounds, n, n), -1, dtype=np.int64),
            latest=np.zeros((n, n, m)),
            latest_stamp=np.full((n, n), -1, dtype=np.int64),
            last_delivered=np.zeros((n, n), dtype=np.int64),
            last_up=np.zeros((n, n), dtype=np.int64),
            up=np.ones((n, n), dtype=bool),
            up_iteration=-1,
            started=False,
            delivered=np.zeros((n, n), dtype=bool),
            forced=np.zeros((n, n), dtype=bool),
            used_sent=np.full((n, n), -1, dtype=np.int64),
            tracking=Tracking.empty(slots, rounds, n, m) if tracking else None,
            stuck=Stuck(np.zeros((n, m)), np.full(n, -1, dtype=np.int64)) if stuck else None,
        )

    def as_arrays(self) -> dict[str, np.ndarray]:
        """The state as named numpy arrays (the fields themselves, not copies; scalars as 0-d arrays)."""
        arrays = {
            f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("tracking", "stuck")
        }
        arrays["up_iteration"] = np.array(self.up_iteration, dtype=np.int64)
        arrays["started"] = np.array(self.started)
        if self.tracking is not None:
            arrays.update({f.name: getattr(self.tracking, f.name) for f in dataclasses.fields(self.tracking)})
        if self.stuck is not None:
            arrays.update({f.name: getattr(self.stuck, f.name) for f in dataclasses.fields(self.stuck)})
        return arrays

    def from_arrays(self, arrays: Mapping[str, np.ndarray]) -> Buffers:
        """Buffers of this one's shapes and dtypes holding copies of `arrays` (a state() or a checkpoint's);
        ValueError naming the first array that is missing or of another shape."""
        mine = self.as_arrays()
        for key, value in mine.items():
            if key not in arrays or np.shape(arrays[key]) != value.shape:
                raise ValueError(f"checkpoint's consensus state '{key}' does not match this team's network/settings")
        copies = {key: np.array(arrays[key], dtype=value.dtype, copy=True) for key, value in mine.items()}
        tracking = None
        if self.tracking is not None:
            tracking = Tracking(**{f.name: copies.pop(f.name) for f in dataclasses.fields(Tracking)})
        stuck = None
        if self.stuck is not None:
            stuck = Stuck(**{f.name: copies.pop(f.name) for f in dataclasses.fields(Stuck)})
        copies["up_iteration"], copies["started"] = int(copies["up_iteration"]), bool(copies["started"])
        return Buffers(**copies, tracking=tracking, stuck=stuck)

    def copy(self) -> Buffers:
        """A deep copy: its arrays are its own."""
        return self.from_arrays(self.as_arrays())

    def shallow(self) -> Buffers:
        """A copy holding the same arrays: rebinding a field of either leaves the other alone."""
        tracking = None if self.tracking is None else dataclasses.replace(self.tracking)
        stuck = None if self.stuck is None else dataclasses.replace(self.stuck)
        return dataclasses.replace(self, tracking=tracking, stuck=stuck)


@dataclass
class Deferred:
    """What the synchronous rounds did since the Buffers were last written (Mixer._sync_round): written into them
    only when something reads them."""

    first: int | None  # the first iteration mixed, when these rounds started the Mixer
    last: int  # the iteration of the last round
    sent: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)  # round -> (iteration, thetas) last sent
    latest: tuple[int, np.ndarray] | None = None  # (slot stamp l R + r, thetas): the newest value on every link

    def copy(self) -> Deferred:
        """A copy that later rounds leave alone (the thetas themselves are never changed)."""
        return Deferred(self.first, self.last, dict(self.sent), self.latest)


Apply = Callable[[Buffers, Deferred], None]


def write_deferred(b: Buffers, deferred: Deferred, *, adjacency: np.ndarray, rounds: int, latest_rule: bool) -> None:
    """Write into `b` (changed in place) what the synchronous rounds in `deferred` did: exactly what `Mixer._send`
    and `Mixer._received` would have written, every link sending and hearing every slot (`adjacency` its links,
    `rounds` per iteration, `latest_rule`: team.stale=latest)."""
    receiver, sender = np.nonzero(adjacency)
    if deferred.first is not None:  # the rounds started the Mixer (see _round)
        b.last_delivered[:] = deferred.first - 1
        b.last_up[:] = deferred.first - 1
        b.started = True
    b.last_delivered[receiver, sender] = deferred.last
    b.delivered = adjacency.copy()
    b.forced = np.zeros_like(adjacency)
    for round_index, (iteration, sent) in deferred.sent.items():  # slot 0: with B0 = 0 a message is due at once
        b.pending[0, round_index, receiver, sender, :] = sent[sender]
        b.pending_sent[0, round_index, receiver, sender] = iteration
        b.pending_due[0, round_index, receiver, sender] = -1  # consumed on arrival
    stamp, latest = deferred.latest
    b.latest[receiver, sender, :] = latest[sender]
    b.latest_stamp[receiver, sender] = stamp
    if latest_rule:
        b.used_sent = np.where(b.latest_stamp >= 0, b.latest_stamp // rounds, -1)
    else:
        b.used_sent = np.where(adjacency, deferred.last, -1)


class MixerState(Mapping):
    """A Mixer's state at one moment (Mixer.snapshot): a read-only mapping of its arrays, built on first access."""

    def __init__(self, base: Buffers, deferred: Deferred | None, apply: Apply):
        self._base, self._deferred, self._apply = base, deferred, apply
        self._keys = list(base.as_arrays())
        self._arrays: dict[str, np.ndarray] | None = None

    def _built(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            buffers = self._base.copy()
            if self._deferred is not None:
                self._apply(buffers, self._deferred)
            self._arrays, self._base, self._deferred = buffers.as_arrays(), buffers, None
        return self._arrays

    def __getitem__(self, key: str) -> np.ndarray:
        return self._built()[key]

    def __contains__(self, key: object) -> bool:
        return key in self._keys

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


class _Store:
    """A Mixer's Buffers with the synchronous rounds not yet written into them: the only way to the Buffers.

    `current()` writes any deferred rounds in before it hands the Buffers out, so no reader, old or new, can see
    stale buffers. A snapshot shares the arrays until this side would change them (copy on write)."""

    def __init__(self, buffers: Buffers, apply: Apply):
        self._buffers, self._apply = buffers, apply
        self.deferred: Deferred | None = None
        self._shared = False  # a snapshot holds the arrays: copy them before changing them in place
        self.latest: MixerState | None = None  # the snapshot of the state the Buffers are in, while they are

    def current(self, writing: bool = True) -> Buffers:
        """The Buffers, up to date; with `writing=False` the caller promises only to read them (no copy is made
        for a snapshot's sake unless deferred rounds must be written in)."""
        if writing:
            self.latest = None
        if self._shared and (writing or self.deferred is not None):
            self._buffers, self._shared = self._buffers.copy(), False
        if self.deferred is not None:
            self._apply(self._buffers, self.deferred)
            self.deferred = None
        return self._buffers

    def snapshot(self) -> MixerState:
        """The state of this moment, copied only when read (see Mixer.snapshot)."""
        self._shared = True
        deferred = None if self.deferred is None else self.deferred.copy()
        self.latest = MixerState(self._buffers.shallow(), deferred, self._apply)
        return self.latest

    def replace(self, buffers: Buffers) -> None:
        """Hold `buffers` from now on (restore)."""
        self._buffers, self.deferred, self._shared, self.latest = buffers, None, False, None


def links_up_at(b: Buffers, network: Network, switching: SwitchingConf, seed: int, iteration: int) -> np.ndarray:
    """Links up at `iteration` under team.switching, drawn once per iteration and kept in `b` so that every round
    sees the same graph."""
    adjacency = network.adjacency
    if not switching.enabled:
        return adjacency
    if b.up_iteration != iteration:
        rng = np.random.default_rng([seed, SWITCH_STREAM, iteration & MASK])
        draw = rng.random(adjacency.shape) < switching.up
        if not network.directed:
            draw = np.triu(draw, 1) | np.triu(draw, 1).T  # an undirected link is up both ways or not at all
        overdue = iteration - b.last_up >= switching.window
        b.up = adjacency & (draw | overdue)
        b.last_up = np.where(b.up, iteration, b.last_up)
        b.up_iteration = iteration
    return b.up


class Mixer:
    """Consensus rounds of eq. (14) (without the gradient term) under delays, drops and switching links, faults and
    resilient aggregation, by the rules of the module docstring; `track` adds gradient tracking
    (`engine.team.tracking`)."""

    def __init__(self, network: Network, team: TeamConf, seed: int, faults: tuple[Fault, ...] | None = None):
        """A Mixer of `network` with the validated settings of `team` (riskplan.config.validate); `faults` the
        team's checked faults (`riskplan.config.faults.faults_of(team)`, which None stands for)."""
        if team.robots != network.robots:
            raise BadInput("team.robots", f"is {team.robots} but the network has {network.robots} robots")
        self.faults = faults_of(team) if faults is None else tuple(faults)
        for fault in self.faults:
            if not 0 <= fault.robot < network.robots:
                raise ValueError(f"fault of robot {fault.robot}, but the network has robots 0..{network.robots - 1}")
        check_value_size(self.faults, network.n_params)
        self.aggregate = Aggregate(team.aggregate)
        self.trim = resilience.rule_f(self.aggregate, team.trim, network.adjacency, self.faults)  # median's from faults
        if team.order == Order.gradient_tracking and (self.faults or self.aggregate != Aggregate.mean):
            key = "team.faults" if self.faults else "team.aggregate"
            raise BadInput(
                key, f"team.order={Order.gradient_tracking} mixes running sums: use team.aggregate=mean and no faults"
            )
        self.network, self.seed = network, int(seed) & MASK
        self.tracking, self.rounds = team.order == Order.gradient_tracking, team.consensus_rounds
        self.max_delay, self.drop, self.max_gap = team.delay.max, team.drop, team.max_gap
        self.latest_rule = team.stale == Stale.latest
        self.switching = team.switching
        slots = self.max_delay + 1
        stuck = any(f.kind == FaultKind.stuck for f in self.faults)
        self._sizes = (network.robots, network.n_params, slots, self.rounds, self.tracking, stuck)
        self._apply = partial(
            write_deferred, adjacency=network.adjacency, rounds=self.rounds, latest_rule=self.latest_rule
        )
        self._store = _Store(Buffers.empty(*self._sizes), self._apply)
        self._sync = not self.tracking and self.max_delay == 0 and self.drop == 0.0 and not self.switching.enabled
        self._sync = self._sync and not self.faults and self.aggregate == Aggregate.mean
        self._links: kernels.Links | None = None  # built by the first synchronous round

    # Diagnostics of the last call, for tests and logs.
    @property
    def delivered(self) -> np.ndarray:
        """(N, N) bool: links whose message sent in the last call was not dropped."""
        return self._store.current(writing=False).delivered.copy()

    @property
    def forced(self) -> np.ndarray:
        """(N, N) bool: links whose send in the last call was forced through by max_gap."""
        return self._store.current(writing=False).forced.copy()

    @property
    def used_sent(self) -> np.ndarray:
        """(N, N) int: iteration at which the neighbour value mixed in the last call was sent (-1: none)."""
        return self._store.current(writing=False).used_sent.copy()

    def healthy(self, iteration: int) -> np.ndarray:
        """(N,) bool: False for the robots whose fault (team.faults) has started by `iteration`."""
        return faulty.healthy(self.faults, self.network.robots, int(iteration))

    def state(self) -> dict[str, np.ndarray]:
        """Everything a resumed Mixer needs, as numpy arrays (copies)."""
        return dict(self.snapshot())

    def snapshot(self) -> MixerState:
        """The state() of this moment as a read-only mapping that copies nothing until it is read (a checkpoint
        reads it; most iterations' snapshots are never read). Its arrays are the state()'s, bit for bit."""
        return self._store.snapshot()

    def fresh(self) -> MixerState:
        """The state of this team's Mixer before it has mixed anything (a run's iteration 0)."""
        return MixerState(Buffers.empty(*self._sizes), None, self._apply)

    def at(self, state: Mapping[str, np.ndarray]) -> Mixer:
        """This Mixer in `state`: restored from it, unless `state` is the snapshot of the state it is in already
        (its last snapshot, with nothing changed since: what the engine's step hands back and gets again)."""
        return self if state is self._store.latest else self.restore(state)

    def restore(self, state: Mapping[str, np.ndarray]) -> Mixer:
        """Load a state() (or snapshot()) taken from a Mixer of the same team; returns self."""
        self._store.replace(self._store.current(writing=False).from_arrays(state))
        return self

    def links_up(self, iteration: int) -> np.ndarray:
        """(N, N) bool links up at `iteration` (all links unless switching is enabled)."""
        return np.array(
            links_up_at(self._store.current(), self.network, self.switching, self.seed, iteration), copy=True
        )

    def mix(self, thetas: np.ndarray, iteration: int, round_index: int = 0) -> np.ndarray:
        """One consensus round of eq. (14) at slot (iteration, round_index): (N, M) in, (N, M) out.

        A gradient-tracking Mixer sends a zero tracker with it (use `track` for the tracking update)."""
        thetas = np.asarray(thetas, dtype=float)
        return self._round(thetas, np.zeros_like(thetas) if self.tracking else None, iteration, round_index)[0]

    def track(self, thetas: np.ndarray, grads: np.ndarray, iteration: int) -> tuple[np.ndarray, np.ndarray]:
        """Gradient tracking at iteration l (`engine.team.tracking`): every robot sends (theta^i_l, y^i_l, v^i_l) in
        one message per round (one delay and drop draw for all). Returns (A theta_l, y_l / v_l) and keeps z_l = A y_l
        and A v_l for the next call; the caller steps theta_{l+1} = A theta_l + eps_l y_l / v_l."""
        if not self.tracking:
            raise ValueError("track needs a Mixer of a team with team.order=gradient_tracking")
        thetas, grads = np.asarray(thetas, dtype=float), np.asarray(grads, dtype=float)
        if grads.shape != thetas.shape:
            raise ValueError(f"expected gradients of shape {thetas.shape}, got {grads.shape}")
        if self.network.robots == 1:
            return thetas.copy(), grads.copy()  # no one to track with: eq. (11), bit for bit
        tracker, mass = gradient_tracking.carried(self._store.current().tracking, grads)
        mixed, carried = thetas, np.concatenate([tracker, mass], axis=1)
        for round_index in range(self.rounds):
            mixed, carried = self._round(mixed, carried, iteration, round_index)
        state = self._store.current().tracking
        state.tracker, state.gradient = carried, grads.copy()
        return mixed, tracker / mass

    def in_flight(self) -> np.ndarray:
        """(2M,) tracker and push-sum weight mass sent but not yet taken in, [y part, v part]: the sum over
        rounds and links of a^{ij} (S^j - rho^{ij})."""
        if not self.tracking:
            return np.zeros(2 * self.network.n_params)
        state = self._store.current(writing=False).tracking
        return gradient_tracking.in_flight(state, self.network.weights, self.network.adjacency)

    def _round(
        self, thetas: np.ndarray, carried: np.ndarray | None, iteration: int, round_index: int
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """One round at slot (iteration, round_index): mixed thetas, and the mixed trackers when `carried`."""
        n, m = self.network.robots, self.network.n_params
        if thetas.shape != (n, m):
            raise ValueError(f"expected thetas of shape ({n}, {m}), got {thetas.shape}")
        if not 0 <= round_index < self.rounds:
            raise ValueError(f"round_index {round_index} outside 0..{self.rounds - 1} (team.consensus_rounds)")
        if n == 1:
            return thetas.copy(), None if carried is None else carried.copy()
        iteration = int(iteration)
        if carried is None and self._sync:
            mixed = self._sync_round(thetas, iteration, round_index)
            if mixed is not None:
                return mixed, None
        b = self._store.current()
        if not b.started:
            # Gaps are counted from just before the first iteration mixed.
            b.last_delivered[:] = iteration - 1
            b.last_up[:] = iteration - 1
            b.started = True
        self._send(b, thetas, carried, iteration, round_index)
        mixed, arrived = self._received(b, thetas, iteration, round_index)
        if carried is None:
            return mixed, None
        slot = iteration % (self.max_delay + 1)
        sent = b.pending_sent[slot, round_index]
        return mixed, gradient_tracking.mix_sums(
            b.tracking, self.network.weights, slot, round_index, sent, arrived, carried
        )

    def _sync_round(self, thetas: np.ndarray, iteration: int, round_index: int) -> np.ndarray | None:
        """A round of a synchronous team (no delays, drops or switching): every link delivers in the slot it sends,
        so robot i mixes sum_j a^{ij} theta^j (with stale=latest, the newest value each link holds) exactly as
        `_received` would, in the same order of sums, without the (N, N, M) buffers. The Buffers are left as they
        were and the store defers what to write into them. None when the general rules must decide: a slot no
        later than the newest value the Buffers already hold (a Mixer set back in time)."""
        deferred = self._store.deferred
        stamp = iteration * self.rounds + round_index
        sent = np.array(thetas, copy=True)
        if deferred is None:
            b = self._store.current(writing=False)  # nothing deferred: these are the Buffers as they stand
            if stamp <= int(b.latest_stamp.max()):
                return None
            deferred = Deferred(None if b.started else iteration, iteration, {}, (stamp, sent))
            self._store.deferred = deferred
        elif stamp > deferred.latest[0]:
            deferred.latest = (stamp, sent)  # a repeated or older slot is not newer: the links keep what they hold
        deferred.last = iteration
        deferred.sent[round_index] = (iteration, sent)
        neighbour = deferred.latest[1] if self.latest_rule else sent
        if self._links is None and self.network.n_params > 1:
            self._links = kernels.Links(self.network)
        return kernels.mix_linked(self.network, self._links, thetas, neighbour)

    def _send(self, b: Buffers, thetas: np.ndarray, carried: np.ndarray | None, iteration: int, round_index: int):
        """Put this slot's messages in flight: delay, drop, forced delivery (Assumption 5 (3)-(4))."""
        # A fresh generator per slot: no random state crosses iterations, so resume is bit-identical. With B0 = 0
        # the delays are all 0 and integers(0, 1) draws nothing; with drop 0 every message is kept: both skipped.
        rng = np.random.default_rng([self.seed, MIX_STREAM, iteration & MASK, round_index])
        shape = (self.network.robots,) * 2
        delay = rng.integers(0, self.max_delay + 1, size=shape) if self.max_delay else kernels.NO_INTS
        kept = rng.random(shape) >= self.drop if self.drop else kernels.NO_FLAGS
        sums, pending_sums = kernels.NO_FLOATS, kernels.NO_PENDING
        if carried is not None:  # the tracker rides in the same message: its sender's running sum
            b.tracking.sums[round_index] += carried
            sums, pending_sums = b.tracking.sums[round_index], b.tracking.pending_sums
        max_gap = min(self.max_gap, INT64_MAX)  # a gap of an int64 iteration never exceeds it: same as any larger B
        adjacency, up = self.network.adjacency, links_up_at(b, self.network, self.switching, self.seed, iteration)
        if self.faults:  # what faulty robots send; a crashed robot's links send nothing and are never forced
            stuck = (None, None) if b.stuck is None else (b.stuck.stuck_theta, b.stuck.stuck_since)
            thetas, silent = faulty.sent_values(self.faults, thetas, self.seed, iteration, round_index, *stuck)
            if silent is not None:
                adjacency, up = adjacency & ~silent[None, :], up & ~silent[None, :]
        kernels.send(  # the buffers one by one (riskplan.engine.team.kernels says why)
            adjacency,
            up,
            kept,
            delay,
            iteration,
            max_gap,
            round_index,
            np.ascontiguousarray(thetas),
            sums,
            b.last_delivered,
            b.delivered,
            b.forced,
            b.pending,
            b.pending_sent,
            b.pending_due,
            pending_sums,
        )

    def _received(
        self, b: Buffers, thetas: np.ndarray, iteration: int, round_index: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The mixed thetas after this slot's arrivals, and the (N, N) links whose message arrived now.

        A link mixes the value that arrived (stale=arrival) or the newest it holds (stale=latest); a neighbour with
        nothing to offer hands its weight to robot i itself, keeping each row stochastic; a late message never
        replaces a newer one, and stale slots never meet a weight, even as 0 * inf. With team.aggregate other than
        mean, each robot aggregates its own value and the values of the links in `use` (`resilience.aggregate_team`)."""
        adjacency = self.network.adjacency
        slot = iteration % (self.max_delay + 1)
        n = self.network.robots
        arrived, use = np.empty((n, n), dtype=bool), np.empty((n, n), dtype=bool)
        kernels.receive(  # the buffers one by one (riskplan.engine.team.kernels says why)
            adjacency,
            iteration,
            round_index,
            self.rounds,
            self.latest_rule,
            b.pending[slot, round_index],
            b.pending_sent[slot, round_index],
            b.pending_due[slot, round_index],
            b.latest,
            b.latest_stamp,
            b.used_sent,
            arrived,
            use,
        )
        neighbour = b.latest if self.latest_rule else b.pending[slot, round_index]
        if self.aggregate != Aggregate.mean:
            weights = self.network.weights
            mixed = resilience.aggregate_team(self.aggregate, weights, adjacency, use, neighbour, thetas, self.trim)
            return mixed, arrived
        return kernels.mix_used(self.network.weights, adjacency, use, neighbour, thetas), arrived
