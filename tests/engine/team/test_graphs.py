"""Team topologies (riskplan.engine.team.graphs): the grid's shape, each topology's links, the edge convention,
random geometric graphs, and strong connectivity."""

from __future__ import annotations

import numpy as np
import pytest
from support import net_of

from riskplan.engine.team import graphs


@pytest.mark.parametrize("n,shape", [(1, (1, 1)), (4, (2, 2)), (6, (2, 3)), (7, (1, 7)), (12, (3, 4)), (16, (4, 4))])
def test_grid_shape_is_most_square(n, shape):
    assert graphs.grid_shape(n) == shape


def test_topologies_have_expected_links():
    assert net_of(robots=4, graph="line").edges == [[0, 1], [1, 2], [2, 3]]
    assert net_of(robots=4, graph="ring").edges == [[0, 1], [0, 3], [1, 2], [2, 3]]
    assert net_of(robots=4, graph="star").edges == [[0, 1], [0, 2], [0, 3]]
    assert len(net_of(robots=5, graph="complete").edges) == 10
    grid = net_of(robots=6, graph="grid")  # 2 x 3: 0 1 2 / 3 4 5
    assert grid.edges == [[0, 1], [0, 3], [1, 2], [1, 4], [2, 5], [3, 4], [4, 5]]
    for net in (grid, net_of(robots=4, graph="ring")):
        assert np.array_equal(net.adjacency, net.adjacency.T) and not net.adjacency.diagonal().any()


def test_edge_convention_j_sends_to_i():
    net = net_of(robots=3, graph="edges", directed=True, edges=[[1, 0], [2, 1], [0, 2]])
    assert net.adjacency[1, 0] and not net.adjacency[0, 1]  # [1, 0]: robot 0 sends to robot 1
    assert net.edges == [[0, 2], [1, 0], [2, 1]]
    w = net.weights[:, :, 0]
    assert w[1, 0] > 0 and w[0, 1] == 0
    undirected = net_of(robots=3, graph="edges", edges=[[1, 0], [2, 1]])
    assert undirected.adjacency[0, 1] and undirected.adjacency[1, 0]


def test_directed_ring_is_a_cycle_and_directed_complete_is_complete():
    ring = net_of(robots=4, graph="ring", directed=True)
    assert ring.edges == [[0, 3], [1, 0], [2, 1], [3, 2]]  # 0->1->2->3->0
    complete = net_of(robots=4, graph="complete", directed=True)
    assert complete.adjacency.sum() == 12


def test_random_geometric_is_seeded_connected_and_within_radius():
    a = net_of(robots=8, graph="random_geometric", radius=0.5, seed=3)
    b = net_of(robots=8, graph="random_geometric", radius=0.5, seed=3)
    c = net_of(robots=8, graph="random_geometric", radius=0.5, seed=4)
    assert np.array_equal(a.positions, b.positions) and not np.array_equal(a.positions, c.positions)
    assert a.positions.shape == (8, 2) and ((a.positions >= 0) & (a.positions <= 1)).all()
    dist = np.linalg.norm(a.positions[:, None] - a.positions[None], axis=-1)
    off = ~np.eye(8, dtype=bool)
    assert np.array_equal(a.adjacency, (dist <= 0.5) & off)
    assert graphs.strongly_connected(a.adjacency)
    assert net_of(robots=4, graph="line").positions is None


def test_strong_connectivity():
    assert graphs.strongly_connected(np.zeros((1, 1), bool))
    assert not graphs.strongly_connected(np.zeros((2, 2), bool))
    chain = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], bool)  # 0 -> 1 -> 2
    assert not graphs.strongly_connected(chain)
    chain[0, 2] = True  # 2 -> 0 closes the cycle
    assert graphs.strongly_connected(chain)
