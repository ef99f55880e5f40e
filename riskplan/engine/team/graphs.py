"""Communication graphs of paper Section IV: topologies, link direction and strong connectivity.

Convention used everywhere in riskplan: ``adjacency[i, j]`` is True when robot i receives from robot j (i != j),
i.e. the row of a robot lists whom it listens to, like row i of the weight matrix A in eq. (14). An edge written
``[i, j]`` (``team.edges``) means the same: j sends to i; undirected edges go both ways.
"""

from __future__ import annotations

import math

import numpy as np

from riskplan.util.checks import is_whole
from riskplan.util.errors import BadInput

MASK = (1 << 64) - 1
GEOMETRIC_STREAM = 7907  # keeps random_geometric draws apart from the Mixer's streams


def grid_shape(robots: int) -> tuple[int, int]:
    """The most square rows x cols with rows * cols == robots and rows <= cols."""
    rows = max(r for r in range(1, math.isqrt(robots) + 1) if robots % r == 0)
    return rows, robots // rows


def _pairs(graph: str, robots: int) -> list[tuple[int, int]]:
    """Edges of a named topology as (sender, receiver), oriented the way a directed version runs."""
    n = robots
    if graph == "line":
        return [(k, k + 1) for k in range(n - 1)]
    if graph == "ring":
        # N = 2 would list 0-1 twice; the closing link only exists from 3 robots on.
        closing = [(n - 1, 0)] if n >= 3 else [(1, 0)] if n == 2 else []
        return [(k, k + 1) for k in range(n - 1)] + closing
    if graph == "star":
        return [(0, k) for k in range(1, n)]
    if graph == "complete":
        return [(j, i) for j in range(n) for i in range(n) if i != j]
    if graph == "grid":
        _rows, cols = grid_shape(n)
        right = [(k, k + 1) for k in range(n) if (k % cols) + 1 < cols]
        down = [(k, k + cols) for k in range(n) if k + cols < n]
        return right + down
    raise ValueError(f"no fixed topology named {graph!r}")


def named_adjacency(graph: str, robots: int, directed: bool) -> np.ndarray:
    """Adjacency of line/ring/star/complete/grid; directed ones send lower -> higher index (ring closes N-1 -> 0)."""
    adjacency = np.zeros((robots, robots), dtype=bool)
    for sender, receiver in _pairs(graph, robots):
        adjacency[receiver, sender] = True
        if not directed:
            adjacency[sender, receiver] = True
    return adjacency


def edges_adjacency(edges, robots: int, directed: bool) -> np.ndarray:
    """Adjacency of an explicit list [[i, j], ...] (j sends to i; both ways unless directed)."""
    if edges is None:
        problem = "graph=edges needs team.edges, a list of [i, j] pairs (j sends to i), e.g. [[0,1],[1,2]]"
        raise BadInput("team.edges", problem)
    adjacency = np.zeros((robots, robots), dtype=bool)
    for k, edge in enumerate(edges):
        i, j = _edge(edge, k, robots)
        adjacency[i, j] = True
        if not directed:
            adjacency[j, i] = True
    return adjacency


def _edge(edge, k: int, robots: int) -> tuple[int, int]:
    """One validated [i, j] pair of team.edges."""
    try:
        pair = None if isinstance(edge, str) else list(edge)
    except TypeError:
        pair = None
    if pair is None or len(pair) != 2 or not all(is_whole(x) for x in pair):
        raise BadInput("team.edges", f"entry {k} is {edge!r}; each edge must be a pair [i, j] of robot indices")
    i, j = int(pair[0]), int(pair[1])
    if not (0 <= i < robots and 0 <= j < robots):
        problem = f"entry {k} [{i}, {j}] names a robot that does not exist; valid indices are 0..{robots - 1}"
        raise BadInput("team.edges", problem)
    if i == j:
        problem = f"entry {k} [{i}, {j}] is a self-loop; list links between different robots (A's diagonal is implicit)"
        raise BadInput("team.edges", problem)
    return i, j


def random_geometric(robots: int, radius: float, resample: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Robots uniform in the unit square, linked within `radius`; redrawn up to `resample` times until connected."""
    for attempt in range(resample + 1):
        # One generator per attempt, keyed by (seed, attempt): the graph depends on the seed only.
        rng = np.random.default_rng([int(seed) & MASK, GEOMETRIC_STREAM, attempt])
        positions = rng.random((robots, 2))
        distance = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
        adjacency = (distance <= radius) & ~np.eye(robots, dtype=bool)
        if strongly_connected(adjacency):
            return adjacency, positions
    hint = math.sqrt(2.0 * math.log(max(robots, 2)) / robots)
    raise BadInput(
        "team.radius",
        f"no random_geometric draw of {robots} robots with radius {radius:g} was connected in {resample + 1} tries "
        f"(Assumption 5 (1)); use a larger team.radius (about {max(hint, radius * 1.5):.2f} or more) "
        "or a larger team.resample",
    )


def _reaches_all(adjacency: np.ndarray) -> bool:
    """Whether information from robot 0 reaches every robot along links (j -> i when adjacency[i, j])."""
    seen = np.zeros(len(adjacency), dtype=bool)
    seen[0] = True
    frontier = seen.copy()
    while frontier.any():
        heard = adjacency[:, frontier].any(axis=1)
        frontier = heard & ~seen
        seen |= frontier
    return bool(seen.all())


def strongly_connected(adjacency: np.ndarray) -> bool:
    """Assumption 5 (1): a directed path between every ordered pair (one robot trivially qualifies)."""
    adjacency = np.asarray(adjacency, dtype=bool)
    if len(adjacency) <= 1:
        return True
    # Strongly connected iff robot 0 reaches everyone and everyone reaches robot 0.
    return _reaches_all(adjacency) and _reaches_all(adjacency.T)


def edge_list(adjacency: np.ndarray, directed: bool) -> list[list[int]]:
    """Links as [i, j] pairs (j sends to i); an undirected link is listed once with i < j."""
    rows, cols = np.nonzero(adjacency)
    if directed:
        return [[int(i), int(j)] for i, j in zip(rows, cols)]
    return [[int(i), int(j)] for i, j in zip(rows, cols) if i < j]


def format_edges(adjacency: np.ndarray, directed: bool, limit: int = 40) -> str:
    """Short text of the links: 'j->i' (j sends to i) when directed, 'i-j' otherwise."""
    pairs = edge_list(adjacency, directed)
    text = [f"{j}->{i}" if directed else f"{i}-{j}" for i, j in pairs]
    if not text:
        return "none"
    more = f", ... ({len(text) - limit} more)" if len(text) > limit else ""
    return ", ".join(text[:limit]) + more
