"""A synchronous team's fast path (riskplan.engine.team.mixer: `_sync_round`, deferred writes through `_Store`): it
must give the numbers of the general rules (the message buffers) call for call, state and diagnostics included,
on known answers, after a snapshot or a restore, on any thread count, and through a checkpointed run."""

from __future__ import annotations

from collections.abc import Mapping

import numba
import numpy as np
import pytest
from support import TINY, team_conf

import riskplan
from riskplan.engine.team.mixer import Mixer, MixerState
from riskplan.engine.team.network import build_network
from riskplan.run.training import train


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


# ---------------------------------------------------------------------------------------------- whole runs


@pytest.mark.slow  # three whole team runs
def test_synchronous_team_resumed_equals_the_uninterrupted_run(tmp_path):
    """Checkpoints written from snapshots (synchronous rounds not yet in the arrays) resume bit for bit."""
    base = [
        "experiment=paper_team",
        *TINY,
        "team.robots=6",
        "team.graph=ring",
        "team.consensus_rounds=2",
        "train.checkpoint_every=2",
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
    assert store_uses <= {"current", "snapshot", "replace", "deferred", "latest"}  # latest: compared, never read
