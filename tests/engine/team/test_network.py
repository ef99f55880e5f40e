"""The team's network (riskplan.engine.team.network, Assumption 5 (1)-(2)): the single robot, frozen networks, the
weights (Metropolis, max-degree, lazy, an explicit matrix, per-parameter diagonals), how `riskplan check` describes
it, and bad input naming the key."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from support import net_of, team_conf

from riskplan.config.schema import TeamConf
from riskplan.engine.team.convergence import consensus_error
from riskplan.engine.team.describe import describe
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import build_network, network_metadata
from riskplan.util.errors import BadInput


def test_single_robot_is_trivial():
    for graph in ("line", "ring", "star", "complete", "grid", "random_geometric"):
        net = net_of(robots=1, graph=graph)
        assert net.weights.shape == (1, 1, 2) and np.all(net.weights == 1.0)
        assert net.slem == 0.0 and net.edges == []
    team = team_conf(robots=1)
    theta = np.array([[1.0, 2.0]])
    out = Mixer(net_of(robots=1), team, 0).mix(theta, 0)
    assert np.array_equal(out, theta) and out is not theta
    assert consensus_error(theta) == 0.0
    assert "centralized" in describe(net_of(robots=1), team)


def test_plain_dataclass_team_is_accepted():
    net = build_network(TeamConf(robots=3, graph="ring"), 2, 0)
    assert net.robots == 3 and net.graph == "ring"


def test_network_is_frozen():
    net = net_of(robots=3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        net.robots = 4
    with pytest.raises(ValueError):
        net.weights[0, 0, 0] = 0.5


def test_metropolis_values_and_double_stochasticity():
    net = net_of(robots=3, graph="line")
    expected = np.array([[2, 1, 0], [1, 1, 1], [0, 1, 2]]) / 3
    assert np.allclose(net.weights[:, :, 0], expected) and np.allclose(net.weights[:, :, 1], expected)
    assert net.gamma == pytest.approx(1 / 3)
    for graph in ("line", "ring", "star", "complete", "grid", "random_geometric"):
        w = net_of(robots=7, graph=graph, radius=0.7).weights
        assert np.allclose(w.sum(axis=0), 1.0) and np.allclose(w.sum(axis=1), 1.0)


def test_max_degree_and_lazy_values():
    star = net_of(robots=4, graph="star", weights="max_degree").weights[:, :, 0]
    assert np.allclose(star[0], [0.25, 0.25, 0.25, 0.25])
    assert np.allclose(star[1], [0.25, 0.75, 0, 0])
    lazy = net_of(robots=4, graph="star", weights="lazy").weights[:, :, 0]
    assert np.allclose(lazy[0], [0.5, 1 / 6, 1 / 6, 1 / 6])
    assert np.allclose(lazy[2], [0.5, 0, 0.5, 0])


def test_directed_metropolis_is_row_stochastic_with_positive_links():
    net = net_of(robots=4, graph="edges", directed=True, edges=[[1, 0], [2, 1], [3, 2], [0, 3], [0, 2]])
    w = net.weights[:, :, 0]
    assert np.allclose(w.sum(axis=1), 1) and (w[net.adjacency] > 0).all() and (np.diag(w) > 0).all()
    assert (w[~net.adjacency & ~np.eye(4, dtype=bool)] == 0).all()


def test_explicit_matrix_and_per_parameter_diagonal():
    matrix = [[0.5, 0.5, 0.0], [0.25, 0.5, 0.25], [0.0, 0.1, 0.9]]
    net = net_of(robots=3, graph="line", weights="matrix", matrix=matrix)
    assert np.allclose(net.weights[:, :, 1], matrix) and net.gamma == pytest.approx(0.1)
    diag = np.stack([np.array(matrix), np.array([[2, 1, 0], [1, 1, 1], [0, 1, 2]]) / 3], axis=2)
    net = net_of(robots=3, graph="line", diagonal=diag.tolist())
    assert np.allclose(net.weights, diag)
    assert "parameter 1" in describe(net, team_conf(robots=3, graph="line", diagonal=diag.tolist()))


def test_describe_and_metadata():
    team = team_conf(robots=4, graph="ring", delay={"max": 2}, drop=0.1, max_gap=5)
    net = build_network(team, 2, 0)
    text = describe(net, team)
    parts = ("ring", "0-1", "Assumption 5", "(1)", "(2) gamma = 0.333333", "(3) B = 5", "(4) B0 = 2", "SLEM = 0.333333")
    for part in parts:
        assert part in text, part
    meta = json.loads(json.dumps(network_metadata(net)))
    assert meta["robots"] == 4 and meta["edges"] == net.edges and meta["graph"] == "ring"
    assert np.allclose(meta["weights"], net.weights) and meta["positions"] is None
    assert meta["gamma"] == pytest.approx(1 / 3) and meta["slem"] == pytest.approx(1 / 3)
    geo = network_metadata(net_of(robots=5, graph="random_geometric", radius=0.8))
    assert len(json.loads(json.dumps(geo))["positions"]) == 5
    assert "exact average" in describe(net_of(robots=3, graph="complete"), team_conf(robots=3, graph="complete"))


LINE3 = {"robots": 3, "graph": "line"}
BAD = [
    ({"robots": 0}, "team.robots"),
    ({"graph": "tree"}, "team.graph"),
    ({"weights": "uniform"}, "team.weights"),
    ({"stale": "oldest"}, "team.stale"),
    ({"delay": {"max": -1}}, "team.delay.max"),
    ({"drop": 1.0}, "team.drop"),
    ({"drop": -0.1}, "team.drop"),
    ({"max_gap": 0}, "team.max_gap"),
    ({"consensus_rounds": 0}, "team.consensus_rounds"),
    ({"resample": -1}, "team.resample"),
    ({"switching": {"enabled": True, "window": 0}}, "team.switching.window"),
    ({"switching": {"enabled": True, "up": 0.0}}, "team.switching.up"),
    ({"switching": {"enabled": True, "up": 1.5}}, "team.switching.up"),
    ({**LINE3, "directed": True}, "team.graph"),
    ({"robots": 3, "graph": "star", "directed": True}, "team.graph"),
    ({"robots": 3, "graph": "edges", "edges": [[0, 1]]}, "team.edges"),
    ({"robots": 3, "graph": "edges"}, "team.edges"),
    ({"robots": 3, "graph": "edges", "edges": [[0, 1], [1, 3]]}, "team.edges"),
    ({"robots": 3, "graph": "edges", "edges": [[0, 1, 2]]}, "team.edges"),
    ({"robots": 3, "graph": "edges", "edges": [[0, 1], [1, 1]]}, "team.edges"),
    ({**LINE3, "weights": "matrix"}, "team.matrix"),
    ({**LINE3, "weights": "matrix", "matrix": [[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]]}, "team.matrix"),
    ({**LINE3, "weights": "matrix", "matrix": [[0.5, 0.5, 0.0], [0.3, 0.3, 0.3], [0.0, 0.5, 0.5]]}, "team.matrix"),
    ({**LINE3, "weights": "matrix", "matrix": [[1.0, 0.0, 0.0], [0.5, 0.25, 0.25], [0.0, 0.5, 0.5]]}, "team.matrix"),
    ({**LINE3, "weights": "matrix", "matrix": [[0.5, 0.4, 0.1], [0.5, 0.25, 0.25], [0.0, 0.5, 0.5]]}, "team.matrix"),
    ({**LINE3, "weights": "matrix", "matrix": [[1.5, -0.5, 0.0], [0.5, 0.25, 0.25], [0.0, 0.5, 0.5]]}, "team.matrix"),
    ({**LINE3, "weights": "matrix", "matrix": [[0.0, 1.0, 0.0], [0.5, 0.25, 0.25], [0.0, 0.5, 0.5]]}, "team.matrix"),
    ({**LINE3, "diagonal": [[[1.0, 1.0]] * 3] * 3}, "team.diagonal"),
    ({**LINE3, "diagonal": [[[0.5], [0.5], [0.0]]] * 3}, "team.diagonal"),
    ({"robots": 12, "graph": "random_geometric", "radius": 0.05, "resample": 3}, "team.radius"),
    ({"robots": 3, "graph": "random_geometric", "radius": 0.0}, "team.radius"),
]


@pytest.mark.parametrize("values,where", BAD, ids=[f"{w}-{k}" for k, (_, w) in enumerate(BAD)])
def test_bad_input_names_the_key(values, where):
    with pytest.raises(BadInput) as err:
        build_network(team_conf(**values), 2, 0)
    assert err.value.where == where
    assert "\n" not in str(err.value) and len(err.value.problem) > 10


def test_messages_say_what_is_valid():
    with pytest.raises(BadInput, match="expected one of line, ring, star, complete, grid, random_geometric, edges"):
        build_network(team_conf(graph="tree"), 2, 0)
    with pytest.raises(BadInput, match="Assumption 5 \\(1\\)"):
        build_network(team_conf(**LINE3, directed=True), 2, 0)
    with pytest.raises(BadInput, match=r"larger team\.radius"):
        build_network(team_conf(robots=12, graph="random_geometric", radius=0.05, resample=2), 2, 0)
    with pytest.raises(BadInput, match=r"valid indices are 0\.\.2"):
        build_network(team_conf(robots=3, graph="edges", edges=[[0, 5]]), 2, 0)
