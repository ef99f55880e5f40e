"""Faulty robots (team.faults): what crashed, stuck and byzantine robots send, seen in the mixed values of a neighbour
with known weights; healthy(); seeded byzantine noise; resume across a checkpoint; the fast path; the checks."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from riskplan.config.faults import faults_of
from riskplan.config.schema import TeamConf
from riskplan.config.typed import typed
from riskplan.config.validate import check_team
from riskplan.engine.team import kernels
from riskplan.engine.team.faulty import BYZANTINE_STREAM
from riskplan.engine.team.mixer import Buffers, Mixer
from riskplan.engine.team.network import build_network
from riskplan.util.errors import BadInput

# Robot 0 mixes 0.5 theta^0 + 0.25 theta^1 + 0.25 s^2, s^2 being what robot 2 sends: exact with whole thetas.
MATRIX = [[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]]


def team(**values) -> TeamConf:
    """Typed, range-checked team settings."""
    conf = typed({"team": values}).team
    check_team(conf)
    return conf


def trio(fault: dict, **values) -> Mixer:
    """Three robots, complete graph, the weights MATRIX, robot 2 faulty; M = 2."""
    conf = team(robots=3, graph="complete", weights="matrix", matrix=MATRIX, faults=[fault], **values)
    return Mixer(build_network(conf, 2, 0), conf, 5)


def thetas_at(iteration: int) -> np.ndarray:
    """Whole-numbered thetas that change every iteration."""
    return np.array([[1.0, -2.0], [3.0, 5.0], [7.0, 11.0]]) + 100.0 * iteration


def sent_by_robot_2(mixed: np.ndarray, thetas: np.ndarray) -> np.ndarray:
    """s^2 recovered from robot 0's mixed value (exact: dyadic weights, whole values)."""
    return (mixed[0] - 0.5 * thetas[0] - 0.25 * thetas[1]) / 0.25


def test_a_crashed_robot_sends_nothing_from_its_iteration_on_and_is_never_forced():
    mixer = trio({"robot": 2, "kind": "crash", "from": 3}, max_gap=2)
    for iteration in range(12):
        thetas = thetas_at(iteration)
        mixed = mixer.mix(thetas, iteration)
        if iteration < 3:
            assert np.array_equal(sent_by_robot_2(mixed, thetas), thetas[2])
            assert mixer.delivered[:, 2].tolist() == [True, True, False]
        else:  # robot 0 hands the silent link's weight to itself: 0.75 theta^0 + 0.25 theta^1
            assert np.array_equal(mixed[0], 0.75 * thetas[0] + 0.25 * thetas[1])
            assert not mixer.delivered[:, 2].any() and not mixer.forced[:, 2].any()
        assert mixer.delivered[2].tolist() == [True, True, False]  # robot 2 still hears the others


def test_under_stale_latest_neighbours_keep_mixing_a_crashed_robots_last_value():
    mixer = trio({"robot": 2, "kind": "crash", "from": 2}, stale="latest")
    last = thetas_at(1)[2]
    for iteration in range(6):
        thetas = thetas_at(iteration)
        mixed = mixer.mix(thetas, iteration)
        expected = thetas[2] if iteration < 2 else last
        assert np.array_equal(sent_by_robot_2(mixed, thetas), expected)


@pytest.mark.parametrize("rounds", [1, 2])
def test_a_stuck_robot_keeps_sending_the_theta_it_had_at_its_iteration(rounds):
    mixer = trio({"robot": 2, "kind": "stuck", "from": 2}, consensus_rounds=rounds)
    for iteration in range(7):
        for r in range(rounds):
            thetas = thetas_at(iteration) + 10.0 * r
            mixed = mixer.mix(thetas, iteration, r)
            expected = thetas[2] if iteration < 2 else thetas_at(2)[2]  # round 0 of iteration 2
            assert np.array_equal(sent_by_robot_2(mixed, thetas), expected), (iteration, r)
    state = mixer.state()
    assert state["stuck_theta"][2].tolist() == thetas_at(2)[2].tolist() and state["stuck_since"].tolist() == [-1, -1, 2]


