"""The team's communication network of paper eq. (14): its graph, its mixing weights a^{ij}_m, and the checks of
Assumption 5 (1)-(2) that it passes once, when it is built.

Conventions (see also riskplan.engine.team.graphs):
- ``adjacency[i, j]`` / ``weights[i, j, m]``: robot i receives from robot j; row i of A is what robot i mixes.
- ``team.edges`` entries ``[i, j]`` mean j sends to i (both ways unless ``team.directed``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from riskplan.config.faults import faults_of
from riskplan.config.schema import Aggregate, Graph, Order, TeamConf, WeightRule
from riskplan.engine.team import graphs, robustness
from riskplan.engine.team.convergence import second_largest_eigenvalue_modulus
from riskplan.util.errors import BadInput

TOL = 1e-9  # row-stochasticity tolerance


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
    weights_key: str  # the key the weights came from: team.weights, team.matrix or team.diagonal

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


def build_network(team: TeamConf, n_params: int, seed: int) -> Network:
    """The team's graph and weights (a validated TeamConf), checked against Assumption 5 (1)-(2), and against the
    doubly stochastic weights gradient tracking needs; BadInput naming the key otherwise. With a resilient
    team.aggregate, a graph that is not (2F+1)-robust, or more than F faulty in-neighbours of a healthy robot, is a
    warning (`robustness.condition`), as Assumption 6 is: the run goes on, without the guarantee."""
    graph, directed = Graph(team.graph), team.directed
    adjacency, positions = _adjacency(team, team.robots, seed)
    if graph == Graph.random_geometric:
        directed = False  # distance links are symmetric whatever team.directed says
    if not graphs.strongly_connected(adjacency):
        key = "team.edges" if graph == Graph.edges else "team.graph"
        kind = "directed " if directed else ""
        if graph == Graph.edges:
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
    network = Network(team.robots, adjacency, weights, positions, str(graph), directed, gamma, where)
    if team.order == Order.gradient_tracking:
        check_tracking(network)
    if team.aggregate != Aggregate.mean and network.robots > 1:
        warning = robustness.condition(adjacency, team.aggregate, team.trim, faults_of(team)).warning
        if warning is not None:
            warnings.warn(warning, stacklevel=2)
    return network


def _adjacency(team: TeamConf, robots: int, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Links of the configured topology, and robot positions for random_geometric."""
    if team.graph == Graph.edges:
        return graphs.edges_adjacency(team.edges, robots, team.directed), None
    if team.graph == Graph.random_geometric:
        return graphs.random_geometric(robots, team.radius, team.resample, seed)
    return graphs.named_adjacency(str(team.graph), robots, team.directed), None


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


def _weights(team: TeamConf, adjacency: np.ndarray, n_params: int) -> tuple[np.ndarray, str]:
    """(N, N, M) weights from team.diagonal, team.matrix or the named rule, and the key they came from."""
    n = len(adjacency)
    if team.diagonal is not None:
        what = "N x N x M per-parameter weights a^{ij}_m"
        return _array(team.diagonal, (n, n, n_params), "team.diagonal", what), "team.diagonal"
    rule = WeightRule(team.weights)
    if rule == WeightRule.matrix:
        matrix = team.matrix
        if matrix is None:
            raise BadInput("team.matrix", f"weights=matrix needs team.matrix, a {n} x {n} row-stochastic list of lists")
        plain = _array(matrix, (n, n), "team.matrix", "the N x N row-stochastic matrix A")
        return np.repeat(plain[:, :, None], n_params, axis=2), "team.matrix"
    return np.repeat(rule_weights(str(rule), adjacency)[:, :, None], n_params, axis=2), "team.weights"


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


def check_tracking(network: Network) -> None:
    """team.order=gradient_tracking needs doubly stochastic weights: with a column of A that does not sum to 1,
    mixing changes the sum of the trackers, which then no longer track the sum of the gradients."""
    if network.robots == 1:
        return
    columns = network.weights.sum(axis=0)  # (N, M): column j of A per parameter
    bad = np.abs(columns - 1.0) > TOL
    if bad.any():
        j, m = (int(k) for k in np.argwhere(bad)[0])
        raise BadInput(
            network.weights_key,
            f"column {j} (parameter {m}) of A sums to {columns[j, m]:.6g}, but "
            f"team.order={Order.gradient_tracking} needs doubly stochastic weights (every column summing to 1 "
            f"too) so that the trackers keep the sum of the gradients; use weights=metropolis on "
            f"an undirected graph, or another order",
        )


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
