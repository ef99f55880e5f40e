"""Consensus layer of paper eq. (14): mixing weights, Assumption 5 checks, delayed/dropped messages, reports.

Conventions (see also riskplan.engine.team.graphs):
- ``adjacency[i, j]`` / ``weights[i, j, m]``: robot i receives from robot j; row i of A is what robot i mixes.
- ``team.edges`` entries ``[i, j]`` mean j sends to i (both ways unless ``team.directed``).
- Every random draw comes from a generator keyed by (seed, stream, iteration[, round]), so a resumed run
  redraws exactly what an uninterrupted one would have drawn.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit, prange

from riskplan.engine.team import graphs
from riskplan.util.checks import finite, one_of, whole
from riskplan.util.errors import BadInput

WEIGHTS = ("metropolis", "max_degree", "lazy", "matrix")
STALE = ("arrival", "latest")
TRACKING = "gradient_tracking"  # team.order whose robots also exchange gradient trackers (Mixer.track)
TOL = 1e-9  # row-stochasticity tolerance
MIX_STREAM = 7919  # delays and drops: default_rng([seed, 7919, iteration, round])
SWITCH_STREAM = 7927  # switching links: default_rng([seed, 7927, iteration])
MASK = (1 << 64) - 1
INT64_MAX = (1 << 63) - 1


@dataclass(frozen=True, eq=False)
class Network:
    """A validated communication graph with per-parameter mixing weights a^{ij}_m of eq. (14)."""

    robots: int
    adjacency: np.ndarray  # (N, N) bool: [i, j] True when robot i receives from robot j
    weights: np.ndarray  # (N, N, M): weights[i, j, m] = a^{ij}_m; each row sums to 1 for every m
    positions: np.ndarray | None  # (N, 2) in the unit square for random_geometric, else None
    graph: str
    directed: bool
    gamma: float  # Assumption 5 (2): the smallest positive weight

    @property
    def n_params(self) -> int:
        """M, the number of policy parameters."""
        return int(self.weights.shape[2])

    @property
    def edges(self) -> list[list[int]]:
        """Links as [i, j] (j sends to i); undirected links once with i < j."""
        return graphs.edge_list(self.adjacency, self.directed)

    @property
    def slem(self) -> float:
        """Worst SLEM over the parameters: the predicted per-round contraction on the fixed graph."""
        return max(second_largest_eigenvalue_modulus(self.weights[:, :, m]) for m in range(self.n_params))


# ---------------------------------------------------------------------------------------------- settings


def _get(team: Any, dotted: str, default: Any = None) -> Any:
    """team.<dotted> from a DictConfig or any object with TeamConf's attributes."""
    value = team
    for part in dotted.split("."):
        value = getattr(value, part, default) if value is not None else default
    return value


def _plain(value: Any) -> Any:
    """An OmegaConf container as plain lists; anything else unchanged."""
    if hasattr(value, "_get_node"):
        from omegaconf import OmegaConf

        return OmegaConf.to_container(value, resolve=True)
    return value


@dataclass(frozen=True)
class Settings:
    """The validated scalar team settings the Mixer needs."""

    robots: int
    max_delay: int  # B0
    drop: float
    max_gap: int  # B
    stale: str
    rounds: int
    switching: bool
    up: float
    window: int


def check_settings(team: Any) -> Settings:
    """Validate the team's scalar keys (robots, names, delays, drops, gaps, rounds, switching)."""
    robots = whole(_get(team, "robots"), "team.robots", 1, "the number of robots")
    one_of(_get(team, "graph"), "team.graph", graphs.GRAPHS)
    one_of(_get(team, "weights"), "team.weights", WEIGHTS)
    stale = one_of(_get(team, "stale"), "team.stale", STALE)
    max_delay = whole(_get(team, "delay.max"), "team.delay.max", 0, "the largest message delay in iterations (B0)")
    drop = finite(_get(team, "drop"), "team.drop")
    if not 0.0 <= drop < 1.0:
        raise BadInput("team.drop", f"is {drop:g}; the drop probability must be in [0, 1)")
    max_gap = whole(_get(team, "max_gap"), "team.max_gap", 1, "the longest gap between deliveries on a link (B)")
    rounds = whole(
        _get(team, "consensus_rounds"), "team.consensus_rounds", 1, "the number of consensus rounds per iteration"
    )
    whole(_get(team, "resample"), "team.resample", 0, "the number of random_geometric redraws")
    window = whole(_get(team, "switching.window"), "team.switching.window", 1, "the switching window (iterations)")
    up = finite(_get(team, "switching.up"), "team.switching.up")
    if not 0.0 < up <= 1.0:
        raise BadInput("team.switching.up", f"is {up:g}; the per-iteration link-up probability must be in (0, 1]")
    switching = bool(_get(team, "switching.enabled", False))
    return Settings(robots, max_delay, drop, max_gap, stale, rounds, switching, up, window)


# ---------------------------------------------------------------------------------------------- network


def build_network(team: Any, n_params: int, seed: int) -> Network:
    """The team's graph and weights, checked against Assumption 5 (BadInput naming the key otherwise)."""
    settings = check_settings(team)
    if not isinstance(n_params, numbers.Integral) or n_params < 1:
        raise BadInput("train.theta0", f"gives {n_params!r} parameters; the policy needs at least one (one per source)")
    graph = str(_get(team, "graph"))
    directed = bool(_get(team, "directed", False))
    adjacency, positions = _adjacency(team, graph, settings.robots, directed, seed)
    if graph == "random_geometric":
        directed = False  # distance links are symmetric whatever team.directed says
    if not graphs.strongly_connected(adjacency):
        key = "team.edges" if graph == "edges" else "team.graph"
        kind = "directed " if directed else ""
        if graph == "edges":
            advice = "add edges so that every robot can reach every other one"
            advice += " or set directed=false" if directed else ""
        else:
            advice = "use graph=ring or complete, directed=false, or graph=edges with a strongly connected list"
        raise BadInput(
            key,
            f"the {kind}{graph} graph with edges {graphs.format_edges(adjacency, directed)} is not strongly connected "
            f"(Assumption 5 (1)); {advice}",
        )
    weights, where = _weights(team, adjacency, int(n_params))
    check_weights(weights, adjacency, where)
    positive = weights[weights > 0]
    gamma = float(positive.min()) if positive.size else 1.0
    for array in (adjacency, weights, positions):
        if array is not None:
            array.setflags(write=False)  # the dataclass is frozen; so are its arrays
    return Network(settings.robots, adjacency, weights, positions, graph, directed, gamma)