@pytest.mark.parametrize("value, sent", [([100.0, -50.0], [100.0, -50.0]), ([7.0], [7.0, 7.0]), (-3.0, [-3.0, -3.0])])
def test_a_byzantine_robot_sends_its_fixed_value(value, sent):
    mixer = trio({"robot": 2, "kind": "byzantine", "from": 1, "value": value})
    for iteration in range(4):
        thetas = thetas_at(iteration)
        mixed = mixer.mix(thetas, iteration)
        assert np.array_equal(sent_by_robot_2(mixed, thetas), thetas[2] if iteration < 1 else sent)


def test_byzantine_noise_is_its_theta_plus_the_keyed_draw():
    """s^2 = theta^2 + scale * N(0, 1) from default_rng([seed, BYZANTINE_STREAM, iteration, round, robot]); robot 0
    mixes it in its usual order of sums, so the expected value is computed in that order and compared exactly."""
    mixer = trio({"robot": 2, "kind": "byzantine", "from": 0, "scale": 2.5}, consensus_rounds=2)
    for iteration in range(3):
        for r in range(2):
            thetas = thetas_at(iteration)
            noise = np.random.default_rng([5, BYZANTINE_STREAM, iteration, r, 2]).standard_normal(2)
            sent = thetas[2] + 2.5 * noise
            expected = ((0.0 + 0.5 * thetas[0]) + 0.25 * thetas[1]) + 0.25 * sent
            assert np.array_equal(mixer.mix(thetas, iteration, r)[0], expected)
    assert BYZANTINE_STREAM not in (7907, 7919, 7927)  # apart from the graph's, the drops' and switching's streams


def test_healthy_says_which_robots_have_failed():
    faults = [{"robot": 1, "kind": "crash", "from": 3}, {"robot": 3, "kind": "byzantine", "from": 0, "scale": 1.0}]
    conf = team(robots=4, graph="ring", faults=faults)
    mixer = Mixer(build_network(conf, 2, 0), conf, 0)
    assert mixer.healthy(0).tolist() == [True, True, True, False]
    assert mixer.healthy(2).tolist() == [True, True, True, False]
    assert mixer.healthy(3).tolist() == [True, False, True, False]
    assert mixer.healthy(10**6).dtype == bool
    plain = team(robots=4, graph="ring")
    assert Mixer(build_network(plain, 2, 0), plain, 0).healthy(5).tolist() == [True] * 4


def test_faults_passed_explicitly_override_the_teams():
    conf = team(robots=3, graph="complete", faults=[{"robot": 2, "kind": "crash", "from": 0}])
    net = build_network(conf, 2, 0)
    assert Mixer(net, conf, 0).faults == faults_of(conf)
    assert Mixer(net, conf, 0, faults=()).healthy(5).all()


# -------------------------------------------------------------------------------- reproducibility and resume

MIXED_FAULTS = [
    {"robot": 1, "kind": "stuck", "from": 2},
    {"robot": 4, "kind": "stuck", "from": 6},  # frozen after the checkpoint
    {"robot": 6, "kind": "byzantine", "from": 1, "scale": 3.0},
    {"robot": 8, "kind": "crash", "from": 4},
]


def run(mixer: Mixer, start: int, stop: int, thetas: np.ndarray, rounds: int) -> tuple[list, np.ndarray]:
    out = []
    for iteration in range(start, stop):
        for r in range(rounds):
            thetas = mixer.mix(thetas, iteration, r)
        out.append(thetas)
        thetas = thetas + 0.5  # a stand-in for the gradient step
    return out, thetas


