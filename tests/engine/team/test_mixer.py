"""Consensus layer (paper eq. 14, Assumption 5): graphs, weights, SLEM, delays/drops, resume, bad input."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import team_conf

from riskplan.config.schema import TeamConf
from riskplan.engine.team import graphs
from riskplan.engine.team.convergence import consensus_error, second_largest_eigenvalue_modulus
from riskplan.engine.team.describe import describe
from riskplan.engine.team.mixer import MIX_STREAM, Mixer
from riskplan.engine.team.network import Network, build_network, network_metadata
from riskplan.util.errors import BadInput


def net_of(m: int = 2, seed: int = 0, **values) -> Network:
    """Network of a team built from overrides."""
    return build_network(team_conf(**values), m, seed)


def run_rounds(network, team, thetas, iterations, seed=0, rounds=1):
    """Mix `iterations` times (each with `rounds` rounds); return the per-iteration trajectory."""
    mixer = Mixer(network, team, seed)
    out = [thetas]
    for l in range(iterations):
        for r in range(rounds):
            thetas = mixer.mix(thetas, l, r)
        out.append(thetas)
    return out


# ---------------------------------------------------------------------------------------------- graphs


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


# ---------------------------------------------------------------------------------------------- weights


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


# ---------------------------------------------------------------------------------------------- SLEM


def ring_metropolis_slem(n):
    return max(abs(1 / 3 + 2 / 3 * math.cos(2 * math.pi * k / n)) for k in range(1, n))


@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_slem_closed_forms(n):
    slem = lambda **kw: net_of(robots=n, **kw).slem
    assert slem(graph="line") == pytest.approx((1 + 2 * math.cos(math.pi / n)) / 3, abs=1e-12)
    assert slem(graph="ring") == pytest.approx(ring_metropolis_slem(n), abs=1e-12)
    assert slem(graph="ring", weights="lazy") == pytest.approx(math.cos(math.pi / n) ** 2, abs=1e-12)
    assert slem(graph="star") == pytest.approx(1 - 1 / n, abs=1e-12)
    assert slem(graph="complete") == pytest.approx(0.0, abs=1e-12)
    assert slem(graph="complete", weights="max_degree") == pytest.approx(0.0, abs=1e-12)
    # Directed lazy ring: eigenvalues (1 + e^{2 pi i k/n}) / 2 have moduli |cos(pi k / n)|.
    assert slem(graph="ring", directed=True, weights="lazy") == pytest.approx(math.cos(math.pi / n), abs=1e-12)


def test_slem_matches_numpy_eig_on_grid_and_geometric():
    for kw in ({"graph": "grid", "robots": 9}, {"graph": "random_geometric", "robots": 9, "radius": 0.6}):
        w = net_of(**kw).weights[:, :, 0]
        moduli = np.sort(np.abs(np.linalg.eigvals(w)))
        assert second_largest_eigenvalue_modulus(w) == pytest.approx(moduli[-2], abs=1e-10)
    assert second_largest_eigenvalue_modulus(np.eye(2)) == pytest.approx(1.0)  # no links: no consensus
    assert second_largest_eigenvalue_modulus([[1.0]]) == 0.0


def test_consensus_error_known_values():
    assert consensus_error(np.array([[0.0, 0.0], [3.0, 4.0], [1.0, 0.0]])) == 5.0
    assert consensus_error(np.array([[1.0, 2.0], [1.0, 2.0]])) == 0.0


# ---------------------------------------------------------------------------------------------- fixed-graph mixing


def log_slope(errors):
    """Per-round contraction fitted on the part of a decay curve above rounding noise."""
    errors = np.asarray(errors)
    keep = np.nonzero(errors > errors[0] * 1e-11)[0]
    k = keep[(keep >= 5)]
    slope = np.polyfit(k, np.log(errors[k]), 1)[0]
    return math.exp(slope)


@pytest.mark.parametrize(
    "kw",
    [
        {"graph": "line", "robots": 5},
        {"graph": "ring", "robots": 6},
        {"graph": "star", "robots": 5},
        {"graph": "grid", "robots": 6},
        {"graph": "ring", "robots": 5, "directed": True, "weights": "lazy"},
        {"graph": "line", "robots": 4, "weights": "lazy"},
    ],
)
def test_consensus_error_decays_at_slem_rate(kw):
    team = team_conf(**kw)
    net = build_network(team, 2, 0)
    theta = np.random.default_rng(5).normal(size=(kw["robots"], 2)) * 10
    errors = [consensus_error(t) for t in run_rounds(net, team, theta, 120)]
    assert log_slope(errors) == pytest.approx(net.slem, abs=0.02)


def test_complete_graph_agrees_in_one_round():
    team = team_conf(robots=5, graph="complete", weights="max_degree")
    theta = np.random.default_rng(0).normal(size=(5, 3))
    out = Mixer(build_network(team, 3, 0), team, 0).mix(theta, 0)
    assert consensus_error(out) < 1e-12 and np.allclose(out[0], theta.mean(axis=0))


@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_no_delay_no_drop_is_exactly_the_matrix_product(stale):
    support = net_of(robots=4, graph="ring").adjacency | np.eye(4, dtype=bool)
    diag = (np.random.default_rng(1).random((4, 4, 2)) + 0.1) * support[:, :, None]  # different per parameter
    diag /= diag.sum(axis=1, keepdims=True)
    team = team_conf(robots=4, graph="ring", diagonal=diag.tolist(), stale=stale)
    net = build_network(team, 2, 0)
    mixer, theta = Mixer(net, team, 0), np.random.default_rng(2).normal(size=(4, 2))
    for l in range(5):
        expected = np.einsum("ijm,jm->im", net.weights, theta)
        theta = mixer.mix(theta, l)
        assert np.allclose(theta, expected, rtol=0, atol=1e-14)


def test_doubly_stochastic_weights_keep_the_average():
    team = team_conf(robots=7, graph="grid", consensus_rounds=3)
    net = build_network(team, 2, 0)
    theta = np.random.default_rng(3).normal(size=(7, 2))
    for t in run_rounds(net, team, theta, 20, rounds=3):
        assert np.allclose(t.mean(axis=0), theta.mean(axis=0), atol=1e-12)


# ---------------------------------------------------------------------------------------------- delays and drops


def gaps(times_by_link, start=-1):
    """Largest gap between consecutive event iterations per link, counting from `start`."""
    return max(np.diff([start] + times).max() for times in times_by_link.values())


@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_delays_and_drops_still_reach_consensus_and_respect_bounds(stale):
    b0, b = 3, 4
    team = team_conf(robots=6, graph="ring", delay={"max": b0}, drop=0.5, max_gap=b, stale=stale)
    net = build_network(team, 2, 0)
    mixer, theta = Mixer(net, team, 11), np.random.default_rng(4).normal(size=(6, 2)) * 10
    start = consensus_error(theta)
    links = list(zip(*np.nonzero(net.adjacency)))
    delivered = {link: [] for link in links}
    used = {link: [] for link in links}
    delays, forced = [], 0
    for l in range(400):
        theta = mixer.mix(theta, l)
        for link in links:
            if mixer.delivered[link]:
                delivered[link].append(l)
            sent = mixer.used_sent[link]
            if sent >= 0:
                used[link].append(l)
                delays.append(l - sent)
        forced += mixer.forced.sum()
    assert consensus_error(theta) < 1e-8 * start
    assert gaps(delivered) <= b  # Assumption 5 (3): a delivered send at least every B iterations
    assert forced > 0  # with drop 0.5 and B = 4 the guarantee had to step in
    if stale == "arrival":
        assert min(delays) == 0 and max(delays) == b0  # Assumption 5 (4): delays on 0..B0
        assert gaps(used) <= b + b0  # so every link is heard at least every B + B0 iterations
    else:
        assert min(delays) == 0 and max(delays) <= b + b0  # the newest value held is never older than B + B0


def test_arrival_rule_matches_a_reference_simulation():
    """Newest message on a link wins; a silent neighbour's weight goes to the robot itself."""
    n, b0, b, p, seed = 3, 3, 3, 0.4, 9
    team = team_conf(robots=n, graph="line", delay={"max": b0}, drop=p, max_gap=b)
    net = build_network(team, 1, seed)
    w = net.weights[:, :, 0]
    links = list(zip(*np.nonzero(net.adjacency)))
    mixer, theta = Mixer(net, team, seed), np.array([[0.0], [10.0], [-5.0]])
    ref, inflight, last = theta.copy(), [], {link: -1 for link in links}
    several = 0
    for l in range(60):
        rng = np.random.default_rng([seed, MIX_STREAM, l, 0])
        delay = rng.integers(0, b0 + 1, size=(n, n))
        kept = rng.random((n, n)) >= p
        for i, j in links:
            if kept[i, j] or l - last[(i, j)] >= b:
                last[(i, j)] = l
                inflight.append((l + delay[i, j], l, i, j, ref[j].copy()))
        new = np.zeros_like(ref)
        for i in range(n):
            new[i] = w[i, i] * ref[i]
            for j in np.nonzero(net.adjacency[i])[0]:
                msgs = [x for x in inflight if x[0] == l and x[2] == i and x[3] == j]
                several += len(msgs) > 1
                new[i] += w[i, j] * (max(msgs, key=lambda x: x[1])[4] if msgs else ref[i])
        inflight = [x for x in inflight if x[0] > l]
        ref, theta = new, mixer.mix(theta, l)
        assert np.allclose(theta, ref, rtol=0, atol=1e-12)
    assert several > 0  # the case "several arrive on one link" was exercised