def _adjacency(team: Any, graph: str, robots: int, directed: bool, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Links of the configured topology, and robot positions for random_geometric."""
    if graph == "edges":
        return graphs.edges_adjacency(_plain(_get(team, "edges")), robots, directed), None
    if graph == "random_geometric":
        radius = finite(_get(team, "radius"), "team.radius")
        if radius <= 0:
            raise BadInput("team.radius", f"is {radius:g}; the link radius must be > 0 (the unit square is 1 x 1)")
        return graphs.random_geometric(robots, radius, int(_get(team, "resample")), seed)
    return graphs.named_adjacency(graph, robots, directed), None


def rule_weights(rule: str, adjacency: np.ndarray) -> np.ndarray:
    """N x N weights of a named rule on the links, the rest of each row on the diagonal."""
    n = len(adjacency)
    links = adjacency.astype(float)
    degree = adjacency.sum(axis=1)  # in-degree: how many robots robot i hears
    if rule == "metropolis":
        # 1/(1+max(d_i, d_j)) is symmetric on undirected graphs, hence doubly stochastic there.
        weights = links / (1.0 + np.maximum(degree[:, None], degree[None, :]))
    elif rule == "max_degree":
        weights = links / (1.0 + (degree.max() if n else 0))
    elif rule == "lazy":
        weights = 0.5 * links / np.maximum(degree, 1)[:, None]
    else:
        raise ValueError(f"no weight rule named {rule!r}")
    np.fill_diagonal(weights, 0.0)
    np.fill_diagonal(weights, 1.0 - weights.sum(axis=1))
    return weights


def _weights(team: Any, adjacency: np.ndarray, n_params: int) -> tuple[np.ndarray, str]:
    """(N, N, M) weights from team.diagonal, team.matrix or the named rule, and the key they came from."""
    n = len(adjacency)
    diagonal = _plain(_get(team, "diagonal"))
    if diagonal is not None:
        what = "N x N x M per-parameter weights a^{ij}_m"
        return _array(diagonal, (n, n, n_params), "team.diagonal", what), "team.diagonal"
    rule = str(_get(team, "weights"))
    if rule == "matrix":
        matrix = _plain(_get(team, "matrix"))
        if matrix is None:
            raise BadInput("team.matrix", f"weights=matrix needs team.matrix, a {n} x {n} row-stochastic list of lists")
        plain = _array(matrix, (n, n), "team.matrix", "the N x N row-stochastic matrix A")
        return np.repeat(plain[:, :, None], n_params, axis=2), "team.matrix"
    return np.repeat(rule_weights(rule, adjacency)[:, :, None], n_params, axis=2), "team.weights"


def _array(value: Any, shape: tuple[int, ...], where: str, what: str) -> np.ndarray:
    """A finite float array of exactly `shape`, or BadInput."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError):
        expected = " x ".join(map(str, shape))
        raise BadInput(where, f"is not a rectangular list of numbers; expected {expected} ({what})") from None
    if array.shape != shape:
        got = " x ".join(map(str, array.shape)) or "a scalar"
        raise BadInput(where, f"has shape {got}; expected {' x '.join(map(str, shape))} ({what})")
    if not np.isfinite(array).all():
        raise BadInput(where, "holds a non-finite number; weights must be finite")
    return array


def check_weights(weights: np.ndarray, adjacency: np.ndarray, where: str) -> None:
    """Assumption 5 (2) and eq. (14): nonnegative, row-stochastic, positive exactly on links and the diagonal."""
    n = len(adjacency)
    off_graph = ~adjacency & ~np.eye(n, dtype=bool)
    entry = "a[{i}][{j}] = {v:g} (parameter {m})"
    checks = (
        (weights < 0, entry + " is negative; weights must be >= 0"),
        (np.eye(n, dtype=bool)[:, :, None] & (weights <= 0), entry + " must be > 0 (Assumption 5 (2))"),
        (
            adjacency[:, :, None] & (weights <= 0),
            entry + " is zero on the link {j}->{i}; every link needs a positive weight (Assumption 5 (2))",
        ),
        (
            off_graph[:, :, None] & (weights != 0),
            entry + " but robot {i} does not receive from {j} in the graph; weights off the graph must be 0",
        ),
    )
    for bad, text in checks:
        if bad.any():
            i, j, m = (int(k) for k in np.argwhere(bad)[0])
            raise BadInput(where, text.format(i=i, j=j, m=m, v=weights[i, j, m]))
    sums = weights.sum(axis=1)
    if (np.abs(sums - 1.0) > TOL).any():
        i, m = (int(k) for k in np.argwhere(np.abs(sums - 1.0) > TOL)[0])
        problem = f"row {i} (parameter {m}) sums to {sums[i, m]:.12g}, not 1; every row of A must sum to 1 (eq. 14)"
        raise BadInput(where, problem)


def check_tracking(network: Network, team: Any) -> None:
    """team.order=gradient_tracking needs doubly stochastic weights: with a column of A that does not sum to 1,
    mixing changes the sum of the trackers, which then no longer track the sum of the gradients."""
    if network.robots == 1:
        return
    columns = network.weights.sum(axis=0)  # (N, M): column j of A per parameter
    bad = np.abs(columns - 1.0) > TOL
    if bad.any():
        j, m = (int(k) for k in np.argwhere(bad)[0])
        where = (
            "team.diagonal"
            if _get(team, "diagonal") is not None
            else "team.matrix"
            if _get(team, "weights") == "matrix"
            else "team.weights"
        )
        raise BadInput(
            where,
            f"column {j} (parameter {m}) of A sums to {columns[j, m]:.6g}, but "
            f"team.order={TRACKING} needs doubly stochastic weights (every column summing to 1 "
            f"too) so that the trackers keep the sum of the gradients; use weights=metropolis on "
            f"an undirected graph, or another order",
        )


# ---------------------------------------------------------------------------------------------- measures


def second_largest_eigenvalue_modulus(weights2d: np.ndarray) -> float:
    """SLEM of an N x N weight matrix: the per-round consensus contraction on a fixed graph (0 for N = 1)."""
    w = np.asarray(weights2d, dtype=float)
    if w.ndim != 2 or w.shape[0] != w.shape[1]:
        raise ValueError(f"expected a square matrix, got shape {w.shape}")
    if len(w) <= 1:
        return 0.0
    # eigvalsh is exact to rounding for the symmetric (undirected, doubly stochastic) case.
    values = np.linalg.eigvalsh(w) if np.allclose(w, w.T, rtol=0, atol=1e-14) else np.linalg.eigvals(w)
    return float(np.sort(np.abs(values))[-2])


def consensus_error(thetas: np.ndarray) -> float:
    """max_{i,j} ||theta^i - theta^j||_2 over the rows of an (N, M) array; 0.0 for N = 1.

    Exact: the very number of the brute force over all pairs (`_largest_squared_gap` of every row against all
    rows), found    without its N x N x M temporaries. Around the centroid c, any pair is at most r_i + r_j apart (r = |theta - c|),
    so the rows are taken farthest first, each against all rows, until no pair of the rows left can beat the best
    gap found (`_gap_bound`, which allows for rounding). A round cloud needs a few dozen rows; the worst case (every
    row as far from c) takes them all, in blocks.
    """
    t = np.asarray(thetas, dtype=float)
    if t.ndim != 2:
        raise ValueError(f"expected thetas of shape (N, M), got {t.shape}")
    n, m = t.shape
    if n <= 1:
        return 0.0
    if (t == t[0]).all():
        return 0.0  # every gap is exactly 0 (this also covers M = 0)
    if n <= _GAP_ROWS or not np.isfinite(t).all():
        return float(np.sqrt(_largest_squared_gap(t, np.arange(n))))
    with np.errstate(over="ignore"):  # huge rows give infinite radii: no pruning, the brute force's own answer
        radii = np.sqrt(((t - t.mean(axis=0)) ** 2).sum(axis=-1))
    order = np.argsort(-radii, kind="stable")
    radii = radii[order]
    best, done, k = -np.inf, 0, _GAP_ROWS
    while done < n:
        best = np.maximum(best, _largest_squared_gap(t, order[done:k]))
        done = k
        if done >= n - 1 or _gap_bound(radii[done] + radii[done + 1], m) ** 2 <= best:
            break  # every pair not compared has both rows within radii[done] of c
        k = min(n, 2 * k)
    return float(np.sqrt(best))


_GAP_ROWS = 32  # rows compared with all rows in the first block of consensus_error
_GAP_BLOCK = 1 << 20  # at most this many numbers in one block's (rows, N, M) temporary


def _largest_squared_gap(t: np.ndarray, rows: np.ndarray) -> float:
    """max over `rows` i and all j of the brute force's squared gap sum_m (t_im - t_jm)^2 (computed alike)."""
    per_block = max(1, _GAP_BLOCK // max(1, t.size))
    best = -np.inf
    for first in range(0, len(rows), per_block):
        gaps = t[rows[first : first + per_block], None, :] - t[None, :, :]
        best = np.maximum(best, (gaps**2).sum(axis=-1).max())  # NaN stays NaN, as in the brute force
    return best


def _gap_bound(radii_sum: float, m: int) -> float:
    """An upper bound on any computed gap |theta^i - theta^j| of two rows whose computed radii sum to `radii_sum`.

    The exact gap is at most the exact radii's sum (triangle inequality); each computed norm is within a relative
    (M + 3) 2^-53 of its exact value, and an underflowing square loses at most 2^-1074 each. The slack below is
    orders of magnitude wider than that and still tight enough to stop early.
    """
    return radii_sum * (1.0 + (m + 4) * 2.0**-40) + 1e-150


# ---------------------------------------------------------------------------------------------- mixing


class Mixer:
    """Consensus rounds of eq. (14) (without the gradient term) under delays, drops and switching links.

    Timing: a call ``mix(thetas, l, r)`` is slot (l, r). Every robot j sends thetas[j] on each outgoing link
    that is up; the message is dropped with probability ``team.drop`` and otherwise arrives in slot (l + D, r),
    D uniform on 0..B0 (``team.delay.max``). Assumption 5 (3) is enforced on the sending side: if a link has
    had no delivered (undropped) send for B = ``team.max_gap`` iterations, the current send is forced through
    (even over a switched-off link), so deliveries are at most B iterations apart and arrivals at most B + B0.
    Switching (``team.switching``): each link is up with probability ``up`` per iteration (both directions of
    an undirected link together), and is forced up when it has been down for ``window`` iterations, so every
    link, hence a strongly connected graph, is up within any ``window`` consecutive iterations.
    """

    def __init__(self, network: Network, team: Any, seed: int):
        self.network = network
        self.settings = check_settings(team)
        if self.settings.robots != network.robots:
            raise BadInput("team.robots", f"is {self.settings.robots} but the network has {network.robots} robots")
        self.seed = int(seed) & MASK
        self.tracking = str(_get(team, "order", "combine_then_adapt")) == TRACKING
        if self.tracking:
            check_tracking(network, team)
        n, m = network.robots, network.n_params
        slots, rounds = self.settings.max_delay + 1, self.settings.rounds
        # Messages in flight, one per (arrival iteration mod B0+1, round, link): a newer send overwrites an
        # older one due in the same slot, which is "the newest sent wins" of the arrival rule.
        self._state = {
            "pending": np.zeros((slots, rounds, n, n, m)),
            "pending_sent": np.full((slots, rounds, n, n), -1, dtype=np.int64),
            "pending_due": np.full((slots, rounds, n, n), -1, dtype=np.int64),
            "latest": np.zeros((n, n, m)),  # newest value received per link (stale="latest")
            "latest_stamp": np.full((n, n), -1, dtype=np.int64),  # its send slot l * R + r, -1 = nothing yet
            "last_delivered": np.zeros((n, n), dtype=np.int64),  # iteration of the last undropped send
            "last_up": np.zeros((n, n), dtype=np.int64),  # iteration the link was last up (switching)
            "up": np.ones((n, n), dtype=bool),  # links up at iteration up_iteration
            "up_iteration": np.array(-1, dtype=np.int64),
            "started": np.array(False),
            "delivered": np.zeros((n, n), dtype=bool),  # last call: links whose send got through
            "forced": np.zeros((n, n), dtype=bool),  # last call: sends forced by max_gap
            "used_sent": np.full((n, n), -1, dtype=np.int64),  # last call: send iteration of the mixed value
        }
        if self.tracking:
            # Gradient tracking (track): the trackers y and their push-sum weights v ride in the same messages as
            # theta, as running sums; the last axis holds [y (M), v (M)].
            self._state.update(
                {
                    "pending_sums": np.zeros((slots, rounds, n, n, 2 * m)),  # the sender's running sums per message
                    "sums": np.zeros((rounds, n, 2 * m)),  # S^j: sum of all [y, v] robot j has sent in round r
                    "seen_sums": np.zeros((rounds, n, n, 2 * m)),  # rho^{ij}: the newest S^j robot i has taken in
                    "seen_sent": np.full((rounds, n, n), -1, dtype=np.int64),  # its send iteration, -1 = none yet
                    # [z^i_{l-1}, v^i_l]: robot i's mixed tracker (before Delta_l - Delta_{l-1}) and push-sum weight
                    "tracker": np.concatenate([np.zeros((n, m)), np.ones((n, m))], axis=1),
                    "gradient": np.zeros((n, m)),  # Delta^i_{l-1}, the gradient last added to the tracker
                }
            )
        # Synchronous teams (no delays, drops or switching; not gradient tracking): every message arrives in its own
        # slot, so `_sync_round` mixes sum_j a^{ij} theta^j directly and notes in `_synced` what the rounds did to
        # the arrays above, which are brought up to date only when something reads them (`_catch_up`).
        self._sync = (
            not self.tracking
            and self.settings.max_delay == 0
            and self.settings.drop == 0.0
            and not self.settings.switching
        )
        self._synced: _Synced | None = None
        self._links: _Links | None = None  # built by the first synchronous round
        self._shared = False  # a snapshot() holds the arrays of _state: copy them before changing them in place

    # Diagnostics of the last call, for tests and logs.
    @property
    def delivered(self) -> np.ndarray:
        """(N, N) bool: links whose message sent in the last call was not dropped."""
        self._catch_up()
        return self._state["delivered"].copy()

    @property
    def forced(self) -> np.ndarray:
        """(N, N) bool: links whose send in the last call was forced through by max_gap."""
        self._catch_up()
        return self._state["forced"].copy()

    @property
    def used_sent(self) -> np.ndarray:
        """(N, N) int: iteration at which the neighbour value mixed in the last call was sent (-1: none)."""
        self._catch_up()
        return self._state["used_sent"].copy()

    def state(self) -> dict[str, np.ndarray]:
        """Everything a resumed Mixer needs, as numpy arrays (copies)."""
        arrays = {key: np.array(value, copy=True) for key, value in self._state.items()}
        if self._synced is not None:
            self._apply_synced(arrays, self._synced)
        return arrays

    def snapshot(self) -> MixerState:
        """The state() of this moment as a read-only mapping that copies nothing until it is read (a checkpoint
        reads it; most iterations' snapshots are never read). Its arrays are the state()'s, bit for bit."""
        self._shared = True
        synced = None if self._synced is None else self._synced.copy()
        return MixerState(dict(self._state), synced, self._apply_synced)

    def restore(self, state: Mapping[str, np.ndarray]) -> Mixer:
        """Load a state() (or snapshot()) taken from a Mixer of the same team; returns self."""
        for key, current in self._state.items():
            if key not in state or np.shape(state[key]) != current.shape:
                raise ValueError(f"checkpoint's consensus state '{key}' does not match this team's network/settings")
        self._state = {key: np.array(state[key], dtype=value.dtype, copy=True) for key, value in self._state.items()}
        self._synced, self._shared = None, False
        return self

    def _own(self) -> None:
        """Copy the arrays a snapshot shares before they change in place."""
        if self._shared:
            self._state = {key: np.array(value, copy=True) for key, value in self._state.items()}
            self._shared = False

    def _catch_up(self) -> None:
        """Bring the arrays up to date with the synchronous rounds since they were last (before reading them or
        mixing by the general rules)."""
        self._own()
        if self._synced is not None:
            self._apply_synced(self._state, self._synced)
            self._synced = None

    def _apply_synced(self, s: dict[str, np.ndarray], synced: _Synced) -> None:
        """Write into `s` (arrays of this Mixer's state, changed in place) what the synchronous rounds in `synced`
        did: exactly what `_send` and `_received` would have written, every link sending and hearing every slot."""
        adjacency, cfg = self.network.adjacency, self.settings
        receiver, sender = np.nonzero(adjacency)
        if synced.first is not None:  # the rounds started the Mixer (see _round)
            s["last_delivered"][:] = synced.first - 1
            s["last_up"][:] = synced.first - 1
            s["started"] = np.array(True)
        s["last_delivered"][receiver, sender] = synced.last
        s["delivered"] = adjacency.copy()
        s["forced"] = np.zeros_like(adjacency)
        for round_index, (iteration, sent) in synced.sent.items():  # slot 0: with B0 = 0 a message is due at once
            s["pending"][0, round_index, receiver, sender, :] = sent[sender]
            s["pending_sent"][0, round_index, receiver, sender] = iteration
            s["pending_due"][0, round_index, receiver, sender] = -1  # consumed on arrival
        stamp, latest = synced.latest
        s["latest"][receiver, sender, :] = latest[sender]
        s["latest_stamp"][receiver, sender] = stamp
        if cfg.stale == "arrival":
            s["used_sent"] = np.where(adjacency, synced.last, -1)
        else:
            s["used_sent"] = np.where(s["latest_stamp"] >= 0, s["latest_stamp"] // cfg.rounds, -1)

    def links_up(self, iteration: int) -> np.ndarray:
        """(N, N) bool links up at `iteration` (all links unless switching is enabled)."""
        return np.array(self._links_up(iteration), copy=True)

    def _links_up(self, iteration: int) -> np.ndarray:
        """Links up at `iteration`, drawn once per iteration and cached so every round sees the same graph."""
        s, adjacency = self._state, self.network.adjacency
        if not self.settings.switching:
            return adjacency
        if int(s["up_iteration"]) != iteration:
            rng = np.random.default_rng([self.seed, SWITCH_STREAM, iteration & MASK])
            draw = rng.random(adjacency.shape) < self.settings.up
            if not self.network.directed:
                draw = np.triu(draw, 1) | np.triu(draw, 1).T  # an undirected link is up both ways or not at all
            overdue = iteration - s["last_up"] >= self.settings.window
            s["up"] = adjacency & (draw | overdue)
            s["last_up"] = np.where(s["up"], iteration, s["last_up"])
            s["up_iteration"] = np.array(iteration, dtype=np.int64)
        return s["up"]

    def mix(self, thetas: np.ndarray, iteration: int, round_index: int = 0) -> np.ndarray:
        """One consensus round of eq. (14) at slot (iteration, round_index): (N, M) in, (N, M) out.

        A gradient-tracking Mixer sends a zero tracker with it (use `track` for the tracking update)."""
        thetas = np.asarray(thetas, dtype=float)
        return self._round(thetas, np.zeros_like(thetas) if self.tracking else None, iteration, round_index)[0]

    def track(self, thetas: np.ndarray, grads: np.ndarray, iteration: int) -> tuple[np.ndarray, np.ndarray]:
        """Gradient tracking (team.order=gradient_tracking: DIGing, MD-PGT without momentum) at iteration l.

        y^i_l = z^i_{l-1} + Delta^i_l - Delta^i_{l-1}, with z_{-1} = Delta_{-1} = 0 so that y_0 = Delta_0. Every robot
        sends (theta^i_l, y^i_l, v^i_l) in one message per round (one delay and drop draw for all). Returns
        (A theta_l, y_l / v_l) and keeps z_l = A y_l and A v_l for the next call; the caller steps
        theta_{l+1} = A theta_l + eps_l y_l / v_l. The trackers y and the push-sum weights v (v_0 = 1) are mixed as
        running sums (`_mix_sums`), so sum_i y^i_l plus the tracker mass still in flight (`in_flight`) equals
        sum_i Delta^i_l under any delays, drops and switching, as long as A is doubly stochastic (checked when the
        Mixer is built). Without delays and drops v stays 1 and this is DIGing's y_{l+1} = A y_l + Delta_{l+1} -
        Delta_l exactly; with them, dividing by v undoes the bursts of late mass (a link that delivers three
        iterations of tracker at once delivers three iterations of weight too), the push-sum correction.
        """
        if not self.tracking:
            raise ValueError("track needs a Mixer of a team with team.order=gradient_tracking")
        thetas, grads = np.asarray(thetas, dtype=float), np.asarray(grads, dtype=float)
        if grads.shape != thetas.shape:
            raise ValueError(f"expected gradients of shape {thetas.shape}, got {grads.shape}")
        if self.network.robots == 1:
            return thetas.copy(), grads.copy()  # no one to track with: eq. (11), bit for bit
        self._catch_up()  # _round would replace _state under `s` otherwise
        s, m = self._state, self.network.n_params
        tracker = s["tracker"][:, :m] + (grads - s["gradient"])
        mass = s["tracker"][:, m:]
        mixed, carried = thetas, np.concatenate([tracker, mass], axis=1)
        for round_index in range(self.settings.rounds):
            mixed, carried = self._round(mixed, carried, iteration, round_index)
        s["tracker"], s["gradient"] = carried, grads.copy()
        return mixed, tracker / mass

    def in_flight(self) -> np.ndarray:
        """(2M,) tracker and push-sum weight mass sent but not yet taken in, [y part, v part]: the sum over
        rounds and links of a^{ij} (S^j - rho^{ij})."""
        if not self.tracking:
            return np.zeros(2 * self.network.n_params)
        self._catch_up()
        s, w = self._state, self.network.weights
        owed = s["sums"][:, None, :, :] - s["seen_sums"]  # (R, N, N, 2M): [r, i, j] what j sent that i lacks
        links = self.network.adjacency[None, :, :, None]
        return (np.where(links, owed, 0.0) * np.concatenate([w, w], axis=2)[None]).sum(axis=(0, 1, 2))

    def _round(
        self, thetas: np.ndarray, carried: np.ndarray | None, iteration: int, round_index: int
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """One round at slot (iteration, round_index): mixed thetas, and the mixed trackers when `carried`."""
        n, m = self.network.robots, self.network.n_params
        if thetas.shape != (n, m):
            raise ValueError(f"expected thetas of shape ({n}, {m}), got {thetas.shape}")
        if not 0 <= round_index < self.settings.rounds:
            raise ValueError(f"round_index {round_index} outside 0..{self.settings.rounds - 1} (team.consensus_rounds)")
        if n == 1:
            return thetas.copy(), None if carried is None else carried.copy()
        iteration = int(iteration)
        if carried is None and self._sync:
            mixed = self._sync_round(thetas, iteration, round_index)
            if mixed is not None:
                return mixed, None
        self._catch_up()
        s = self._state
        if not s["started"]:
            # Gaps are counted from just before the first iteration mixed.
            s["last_delivered"][:] = iteration - 1
            s["last_up"][:] = iteration - 1
            s["started"] = np.array(True)
        self._send(thetas, carried, iteration, round_index)
        mixed, arrived = self._received(thetas, iteration, round_index)
        return mixed, None if carried is None else self._mix_sums(carried, arrived, iteration, round_index)

    def _sync_round(self, thetas: np.ndarray, iteration: int, round_index: int) -> np.ndarray | None:
        """A round of a synchronous team (no delays, drops or switching): every link delivers in the slot it sends,
        so robot i mixes sum_j a^{ij} theta^j (with stale=latest, the newest value each link holds) exactly as
        `_received` would, in the same order of sums, without the (N, N, M) buffers. The arrays of the state are
        left as they were and `_synced` records what to write into them. None when the general rules must decide:
        a slot no later than the newest value the arrays already hold (a Mixer set back in time)."""
        cfg, synced = self.settings, self._synced
        stamp = iteration * cfg.rounds + round_index
        if synced is None and stamp <= int(self._state["latest_stamp"].max()):
            return None
        sent = np.array(thetas, copy=True)
        if synced is None:
            first = None if bool(self._state["started"]) else iteration
            self._synced = synced = _Synced(first, iteration, {}, (stamp, sent))
        elif stamp > synced.latest[0]:
            synced.latest = (stamp, sent)  # a repeated or older slot is not newer: the links keep what they hold
        synced.last = iteration
        synced.sent[round_index] = (iteration, sent)
        neighbour = sent if cfg.stale == "arrival" else synced.latest[1]
        if self._links is None and self.network.n_params > 1:
            self._links = _Links(self.network)
        return _mix_linked(self.network, self._links, thetas, neighbour)

    def _mix_sums(self, carried: np.ndarray, arrived: np.ndarray, iteration: int, round_index: int) -> np.ndarray:
        """Trackers after one round, mixed as running sums: robot i takes a^{ij} (S^j - rho^{ij}) from each link.

        S^j is the sum of every tracker robot j has sent in this round slot, and rho^{ij} the newest S^j that robot
        i has taken in. A message newer than rho^{ij} hands over all the mass sent on the link since then, so a
        dropped or delayed tracker is late, never lost or counted twice, and an older message arriving after a
        newer one is ignored. With no delays or drops the increment is a^{ij} y^j: the plain A y of DIGing.
        """
        s, slot = self._state, iteration % (self.settings.max_delay + 1)
        sent = s["pending_sent"][slot, round_index]
        fresh = arrived & (sent > s["seen_sent"][round_index])
        sums = s["pending_sums"][slot, round_index]
        seen = s["seen_sums"][round_index]
        increment = np.where(fresh[:, :, None], sums - seen, 0.0)
        seen[fresh] = sums[fresh]
        s["seen_sent"][round_index] = np.where(fresh, sent, s["seen_sent"][round_index])
        w = np.concatenate([self.network.weights] * (carried.shape[1] // self.network.n_params), axis=2)
        diagonal = np.arange(len(w))
        off = w.copy()
        off[diagonal, diagonal, :] = 0.0
        return w[diagonal, diagonal, :] * carried + np.einsum("ijm,ijm->im", off, increment)

    def _send(self, thetas: np.ndarray, carried: np.ndarray | None, iteration: int, round_index: int) -> None:
        """Put this slot's messages in flight: delay, drop, forced delivery (Assumption 5 (3)-(4))."""
        s, cfg = self._state, self.settings
        # A fresh generator per slot: no random state crosses iterations, so resume is bit-identical. With B0 = 0
        # the delays are all 0 and integers(0, 1) draws nothing; with drop 0 every message is kept: both skipped.
        rng = np.random.default_rng([self.seed, MIX_STREAM, iteration & MASK, round_index])
        shape = (self.network.robots,) * 2
        delay = rng.integers(0, cfg.max_delay + 1, size=shape) if cfg.max_delay else _NO_INTS
        kept = rng.random(shape) >= cfg.drop if cfg.drop else _NO_FLAGS
        sums, pending_sums = _NO_FLOATS, _NO_PENDING
        if carried is not None:  # the tracker rides in the same message: its sender's running sum
            s["sums"][round_index] += carried
            sums, pending_sums = s["sums"][round_index], s["pending_sums"]
        max_gap = min(cfg.max_gap, INT64_MAX)  # a gap of an int64 iteration never exceeds it: same as any larger B
        args = (
            self.network.adjacency,
            self._links_up(iteration),
            kept,
            delay,
            iteration,
            max_gap,
            round_index,
            np.ascontiguousarray(thetas),
            sums,
            s["last_delivered"],
            s["delivered"],
            s["forced"],
            s["pending"],
            s["pending_sent"],
            s["pending_due"],
            pending_sums,
        )
        if shape[0] * shape[1] >= PARALLEL_ENTRIES:
            _send_parallel(*args)
        else:
            _send_links(*args, 0, shape[0])

    def _received(self, thetas: np.ndarray, iteration: int, round_index: int) -> tuple[np.ndarray, np.ndarray]:
        """The mixed thetas after this slot's arrivals, and the (N, N) links whose message arrived now.

        A link mixes the value that arrived (stale=arrival) or the newest it holds (stale=latest); a neighbour with
        nothing to offer hands its weight to robot i itself, keeping each row stochastic; a late message never
        replaces a newer one, and stale slots never meet a weight, even as 0 * inf."""
        s, cfg, adjacency = self._state, self.settings, self.network.adjacency
        slot = iteration % (cfg.max_delay + 1)
        n = self.network.robots
        arrived, use = np.empty((n, n), dtype=bool), np.empty((n, n), dtype=bool)
        parallel = n * n >= PARALLEL_ENTRIES
        args = (
            adjacency,
            iteration,
            round_index,
            cfg.rounds,
            cfg.stale == "latest",
            s["pending"][slot, round_index],
            s["pending_sent"][slot, round_index],
            s["pending_due"][slot, round_index],
            s["latest"],
            s["latest_stamp"],
            s["used_sent"],
            arrived,
            use,
        )
        if parallel:
            _receive_parallel(*args)
        else:
            _receive_links(*args, 0, n)
        neighbour = s["pending"][slot, round_index] if cfg.stale == "arrival" else s["latest"]
        w = self.network.weights
        if self.network.n_params > 1:
            mixed = np.empty((n, self.network.n_params))
            args = (w, adjacency, use, neighbour, np.ascontiguousarray(thetas), mixed)
            if parallel:
                _mix_used_parallel(*args)
            else:
                _mix_used(*args, 0, n)
            return mixed, arrived
        # One parameter: numpy's own sums (pairwise over j for idle, its einsum order), as they always were.
        return mix_numpy(w, adjacency, use, neighbour, thetas), arrived


def mix_numpy(
    weights: np.ndarray, adjacency: np.ndarray, use: np.ndarray, neighbour: np.ndarray, own: np.ndarray
) -> np.ndarray:
    """sum_j a^{ij} theta^j over the links in `use` (neighbour values), each idle link's weight handed to robot i
    itself (`own`), by numpy: the rule the per-link kernels below follow, summed in numpy's order."""
    n = len(own)
    effective = weights * use[:, :, None]
    idle = (weights * (adjacency & ~use)[:, :, None]).sum(axis=1)
    diagonal = np.arange(n)
    effective[diagonal, diagonal, :] = weights[diagonal, diagonal, :] + idle
    values = np.where(use[:, :, None], neighbour, 0.0)  # stale slots never meet a weight, even as 0 * inf
    values[diagonal, diagonal, :] = own
    return np.einsum("ijm,ijm->im", effective, values)


# The kernels below run over a range of rows (robots i); from PARALLEL_ENTRIES links or (N, N) entries on, their
# _parallel drivers run ROWS rows at a time in parallel. A row is always one thread's: the numbers do not depend
# on the thread count.
PARALLEL_ENTRIES = 1 << 15
ROWS = 16
_NO_INTS = np.zeros((0, 0), dtype=np.int64)  # placeholders for the kernels' optional arrays
_NO_FLAGS = np.zeros((0, 0), dtype=bool)
_NO_FLOATS = np.zeros((0, 0))
_NO_PENDING = np.zeros((0, 0, 0, 0, 0))


@njit(parallel=True, cache=True)
def _send_parallel(
    adjacency,
    up,
    kept,
    delay,
    iteration,
    max_gap,
    round_index,
    thetas,
    sums,
    last_delivered,
    delivered,
    forced,
    pending,
    pending_sent,
    pending_due,
    pending_sums,
):
    """`_send_links` of every row, ROWS at a time in parallel."""
    chunks = (adjacency.shape[0] + ROWS - 1) // ROWS
    for chunk in prange(chunks):
        _send_links(
            adjacency,
            up,
            kept,
            delay,
            iteration,
            max_gap,
            round_index,
            thetas,
            sums,
            last_delivered,
            delivered,
            forced,
            pending,
            pending_sent,
            pending_due,
            pending_sums,
            chunk * ROWS,
            min(adjacency.shape[0], (chunk + 1) * ROWS),
        )


@njit(cache=True)
def _send_links(
    adjacency,
    up,
    kept,
    delay,
    iteration,
    max_gap,
    round_index,
    thetas,
    sums,
    last_delivered,
    delivered,
    forced,
    pending,
    pending_sent,
    pending_due,
    pending_sums,
    first,
    last,
):
    """Mixer._send per link of rows first..last-1: a link that is up sends unless dropped (`kept`, empty: none is);
    one without a delivery for max_gap iterations is forced through; a sent message is due `delay` later (empty:
    at once) in slot due mod B0+1, carrying theta^j (and the running sums `sums`, unless empty)."""
    n = adjacency.shape[0]
    slots = pending.shape[0]
    for i in range(first, last):
        for j in range(n):
            overdue = adjacency[i, j] and iteration - last_delivered[i, j] >= max_gap
            sent = up[i, j] and (kept.shape[0] == 0 or kept[i, j])
            forced[i, j] = overdue and not sent
            sent = sent or overdue
            delivered[i, j] = sent
            if sent:
                last_delivered[i, j] = iteration
                due = iteration + (delay[i, j] if delay.shape[0] else 0)
                slot = due % slots
                pending[slot, round_index, i, j, :] = thetas[j, :]
                pending_sent[slot, round_index, i, j] = iteration
                pending_due[slot, round_index, i, j] = due
                if sums.shape[0]:
                    pending_sums[slot, round_index, i, j, :] = sums[j, :]


@njit(parallel=True, cache=True)
def _receive_parallel(
    adjacency,
    iteration,
    round_index,
    rounds,
    latest_rule,
    pending,
    pending_sent,
    pending_due,
    latest,
    latest_stamp,
    used_sent,
    arrived,
    use,
):
    """`_receive_links` of every row, ROWS at a time in parallel."""
    chunks = (adjacency.shape[0] + ROWS - 1) // ROWS
    for chunk in prange(chunks):
        _receive_links(
            adjacency,
            iteration,
            round_index,
            rounds,
            latest_rule,
            pending,
            pending_sent,
            pending_due,
            latest,
            latest_stamp,
            used_sent,
            arrived,
            use,
            chunk * ROWS,
            min(adjacency.shape[0], (chunk + 1) * ROWS),
        )


@njit(cache=True)
def _receive_links(
    adjacency,
    iteration,
    round_index,
    rounds,
    latest_rule,
    pending,
    pending_sent,
    pending_due,
    latest,
    latest_stamp,
    used_sent,
    arrived,
    use,
    first,
    last,
):
    """Mixer._received's bookkeeping per link of rows first..last-1, on one slot's (N, N[, M]) buffers: arrivals are
    consumed, a newer arrival (stamp l R + r) becomes the link's latest value, and `use` says which links mix a
    neighbour value: the arrived ones (stale=arrival) or those holding any (stale=latest)."""
    n, m = latest.shape[0], latest.shape[2]
    for i in range(first, last):  # selects rather than branches: arrivals come in no order a branch predictor learns
        for j in range(n):
            sent = pending_sent[i, j]
            here = adjacency[i, j] and pending_due[i, j] == iteration
            arrived[i, j] = here
            pending_due[i, j] = -1 if here else pending_due[i, j]  # consumed
            stamp = sent * rounds + round_index
            newer = here and stamp > latest_stamp[i, j]
            for k in range(m):
                latest[i, j, k] = pending[i, j, k] if newer else latest[i, j, k]
            held = stamp if newer else latest_stamp[i, j]
            latest_stamp[i, j] = held
            if latest_rule:
                use[i, j] = held >= 0
                used_sent[i, j] = held // rounds if held >= 0 else -1
            else:
                use[i, j] = here
                used_sent[i, j] = sent if here else -1


@njit(parallel=True, cache=True)
def _mix_used_parallel(weights, adjacency, use, neighbour, own, out):
    """`_mix_used` of every row, ROWS at a time in parallel."""
    chunks = (own.shape[0] + ROWS - 1) // ROWS
    for chunk in prange(chunks):
        _mix_used(weights, adjacency, use, neighbour, own, out, chunk * ROWS, min(own.shape[0], (chunk + 1) * ROWS))


@njit(cache=True)
def _mix_used(weights, adjacency, use, neighbour, own, out, first, last):
    """Rows first..last-1 of sum_j e^{ij}_m v^{ij}_m for M > 1, with e^{ij} = a^{ij}, v^{ij} = neighbour^{ij} on the links in `use`,
    e^{ii} = a^{ii} + idle^i (idle: the weights of the links not in use, summed over j in order) and v^{ii} = own^i:
    numpy's einsum and sums of `_received`, bit for bit (see `_mix_linked`: terms of +0.0 are left out)."""
    n, m = own.shape
    for i in range(first, last):
        for k in range(m):
            idle = 0.0
            for j in range(n):
                a = weights[i, j, k]  # loaded either way, so that the choices below need no branch
                idle += a if adjacency[i, j] and not use[i, j] else 0.0  # + 0.0 leaves a sum >= +0.0 as it is
            diagonal = weights[i, i, k] + idle
            total = 0.0
            for j in range(i):  # a term not in use is +0.0 (a * 0.0): left out, even where a * value is not finite
                term = weights[i, j, k] * neighbour[i, j, k]
                total += term if use[i, j] else 0.0
            total += diagonal * own[i, k]
            for j in range(i + 1, n):
                term = weights[i, j, k] * neighbour[i, j, k]
                total += term if use[i, j] else 0.0
            out[i, k] = total


@dataclass
class _Synced:
    """What the synchronous rounds since the Mixer's arrays were last brought up to date did (Mixer._sync_round)."""

    first: int | None  # the first iteration mixed, when these rounds started the Mixer
    last: int  # the iteration of the last round
    sent: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)  # round -> (iteration, thetas) last sent
    latest: tuple[int, np.ndarray] | None = None  # (slot stamp l R + r, thetas): the newest value on every link

    def copy(self) -> _Synced:
        """A copy that later rounds leave alone (the thetas themselves are never changed)."""
        return _Synced(self.first, self.last, dict(self.sent), self.latest)


class MixerState(Mapping):
    """A Mixer's state at one moment (Mixer.snapshot): a read-only mapping of its arrays, built on first access."""

    def __init__(
        self,
        arrays: dict[str, np.ndarray],
        synced: _Synced | None,
        apply: Callable[[dict[str, np.ndarray], _Synced], None],
    ):
        self._base, self._synced, self._apply = arrays, synced, apply
        self._arrays: dict[str, np.ndarray] | None = None

    def _built(self) -> dict[str, np.ndarray]:
        if self._arrays is None:
            arrays = {key: np.array(value, copy=True) for key, value in self._base.items()}
            if self._synced is not None:
                self._apply(arrays, self._synced)
            self._arrays, self._base, self._synced = arrays, arrays, None
        return self._arrays

    def __getitem__(self, key: str) -> np.ndarray:
        return self._built()[key]

    def __contains__(self, key: object) -> bool:
        return key in self._base

    def __iter__(self) -> Iterator[str]:
        return iter(self._base)

    def __len__(self) -> int:
        return len(self._base)


class _Links:
    """The links of row i of A with the diagonal, in order of j (compressed rows), and their weights a^{ij}_m."""

    def __init__(self, network: Network):
        n = network.robots
        linked = network.adjacency | np.eye(n, dtype=bool)
        receiver, sender = np.nonzero(linked)  # row by row, j increasing
        self.starts = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(linked.sum(axis=1), out=self.starts[1:])
        self.senders = sender.astype(np.int64)
        self.own = np.flatnonzero(receiver == sender)  # where each row's diagonal entry sits
        self.weights = np.ascontiguousarray(network.weights[receiver, sender])  # (links + N, M)


def _mix_linked(network: Network, links: _Links | None, own: np.ndarray, neighbour: np.ndarray) -> np.ndarray:
    """sum_j a^{ij}_m v^{ij}_m with v^{ii} = own^i, v^{ij} = neighbour^j on links and 0 elsewhere: the einsum of
    `_received`, bit for bit. With M > 1 numpy's inner loop runs over m, so each sum over j is taken one term after
    the other, from 0.0; the terms off the links are a^{ij} * 0.0 = +0.0, which leave such a sum as it is (it is
    never -0.0), so the kernel adds the links alone. With M = 1 numpy's inner loop is the sum over j itself, in its
    own order: the very same einsum does it here."""
    n, m = own.shape
    if m == 1 or links is None:
        values = np.where(network.adjacency[:, :, None], neighbour[None, :, :], 0.0)
        values[np.arange(n), np.arange(n), :] = own
        return np.einsum("ijm,ijm->im", network.weights, values)
    out = np.empty((n, m))
    args = (
        links.starts,
        links.senders,
        links.own,
        links.weights,
        np.ascontiguousarray(own),
        np.ascontiguousarray(neighbour),
        out,
    )
    if len(links.senders) >= PARALLEL_ENTRIES:
        _mix_links_parallel(*args)
    else:
        _mix_links(*args, 0, n)
    return out


@njit(parallel=True, cache=True)
def _mix_links_parallel(starts, senders, diagonal, weights, own, neighbour, out):
    """`_mix_links` of every row, ROWS at a time in parallel (each row by one thread)."""
    chunks = (own.shape[0] + ROWS - 1) // ROWS
    for chunk in prange(chunks):
        _mix_links(
            starts, senders, diagonal, weights, own, neighbour, out, chunk * ROWS, min(own.shape[0], (chunk + 1) * ROWS)
        )


@njit(cache=True)
def _mix_links(starts, senders, diagonal, weights, own, neighbour, out, first, last):
    """`_mix_linked` for M > 1, rows first..last-1: each robot's row summed over its links in order of j."""
    m = own.shape[1]
    for i in range(first, last):
        d = diagonal[i]
        for k in range(0, m - 1, 2):  # two parameters at a time: two independent chains of additions
            one, two = 0.0, 0.0
            for p in range(starts[i], d):
                j = senders[p]
                one += weights[p, k] * neighbour[j, k]
                two += weights[p, k + 1] * neighbour[j, k + 1]
            one += weights[d, k] * own[i, k]
            two += weights[d, k + 1] * own[i, k + 1]
            for p in range(d + 1, starts[i + 1]):
                j = senders[p]
                one += weights[p, k] * neighbour[j, k]
                two += weights[p, k + 1] * neighbour[j, k + 1]
            out[i, k], out[i, k + 1] = one, two
        if m % 2:
            k = m - 1
            total = 0.0
            for p in range(starts[i], d):
                total += weights[p, k] * neighbour[senders[p], k]
            total += weights[d, k] * own[i, k]
            for p in range(d + 1, starts[i + 1]):
                total += weights[p, k] * neighbour[senders[p], k]
            out[i, k] = total


# ---------------------------------------------------------------------------------------------- reports


def network_metadata(network: Network) -> dict:
    """JSON-able description of the network for the MCAP log."""
    return {
        "robots": network.robots,
        "graph": network.graph,
        "directed": network.directed,
        "edge_convention": "[i, j]: robot j sends to robot i",
        "edges": network.edges,
        "weights": network.weights.tolist(),  # [i][j][m] = a^{ij}_m
        "positions": None if network.positions is None else network.positions.tolist(),
        "gamma": network.gamma,
        "slem": network.slem,
    }


def _matrix_text(matrix: np.ndarray, indent: str = "    ") -> str:
    """An N x N matrix as aligned rows."""
    rows = np.array2string(matrix, precision=4, suppress_small=True, max_line_width=160).splitlines()
    return "\n".join(indent + row for row in rows)


def describe(network: Network, team: Any) -> str:
    """Multi-line text for `riskplan check`: graph, weights, Assumption 5 parts, SLEM and predicted rate."""
    cfg = check_settings(team)
    n = network.robots
    kind = "directed" if network.directed else "undirected"
    lines = [f"team: {n} robot{'s' if n != 1 else ''}, {network.graph} graph ({kind}), weights={_get(team, 'weights')}"]
    if n == 1:
        lines.append("centralized run: no communication; Assumption 5 holds trivially")
        return "\n".join(lines)
    notation = "j->i: robot j sends to robot i" if network.directed else "i-j: a two-way link"
    lines.append(f"edges ({notation}): {graphs.format_edges(network.adjacency, network.directed)}")
    if network.positions is not None:
        spots = "; ".join(f"{k}:({x:.3f},{y:.3f})" for k, (x, y) in enumerate(network.positions))
        lines.append(f"positions (unit square): {spots}")
    w = network.weights
    same = all(np.array_equal(w[:, :, 0], w[:, :, k]) for k in range(network.n_params))
    lines.append("weights A (row i = what robot i mixes; rows sum to 1):")
    for k in range(1 if same else network.n_params):
        if not same:
            lines.append(f"  parameter {k}:")
        lines.append(_matrix_text(w[:, :, k]))
    doubly = np.allclose(w.sum(axis=0), 1.0, atol=TOL)
    lines.append("Assumption 5: holds")
    switching = f"; under switching every link is up within any {cfg.window} iterations" if cfg.switching else ""
    lines.append("  (1) strongly connected: yes" + switching)
    lines.append(f"  (2) gamma = {network.gamma:.6g} > 0 (smallest weight on the diagonal and on the links)")
    lines.append(
        f"  (3) B = {cfg.max_gap}: a link delivers at least once every {cfg.max_gap} iterations "
        f"(drop probability {cfg.drop:g}; arrivals at most B + B0 = {cfg.max_gap + cfg.max_delay} apart)"
    )
    lines.append(f"  (4) B0 = {cfg.max_delay}: delays uniform on 0..{cfg.max_delay} iterations; stale={cfg.stale}")
    weighted = "" if doubly else ": the consensus value is a weighted, not plain, average"
    lines.append(f"  A is {'doubly' if doubly else 'row'} stochastic{weighted}")
    slem = network.slem
    slem = 0.0 if slem < 1e-12 else slem  # rounding noise of an exact-averaging matrix (e.g. complete graph)
    per_iteration = slem**cfg.rounds
    rate = f"SLEM = {slem:.6g}: on the fixed graph the consensus error shrinks by about x{slem:.4g} per round"
    if cfg.rounds > 1:
        rate += f", x{per_iteration:.4g} per iteration ({cfg.rounds} rounds)"
    if slem == 0:
        rate += " (exact average after one round)"
    elif slem < 1:
        rate += f"; {1.0 / -math.log(slem):.3g} rounds per e-fold"
    lines.append(rate)
    if cfg.max_delay or cfg.drop or cfg.switching:
        lines.append("  (delays, drops and switching slow this down; the SLEM rate is a best case)")
    lines.append(describe_order(str(_get(team, "order", "combine_then_adapt")), cfg))
    return "\n".join(lines)


def describe_order(order: str, cfg: Settings) -> str:
    """One line for `riskplan check`: what team.order does each iteration, and for gradient tracking what is exact."""
    rounds = f"A^{cfg.rounds}" if cfg.rounds > 1 else "A"
    if order == "adapt_then_combine":
        return f"order: adapt_then_combine: theta <- {rounds} (theta + eps Delta) (the gradient steps are mixed too)"
    if order != TRACKING:
        return (
            f"order: combine_then_adapt (eq. 14): theta <- {rounds} theta + eps Delta; the consensus error keeps "
            f"a floor of about eps |Delta^i - Delta^j|"
        )
    text = (
        f"order: gradient_tracking: theta <- {rounds} theta + eps y / v, y <- {rounds} y + Delta_new - Delta_old "
        f"(y_0 = Delta_0); y and the push-sum weight v (v_0 = 1) travel with theta in one message, as running "
        f"sums"
    )
    if cfg.max_delay or cfg.drop or cfg.switching:
        return text + (
            "; sum_i y^i + the mass in flight = sum_i Delta^i exactly; late mass arrives within "
            f"B + B0 = {cfg.max_gap + cfg.max_delay} iterations, so the trackers lag, never drift"
        )
    return text + "; no delays or drops: v = 1 and sum_i y^i = sum_i Delta^i exactly (DIGing)"