@pytest.mark.filterwarnings("ignore:team.aggregate=wmsr with team.trim=1")  # four faults: not F-local, on purpose
@pytest.mark.parametrize("aggregate", ["mean", "wmsr"])
@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_resume_from_a_checkpoint_is_bit_identical_with_stuck_and_byzantine_faults(aggregate, stale):
    conf = team(
        robots=10,
        graph="random_geometric",
        radius=0.6,
        delay={"max": 2},
        drop=0.3,
        stale=stale,
        consensus_rounds=2,
        faults=MIXED_FAULTS,
        aggregate=aggregate,
        trim=1,
    )
    net = build_network(conf, 3, 7)
    start = np.random.default_rng(0).normal(size=(10, 3))
    full, _ = run(Mixer(net, conf, 9), 0, 10, start, 2)
    first = Mixer(net, conf, 9)
    head, thetas = run(first, 0, 4, start, 2)
    checkpoint = {k: np.array(v).tolist() for k, v in first.snapshot().items()}  # as a JSON checkpoint holds it
    dtypes = {k: v.dtype for k, v in first.state().items()}
    resumed = Mixer(net, conf, 9).restore({k: np.array(v, dtype=dtypes[k]) for k, v in checkpoint.items()})
    tail, _ = run(resumed, 4, 10, thetas, 2)
    assert all(np.array_equal(a, b) for a, b in zip(full, head + tail))
    assert checkpoint["stuck_since"] == [-1, 2, -1, -1, -1, -1, -1, -1, -1, -1]


def test_a_checkpoint_without_the_stuck_state_is_refused():
    conf = team(robots=4, graph="ring", faults=[{"robot": 1, "kind": "stuck", "from": 0}])
    net = build_network(conf, 2, 0)
    mixer = Mixer(net, conf, 0)
    mixer.mix(np.ones((4, 2)), 0)
    state = mixer.state()
    for key in ("stuck_theta", "stuck_since"):
        partial = {k: v for k, v in state.items() if k != key}
        with pytest.raises(ValueError, match=key):
            Mixer(net, conf, 0).restore(partial)
    plain = team(robots=4, graph="ring")
    assert "stuck_theta" not in Mixer(build_network(plain, 2, 0), plain, 0).state()  # default checkpoints unchanged


def test_buffers_round_trip_the_stuck_state():
    buffers = Buffers.empty(3, 2, 2, 1, tracking=False, stuck=True)
    buffers.stuck.stuck_theta[1] = [4.0, -1.5]
    buffers.stuck.stuck_since[1] = 7
    arrays = buffers.as_arrays()
    back = buffers.from_arrays(arrays)
    assert back.stuck.stuck_theta.tolist() == [[0.0, 0.0], [4.0, -1.5], [0.0, 0.0]]
    assert back.stuck.stuck_since.tolist() == [-1, 7, -1] and back.stuck.stuck_since.dtype == np.int64
    assert back.stuck.stuck_theta is not buffers.stuck.stuck_theta
    assert Buffers.empty(3, 2, 2, 1, tracking=False).stuck is None


@pytest.mark.parametrize("aggregate", ["mean", "trimmed_mean"])
def test_byzantine_noise_is_reproducible_and_independent_of_the_thread_count(aggregate, monkeypatch):
    faults = [{"robot": 3, "kind": "byzantine", "from": 0, "scale": 1.0}, {"robot": 17, "kind": "stuck", "from": 2}]
    conf = team(robots=30, graph="random_geometric", drop=0.2, faults=faults, aggregate=aggregate, trim=1)
    net = build_network(conf, 2, 0)
    start = np.random.default_rng(1).normal(size=(30, 2))
    serial, _ = run(Mixer(net, conf, 4), 0, 6, start, 1)
    again, _ = run(Mixer(net, conf, 4), 0, 6, start, 1)
    other_seed, _ = run(Mixer(net, conf, 5), 0, 6, start, 1)
    assert all(np.array_equal(a, b) for a, b in zip(serial, again))
    assert not np.array_equal(serial[-1], other_seed[-1])
    monkeypatch.setattr(kernels, "PARALLEL_ENTRIES", 1)  # the parallel drivers, even for 30 robots
    previous = numba.get_num_threads()
    try:
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(threads)
            parallel, _ = run(Mixer(net, conf, 4), 0, 6, start, 1)
            assert all(np.array_equal(a, b) for a, b in zip(serial, parallel))
    finally:
        numba.set_num_threads(previous)