def test_latest_rule_never_goes_back_in_time():
    team = team_conf(robots=4, graph="ring", delay={"max": 4}, drop=0.3, stale="latest")
    net = build_network(team, 2, 0)
    mixer, theta, previous = Mixer(net, team, 1), np.random.default_rng(0).normal(size=(4, 2)), None
    for l in range(50):
        theta = mixer.mix(theta, l)
        used = mixer.used_sent
        if previous is not None:
            assert (used >= previous).all()
        previous = used


# ---------------------------------------------------------------------------------------------- switching


def test_switching_union_over_window_has_every_link_and_consensus_holds():
    window = 4
    team = team_conf(robots=6, graph="ring", switching={"enabled": True, "up": 0.3, "window": window})
    net = build_network(team, 2, 0)
    mixer, theta = Mixer(net, team, 2), np.random.default_rng(6).normal(size=(6, 2))
    ups = []
    for l in range(300):
        theta = mixer.mix(theta, l)
        ups.append(mixer.links_up(l).copy())
    ups = np.array(ups)
    assert np.array_equal(ups[0] & ~net.adjacency, np.zeros_like(net.adjacency))
    assert all(np.array_equal(ups[t], ups[t].T) for t in range(len(ups)))  # undirected links switch both ways
    for t in range(len(ups) - window + 1):
        assert np.array_equal(ups[t : t + window].any(axis=0), net.adjacency)
    fraction = ups[:, net.adjacency].mean()
    assert 0.3 <= fraction <= 0.6  # up with probability 0.3, plus the forced ups
    assert consensus_error(theta) < 1e-8


