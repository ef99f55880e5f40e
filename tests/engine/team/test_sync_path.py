"""The team loop's fast paths (a 1000-robot team within 1.5x of a centralized run): each must give the numbers of
the plain computation it replaces, bit for bit. The plain computations are written out here as references."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numba
import numpy as np
import pytest
from conftest import team_conf

import riskplan
from riskplan.engine import rng
from riskplan.engine.policy import move_features, probabilities, scores, tables
from riskplan.engine.team.convergence import consensus_error
from riskplan.engine.team.kernels import mix_numpy
from riskplan.engine.team.mixer import Mixer, MixerState
from riskplan.engine.team.network import build_network
from riskplan.risk import summary_stats
from riskplan.run.build import build_setup
from riskplan.run.training import _robot_rows, _row, train

# ---------------------------------------------------------------------------------------------- consensus error


def brute_force_error(thetas: np.ndarray) -> float:
    """The definition, over all N^2 pairs at once (consensus_error's former body)."""
    t = np.asarray(thetas, dtype=float)
    if len(t) <= 1:
        return 0.0
    gaps = t[:, None, :] - t[None, :, :]
    return float(np.sqrt((gaps**2).sum(axis=-1)).max())


def test_consensus_error_known_answers_beyond_the_first_block():
    grid = np.array([[i, j] for i in range(30) for j in range(20)], dtype=float)  # 600 rows: the pruned path
    grid = grid[np.random.default_rng(0).permutation(len(grid))]
    assert consensus_error(grid) == math.sqrt(29**2 + 19**2)
    ball = np.random.default_rng(1).normal(size=(500, 3))
    ball /= 2 * np.linalg.norm(ball, axis=1, keepdims=True)  # radius 1/2 around 0
    cloud = np.vstack([ball[:200], [[3.0, 4.0, 0.0]], ball[200:], [[-3.0, -4.0, 0.0]]])
    assert consensus_error(cloud) == 10.0  # the two far points; any other pair is at most 5.5 apart
    assert consensus_error(np.full((100, 2), 0.1)) == 0.0
    assert consensus_error(np.zeros((3, 0))) == 0.0


def test_consensus_error_finds_a_diameter_away_from_the_farthest_rows():
    """65 rows evenly on the unit circle (no two opposite: at most 2 cos(pi / 130) = 1.99942 apart) and two opposite
    rows just inside it, 1.9999 apart, whose directions are a quarter spacing off the circle's rows (so they are at
    most 1.99995 - 0.00015 from any): the widest pair is of the two rows nearest the centroid, and the first 64 rows
    already see a gap within 3e-4 of the bound 1 + 0.99995 on the pairs left."""
    step = 2 * np.pi / 65
    circle = np.column_stack([np.cos(step * np.arange(65)), np.sin(step * np.arange(65))])
    p = 0.99995 * np.array([np.cos(step / 4), np.sin(step / 4)])
    thetas = np.vstack([circle[:20], p, circle[20:], -p])
    assert abs(consensus_error(thetas) - 1.9999) < 1e-12
    assert consensus_error(thetas) == brute_force_error(thetas)


def _cloud(kind: str, n: int, m: int, seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    if kind == "normal":
        return g.normal(size=(n, m)) * 10
    if kind == "sphere":  # every row as far from the centroid: nothing can be pruned
        t = g.normal(size=(n, m))
        return t / np.linalg.norm(t, axis=1, keepdims=True)
    if kind == "ties":
        return np.round(g.normal(size=(n, m)) * 2)
    if kind == "near_consensus":
        return 20.0 + g.normal(size=(n, m)) * 1e-13
    if kind == "wide_magnitudes":
        return g.normal(size=(n, m)) * 10.0 ** g.integers(-150, 150, size=(n, m))
    if kind == "tiny":  # squares underflow
        return g.normal(size=(n, m)) * 1e-160
    if kind == "huge":  # squares overflow to inf
        return g.normal(size=(n, m)) * 1e155
    if kind == "one_apart":
        t = np.full((n, m), 3.0)
        t[n // 2, 0] = 3.5
        return t
    if kind == "nan":
        t = g.normal(size=(n, m))
        t[n // 3, m - 1] = np.nan
        return t
    if kind == "inf":
        t = g.normal(size=(n, m))
        t[n // 3, 0] = np.inf
        return t
    raise ValueError(kind)


@pytest.mark.parametrize(
    "kind", ["normal", "sphere", "ties", "near_consensus", "wide_magnitudes", "tiny", "huge", "one_apart", "nan", "inf"]
)
@pytest.mark.parametrize(
    "n,m", [(1, 2), (2, 2), (2, 1), (5, 3), (32, 2), (33, 2), (64, 1), (65, 2), (300, 2), (257, 3), (200, 7), (150, 9)]
)
def test_consensus_error_is_the_brute_force_bit_for_bit(kind, n, m):
    thetas = _cloud(kind, n, m, seed=n * 31 + m)
    with np.errstate(over="ignore", invalid="ignore"):
        expected = brute_force_error(thetas)
        got = consensus_error(thetas)
    assert type(got) is float
    assert got == expected or (math.isnan(got) and math.isnan(expected))


def test_consensus_error_of_team_thetas_is_the_brute_force():
    """Clouds as a team run makes them: a 1000-robot team's thetas after a few consensus steps."""
    team = team_conf(robots=400, graph="random_geometric")
    net = build_network(team, 2, 0)
    mixer, g = Mixer(net, team, 0), np.random.default_rng(5)
    thetas = 20.0 + g.normal(size=(400, 2))
    for l in range(6):
        thetas = mixer.mix(thetas, l) + 0.1 * g.normal(size=(400, 2))
        assert consensus_error(thetas) == brute_force_error(thetas)


# ---------------------------------------------------------------------------------------------- robot keys


@pytest.mark.parametrize(
    "seed,purpose,iteration,robots",
    [
        (0, rng.TRAIN, 0, 1),
        (0, rng.TRAIN, 7, 1000),
        (2**63 - 1, rng.PATHS, 2**40 + 3, 50),
        (12345, rng.EVAL, 1, 3),
        (5, rng.TRAIN, 0, 0),
        (2**63 - 1, rng.TRAIN, 2**64 - 1, 5),
        (77, rng.BOOTSTRAP, 3, 4),
    ],
)
def test_robot_keys_are_the_scalar_stream_keys(seed, purpose, iteration, robots):
    keys = rng.robot_keys(seed, purpose, iteration, robots)
    expected = np.array([rng.stream_key(seed, purpose, iteration, r) for r in range(robots)], dtype=np.uint64)
    assert keys.dtype == np.uint64 and keys.shape == (robots,)
    assert np.array_equal(keys, expected)


def test_robot_keys_known_values():
    """Keys as the scalar loop gave them before robot_keys was vectorised."""
    assert rng.robot_keys(0, rng.TRAIN, 0, 3).tolist() == [
        15060180617161591093,
        17701245739403276522,
        902475832917225024,
    ]
    assert int(rng.robot_keys(2**63 - 1, rng.EVAL, 99, 5)[4]) == 7221517220371294345


# ---------------------------------------------------------------------------------------------- mixer


def general(network, team, seed) -> Mixer:
    """A Mixer that mixes by the general rules (the message buffers) even on a synchronous team."""
    mixer = Mixer(network, team, seed)
    mixer._sync = False
    return mixer


def assert_same_mixers(fast: Mixer, plain: Mixer) -> None:
    for name in ("delivered", "forced", "used_sent"):
        assert np.array_equal(getattr(fast, name), getattr(plain, name)), name
    assert_same_state(fast.state(), plain.state())


def assert_same_state(got: Mapping, expected: Mapping) -> None:
    assert list(got) == list(expected)
    for key in expected:
        assert got[key].dtype == expected[key].dtype and np.array_equal(got[key], expected[key]), key


SLOTS = [(0, 0), (1, 0), (2, 0), (2, 0), (3, 0), (1, 0), (5, 0), (5, 0), (9, 0), (10, 0), (4, 0), (11, 0)]


@pytest.mark.parametrize("stale", ["arrival", "latest"])
@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize(
    "graph",
    [
        {"robots": 3, "graph": "line"},
        {"robots": 6, "graph": "ring", "weights": "lazy"},
        {"robots": 4, "graph": "edges", "edges": [[0, 1], [1, 2], [2, 3], [3, 0], [2, 0]], "directed": True},
        {"robots": 12, "graph": "random_geometric", "radius": 0.6},
    ],
)
@pytest.mark.parametrize("rounds", [1, 2])
@pytest.mark.parametrize("read_every_iteration", [True, False])
def test_synchronous_rounds_equal_the_general_rules(stale, m, graph, rounds, read_every_iteration):
    """Every call (forward, repeated and backward slots) mixes the same numbers, leaves the same state and
    diagnostics, and a snapshot taken at any call reads as that call's state, however late it is read; whether
    the diagnostics are read every iteration (bringing the arrays up to date) or only at the end."""
    team = team_conf(stale=stale, consensus_rounds=rounds, **graph)
    net = build_network(team, m, 3)
    fast, plain = Mixer(net, team, 4), general(net, team, 4)
    g = np.random.default_rng(m * 7 + rounds)
    thetas, snapshots, took_fast_path = g.normal(size=(net.robots, m)) * 5, [], False
    for l, _ in SLOTS:
        for r in range(rounds):
            thetas = g.normal(size=thetas.shape) * 5 if r == 0 else thetas
            a, b = fast.mix(thetas, l, r), plain.mix(thetas, l, r)
            took_fast_path |= fast._store.deferred is not None
            assert np.array_equal(a, b)
            snapshots.append((fast.snapshot(), plain.state()))
            thetas = a
        if read_every_iteration:
            assert_same_mixers(fast, plain)
    assert_same_mixers(fast, plain)
    assert took_fast_path
    for snapshot, expected in snapshots:
        assert isinstance(snapshot, Mapping) and isinstance(snapshot, MixerState)
        assert_same_state(snapshot, expected)


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


def test_known_average_on_the_complete_graph():
    """max_degree weights on 4 complete robots are all 1/4: one round gives every robot the exact average."""
    team = team_conf(robots=4, graph="complete", weights="max_degree")
    for thetas, mean in (
        ([[4.0, 8.0], [0.0, -4.0], [8.0, 12.0], [-4.0, 0.0]], [2.0, 4.0]),
        ([[4.0], [0.0], [8.0], [-4.0]], [2.0]),
    ):
        mixer = Mixer(build_network(team, len(mean), 0), team, 0)
        assert np.array_equal(mixer.mix(np.array(thetas), 0), np.tile(mean, (4, 1)))
        assert mixer._store.deferred is not None  # the synchronous path did it
        assert np.array_equal(mixer.used_sent, np.where(~np.eye(4, dtype=bool), 0, -1))
        assert mixer.delivered.sum() == 12 and not mixer.forced.any()


def test_line_mixing_known_answer():
    """Metropolis on the 3-robot line: every link weighs 1/3, the ends keep 2/3."""
    team = team_conf(robots=3, graph="line")
    mixer = Mixer(build_network(team, 2, 0), team, 0)
    out = mixer.mix(np.array([[3.0, 0.0], [0.0, 3.0], [6.0, -3.0]]), 0)
    np.testing.assert_allclose(out, [[2.0, 1.0], [3.0, 0.0], [4.0, -1.0]], rtol=0, atol=1e-14)


def test_snapshot_is_a_lazy_read_only_copy():
    team = team_conf(robots=5, graph="ring")
    mixer = Mixer(build_network(team, 2, 0), team, 0)
    thetas = np.arange(10.0).reshape(5, 2)
    mixer.mix(thetas, 0)
    snapshot, state = mixer.snapshot(), mixer.state()
    assert set(snapshot) == set(state) and len(snapshot) == len(state) and "pending" in snapshot
    mixer.mix(thetas * 2, 1)
    assert_same_state(snapshot, state)  # later rounds leave it as it was
    snapshot["pending"][...] = 99.0  # its arrays are its own
    assert not (mixer.state()["pending"] == 99.0).any()
    assert type(mixer.state()) is dict


def test_resume_from_a_snapshot_equals_the_uninterrupted_run():
    team = team_conf(robots=8, graph="ring", consensus_rounds=2)
    net = build_network(team, 2, 0)
    g = np.random.default_rng(2)
    thetas = [g.normal(size=(8, 2)) for _ in range(12)]
    full, saved = Mixer(net, team, 1), None
    out_full = []
    for l in range(12):
        mixed = thetas[l]
        for r in range(2):
            mixed = full.mix(mixed, l, r)
        out_full.append(mixed)
        if l == 5:
            saved = full.snapshot()
    for source in (saved, {k: v.tolist() for k, v in saved.items()}):  # as read, and as a JSON checkpoint holds it
        for resumed in (Mixer(net, team, 1).restore(source), general(net, team, 1).restore(source)):
            for l in range(6, 12):
                mixed = thetas[l]
                for r in range(2):
                    mixed = resumed.mix(mixed, l, r)
                assert np.array_equal(mixed, out_full[l])
            assert_same_state(resumed.state(), full.state())


def test_general_rules_restored_into_a_synchronous_mixer():
    """A state written by the general rules (e.g. an older checkpoint) continues on the synchronous path alike."""
    team = team_conf(robots=7, graph="grid", stale="latest")
    net = build_network(team, 3, 0)
    g = np.random.default_rng(9)
    plain = general(net, team, 0)
    for l in range(4):
        plain.mix(g.normal(size=(7, 3)), l)
    fast, reference = Mixer(net, team, 0).restore(plain.state()), general(net, team, 0).restore(plain.state())
    for l in (4, 5, 5, 2, 8):
        thetas = g.normal(size=(7, 3))
        assert np.array_equal(fast.mix(thetas, l), reference.mix(thetas, l))
        assert_same_mixers(fast, reference)


def test_zero_range_integers_draw_nothing():
    """Mixer._send skips integers(0, 1) (delays with B0 = 0): it must not move the generator."""
    a = np.random.default_rng([1, 7919, 3, 0])
    a.integers(0, 1, size=(40, 40))
    assert np.array_equal(a.random((40, 40)), np.random.default_rng([1, 7919, 3, 0]).random((40, 40)))


@pytest.mark.parametrize(
    "values",
    [
        {},
        {"stale": "latest", "consensus_rounds": 3},
        {"delay": {"max": 2}, "drop": 0.3, "max_gap": 3},
        {"drop": 0.2, "stale": "latest", "consensus_rounds": 2},
        {"switching": {"enabled": True, "up": 0.5, "window": 2}},
    ],
)
def test_mixing_does_not_depend_on_the_thread_count(values, monkeypatch):
    import riskplan.engine.team.kernels

    monkeypatch.setattr(riskplan.engine.team.kernels, "PARALLEL_ENTRIES", 1)  # the parallel drivers, even for 30 robots
    team = team_conf(robots=30, graph="random_geometric", **values)
    net = build_network(team, 2, 0)
    thetas = np.random.default_rng(0).normal(size=(30, 2))
    results = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        previous = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            mixer, mixed, out = Mixer(net, team, 3), thetas, []
            for l in range(6):
                for r in range(team.consensus_rounds):
                    mixed = mixer.mix(mixed, l, r)
                out.append(mixed)
            results.append((out, mixer.state()))
        finally:
            numba.set_num_threads(previous)
    assert all(np.array_equal(a, b) for a, b in zip(results[0][0], results[1][0]))
    assert_same_state(results[0][1], results[1][1])
    monkeypatch.setattr(riskplan.engine.team.kernels, "PARALLEL_ENTRIES", 1 << 62)  # and the serial kernels alike
    mixer, mixed = Mixer(net, team, 3), thetas
    for l in range(6):
        for r in range(team.consensus_rounds):
            mixed = mixer.mix(mixed, l, r)
        assert np.array_equal(mixed, results[0][0][l])
    assert_same_state(mixer.state(), results[0][1])


# ---------------------------------------------------------------------------------------------- tables and rows


def test_policy_tables_do_not_depend_on_the_thread_count():
    world = build_setup(riskplan.compose([])).world
    thetas = np.random.default_rng(0).normal(size=(64, world.sources)) * 10
    results = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        previous = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            results.append(tables(world, thetas))
        finally:
            numba.set_num_threads(previous)
    assert all(np.array_equal(a, b) for a, b in zip(results[0], results[1]))
    few = tables(world, thetas[:5])  # fewer than PARALLEL_POLICIES: the serial loop
    assert np.array_equal(few[0], results[0][0][:5]) and np.array_equal(few[1], results[0][1][:5])
    features = move_features(world)
    cum, score = results[0]
    np.testing.assert_allclose(np.diff(cum, axis=-1, prepend=0.0), probabilities(features, thetas), atol=1e-12)
    np.testing.assert_allclose(score, scores(features, probabilities(features, thetas)), atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 5, 7, 100])
def test_robot_rows_are_the_per_robot_rows(n):
    g = np.random.default_rng(n)
    z = g.normal(size=(n, 50)) * 100
    stats = summary_stats(z, 0.1)
    thetas, grads = g.normal(size=(n, 2)), g.normal(size=(n, 2)) * 1e3
    rows = _robot_rows(4, stats, thetas, grads, 0.05, 1.25, 50, 0.5, 0.2)  # eps, error, samples, seconds, level
    expected = [
        _row(4, i, {k: v[i] for k, v in stats.items()}, thetas[i], grads[i], 0.05, 1.25, 50, 0.5, 0.2) for i in range(n)
    ]
    assert rows == expected
    for got, want in zip(rows, expected):
        assert list(got) == list(want)
        assert [type(v) for v in got.values()] == [type(v) for v in want.values()]
    assert rows[-1]["robot"] == n - 1 and rows[0]["grad_norm"] == float(np.linalg.norm(grads[0]))


@pytest.mark.parametrize("m", [1, 2, 3, 40])
def test_row_norms_are_numpy_norms_bit_for_bit(m):
    from riskplan.run.training import _norms

    g = np.random.default_rng(m)
    vectors = g.normal(size=(2000, m)) * 10.0 ** g.integers(-150, 150, size=(2000, m))
    assert _norms(vectors) == [float(np.linalg.norm(v)) for v in vectors]
    assert _norms(np.array([[3.0, 4.0][:m] + [0.0] * (m - 2)] if m >= 2 else [[-5.0]])) == [5.0]


# ---------------------------------------------------------------------------------------------- whole runs


def test_synchronous_team_resumed_equals_the_uninterrupted_run(tmp_path):
    """Checkpoints written from snapshots (synchronous rounds not yet in the arrays) resume bit for bit."""
    base = [
        "experiment=paper_team",
        "team.robots=6",
        "team.graph=ring",
        "team.consensus_rounds=2",
        "train.samples=200",
        "train.eval_episodes=200",
        "train.paths=2",
        "train.checkpoint_every=2",
        "train.bootstrap=10",
    ]
    full = train(riskplan.compose(base + ["train.iterations=6"]), tmp_path / "full", progress=None)
    train(riskplan.compose(base + ["train.iterations=3"]), tmp_path / "part", progress=None)
    resumed = train(riskplan.compose(base + ["train.iterations=6"]), tmp_path / "part", resume=True, progress=None)
    columns = [c for c in full.metrics.columns if c != "seconds"]
    assert full.metrics[columns].equals(resumed.metrics[columns])
    assert full.eval.equals(resumed.eval)


def test_the_buffers_are_reached_only_through_the_store():
    """The catch-up rule lives in one place: only `_Store` holds the Buffers, and every Mixer method reaches them
    through `_store.current()` (which writes deferred synchronous rounds in first), so none can read stale ones."""
    import ast
    import inspect

    from riskplan.engine.team import mixer as module

    tree = ast.parse(inspect.getsource(module))
    holders = {
        node.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
        for inner in ast.walk(node)
        if isinstance(inner, ast.Attribute) and inner.attr == "_buffers"
    }
    assert holders == {"_Store"}
    mixer_class = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Mixer")
    touched = {n.attr for n in ast.walk(mixer_class) if isinstance(n, ast.Attribute) and n.attr.startswith("_store")}
    assert touched == {"_store"}
    store_uses = {
        n.attr
        for n in ast.walk(mixer_class)
        if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Attribute) and n.value.attr == "_store"
    }
    assert store_uses <= {"current", "snapshot", "replace", "deferred"}
