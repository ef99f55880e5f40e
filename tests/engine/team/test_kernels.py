"""The per-link numba kernels (riskplan.engine.team.kernels) add in numpy's einsum order, serial and parallel."""

from __future__ import annotations

import numpy as np
import pytest

from riskplan.engine.team.kernels import mix_numpy


@pytest.mark.parametrize("m", [2, 3, 5, 8, 11])
@pytest.mark.parametrize("n", [3, 40, 200])
def test_mixing_kernels_add_in_numpy_einsum_order(n, m):
    """Terms of wildly different sizes, so that any other order of the sums would round differently."""
    from riskplan.engine.team.kernels import (
        Links,
        _mix_links,
        _mix_links_parallel,
        _mix_used,
        _mix_used_parallel,
        mix_linked,
    )
    from riskplan.engine.team.network import Network

    g = np.random.default_rng(n * m)
    adjacency = g.random((n, n)) < 0.5
    adjacency = (adjacency | adjacency.T) & ~np.eye(n, dtype=bool)
    weights = g.random((n, n, m)) * 10.0 ** g.integers(-8, 8, size=(n, n, m)) * adjacency[:, :, None]
    weights[np.arange(n), np.arange(n), :] = g.random((n, m)) + 0.1
    own = g.normal(size=(n, m)) * 10.0 ** g.integers(-8, 8, size=(n, m))
    neighbour = g.normal(size=(n, n, m)) * 10.0 ** g.integers(-8, 8, size=(n, n, m))
    neighbour[g.random((n, n)) < 0.05] = np.inf  # stale slots may hold anything; those in use must stay finite
    for use in (adjacency & (g.random((n, n)) < 0.6), adjacency, np.zeros_like(adjacency)):
        neighbour_in_use = np.where(use[:, :, None] & ~np.isfinite(neighbour), 1.0, neighbour)
        expected = mix_numpy(weights, adjacency, use, neighbour_in_use, own)
        serial, parallel = np.empty((n, m)), np.empty((n, m))
        _mix_used(weights, adjacency, use, neighbour_in_use, own, serial, 0, n)
        _mix_used_parallel(weights, adjacency, use, neighbour_in_use, own, parallel)
        assert np.array_equal(serial, expected) and np.array_equal(parallel, expected)
    network = Network(n, adjacency, weights, None, "edges", False, 0.1, "team.diagonal")
    sent = g.normal(size=(n, m)) * 10.0 ** g.integers(-8, 8, size=(n, m))
    expected = mix_numpy(weights, adjacency, adjacency, np.broadcast_to(sent, (n, n, m)), own)
    links = Links(network)
    assert np.array_equal(mix_linked(network, links, own, sent), expected)
    serial, parallel = np.empty((n, m)), np.empty((n, m))
    _mix_links(links.starts, links.senders, links.own, links.weights, own, sent, serial, 0, n)
    _mix_links_parallel(links.starts, links.senders, links.own, links.weights, own, sent, parallel)
    assert np.array_equal(serial, expected) and np.array_equal(parallel, expected)