# ---------------------------------------------------------------------------------------------- determinism


def noisy_team(stale="arrival"):
    return team_conf(
        robots=5,
        graph="grid",
        delay={"max": 3},
        drop=0.3,
        max_gap=3,
        consensus_rounds=2,
        stale=stale,
        switching={"enabled": True, "up": 0.6, "window": 3},
    )


@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_same_seed_same_output_and_resume_is_bit_identical(stale, tmp_path):
    team = noisy_team(stale)
    net = build_network(team, 2, 0)
    theta0 = np.random.default_rng(7).normal(size=(5, 2))
    full = run_rounds(net, team, theta0, 30, seed=5, rounds=2)
    again = run_rounds(net, team, theta0, 30, seed=5, rounds=2)
    other = run_rounds(net, team, theta0, 30, seed=6, rounds=2)
    assert all(np.array_equal(a, b) for a, b in zip(full, again))
    assert not np.array_equal(full[-1], other[-1])

    mixer, theta = Mixer(net, team, 5), theta0
    for l in range(13):
        for r in range(2):
            theta = mixer.mix(theta, l, r)
    state = mixer.state()
    assert all(isinstance(v, np.ndarray) for v in state.values())
    np.savez(tmp_path / "ck.npz", **state)  # a checkpoint writer can store it as is
    loaded = dict(np.load(tmp_path / "ck.npz"))
    as_json = json.loads(json.dumps({key: value.tolist() for key, value in state.items()}))  # a JSON checkpoint
    for saved in (loaded, as_json):
        resumed, theta_r = Mixer(build_network(team, 2, 0), team, 5).restore(saved), theta
        for l in range(13, 30):
            for r in range(2):
                theta_r = resumed.mix(theta_r, l, r)
            assert np.array_equal(theta_r, full[l + 1])


def test_state_is_a_copy_and_restore_checks_shapes():
    team = noisy_team()
    net = build_network(team, 2, 0)
    mixer = Mixer(net, team, 0)
    state = mixer.state()
    state["pending"][...] = 99.0
    assert not (mixer.state()["pending"] == 99.0).any()
    other = team_conf(robots=4, graph="ring")
    with pytest.raises(ValueError):
        Mixer(build_network(other, 2, 0), other, 0).restore(state)


def test_mix_rejects_wrong_shapes_and_rounds():
    team = team_conf(robots=3, consensus_rounds=2)
    mixer = Mixer(build_network(team, 2, 0), team, 0)
    with pytest.raises(ValueError):
        mixer.mix(np.zeros((3, 3)), 0)
    with pytest.raises(ValueError):
        mixer.mix(np.zeros((3, 2)), 0, round_index=2)


# ---------------------------------------------------------------------------------------------- reports


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


# ---------------------------------------------------------------------------------------------- bad input

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