# ---------------------------------------------------------------------------------------------- the fast path


@pytest.mark.parametrize(
    "values",
    [
        {"faults": [{"robot": 1, "kind": "crash", "from": 5}]},
        {"aggregate": "median"},
        {"aggregate": "trimmed_mean", "trim": 0},
    ],
)
def test_faults_and_resilient_aggregates_take_the_general_rules(values):
    conf = team(robots=4, graph="ring", **values)
    mixer = Mixer(build_network(conf, 2, 0), conf, 0)
    for iteration in range(3):
        mixer.mix(np.arange(8.0).reshape(4, 2), iteration)
        assert mixer._store.deferred is None  # nothing deferred: the synchronous rounds were not used


@pytest.mark.parametrize("stale", ["arrival", "latest"])
@pytest.mark.parametrize("kind", ["crash", "stuck"])
def test_faults_not_yet_started_mix_as_the_fast_path_does(stale, kind):
    """Before `from`, a faulty team mixes by the general rules exactly what a fault-free synchronous team mixes by
    its fast path (deferred rounds), state included."""
    faulty = team(
        robots=6, graph="ring", stale=stale, consensus_rounds=2, faults=[{"robot": 2, "kind": kind, "from": 50}]
    )
    plain = team(robots=6, graph="ring", stale=stale, consensus_rounds=2)
    net = build_network(plain, 3, 0)
    a, b = Mixer(net, faulty, 1), Mixer(net, plain, 1)
    thetas, took_fast_path = np.random.default_rng(2).normal(size=(6, 3)), False
    for iteration in range(8):
        for r in range(2):
            got, expected = a.mix(thetas, iteration, r), b.mix(thetas, iteration, r)
            took_fast_path |= b._store.deferred is not None
            assert np.array_equal(got, expected)
            thetas = got
    assert took_fast_path
    state_a, state_b = a.state(), b.state()
    for key, value in state_b.items():
        assert np.array_equal(state_a[key], value), key


# ---------------------------------------------------------------------------------------------- the checks


def test_gradient_tracking_refuses_faults_with_one_line_naming_the_key():
    with pytest.raises(BadInput) as caught:
        team(robots=3, order="gradient_tracking", faults=[{"robot": 1, "kind": "crash", "from": 2}])
    assert caught.value.args and "team.faults" in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(BadInput, match=r"team\.aggregate"):
        team(robots=3, order="gradient_tracking", aggregate="median")
    for order in ("combine_then_adapt", "adapt_then_combine"):
        team(robots=3, order=order, aggregate="wmsr", trim=1, faults=[{"robot": 1, "kind": "crash", "from": 2}])


def test_the_mixer_refuses_tracking_with_faults_even_unvalidated():
    conf = typed({"team": {"robots": 3, "order": "gradient_tracking"}}).team
    net = build_network(conf, 2, 0)
    faults = faults_of(team(robots=3, faults=[{"robot": 1, "kind": "crash", "from": 2}]))
    with pytest.raises(BadInput, match=r"team\.faults"):
        Mixer(net, conf, 0, faults=faults)


def test_a_byzantine_value_of_the_wrong_length_is_bad_input():
    conf = team(robots=3, graph="complete", faults=[{"robot": 2, "kind": "byzantine", "from": 0, "value": [1, 2, 3]}])
    with pytest.raises(BadInput, match=r"team\.faults\.0\.value"):
        Mixer(build_network(conf, 2, 0), conf, 0)
