"""Resilient aggregation (team.aggregate=trimmed_mean, median, wmsr; team.trim=F): hand-computed rows, the per-row
rule against the team kernel bit for bit, the Mixer's received values, and the resilience property on a complete
graph with a byzantine robot."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from riskplan.config.faults import faults_of
from riskplan.config.schema import TeamConf
from riskplan.config.typed import typed
from riskplan.config.validate import check_team
from riskplan.engine.team import kernels
from riskplan.engine.team.convergence import consensus_error
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import build_network
from riskplan.engine.team.resilience import aggregate_row, aggregate_team, row_inputs, rule_f

RULES = ["trimmed_mean", "median", "wmsr"]


def team(**values) -> TeamConf:
    """Typed, range-checked team settings."""
    conf = typed({"team": values}).team
    check_team(conf)
    return conf


def row(rule, own, received, weights, own_weight, trim) -> np.ndarray:
    """aggregate_row on one coordinate (M = 1) given as plain lists."""
    received = np.array(received, dtype=float).reshape(-1, 1)
    return aggregate_row(rule, [own], received, np.array(weights, dtype=float).reshape(-1, 1), [own_weight], trim)


# ----------------------------------------------------------------------------------------- hand-computed rows
# Dyadic weights and whole values: every sum below is exact, so the known answers are compared with ==.


def test_trimmed_mean_drops_the_f_largest_and_smallest_and_hands_their_weight_to_the_robot():
    # received 1 (j0), 9 (j1), 4 (j2), 7 (j3); F = 1 drops 1 and 9: own weight 0.125 + 0.125 + 0.25 = 0.5
    out = row("trimmed_mean", 5.0, [1, 9, 4, 7], [0.125, 0.25, 0.375, 0.125], 0.125, 1)
    assert out[0] == 0.5 * 5 + 0.375 * 4 + 0.125 * 7 == 4.875
    # F = 0 drops nothing: the plain weighted mix
    out = row("trimmed_mean", 5.0, [1, 9, 4, 7], [0.125, 0.25, 0.375, 0.125], 0.125, 0)
    assert out[0] == 0.125 * 5 + 0.125 * 1 + 0.25 * 9 + 0.375 * 4 + 0.125 * 7


def test_trimmed_mean_ties_are_broken_by_sender_index():
    # 3 (j0) and 3 (j1) tie: j0 counts as the smaller, so F = 1 drops j0 and 8 (j2) and keeps j1's weight 0.125
    out = row("trimmed_mean", 6.0, [3, 3, 8], [0.25, 0.125, 0.25], 0.375, 1)
    assert out[0] == (0.375 + 0.25 + 0.25) * 6 + 0.125 * 3 == 5.625  # keeping j0 instead would give 5.25


@pytest.mark.parametrize("received", [[1.0, 100.0, 3.0], [1.0, 100.0, 3.0, -50.0], []])
def test_trimmed_mean_with_2f_or_fewer_values_keeps_the_robots_own(received):
    weights = [0.125] * len(received)
    own_weight = 1.0 - 0.125 * len(received)
    assert row("trimmed_mean", 5.0, received, weights, own_weight, 2)[0] == 5.0


def test_wmsr_drops_only_values_strictly_above_or_below_its_own():
    # own 5; below: 1 (j0), 2 (j1) -> drop 1; equal: 5 (j2) kept; above: 8 (j3), 9 (j4), 9 (j5) -> drop the
    # largest, the tie going to the higher index j5
    weights = [0.125, 0.125, 0.125, 0.125, 0.25, 0.125]
    out = row("wmsr", 5.0, [1, 2, 5, 8, 9, 9], weights, 0.125, 1)
    assert out[0] == (0.125 + 0.125 + 0.125) * 5 + 0.125 * 2 + 0.125 * 5 + 0.125 * 8 + 0.25 * 9 == 6.0
    # (dropping j4, the 9 of weight 0.25, would give 5.5)


def test_wmsr_with_fewer_than_f_on_a_side_drops_all_of_that_side():
    # F = 2, own 5: above only 6 (j0) -> dropped; below 1, 2, 3 -> the two smallest dropped, 3 kept
    out = row("wmsr", 5.0, [6, 1, 2, 3], [0.25, 0.125, 0.125, 0.25], 0.25, 2)
    assert out[0] == (0.25 + 0.25 + 0.125 + 0.125) * 5 + 0.25 * 3 == 4.5
    # F = 2, two on each side: all dropped, the robot keeps its own value
    assert row("wmsr", 5.0, [4, 6, 7, 1], [0.125] * 4, 0.5, 2)[0] == 5.0


def test_wmsr_and_trimmed_mean_differ_where_all_values_are_on_one_side():
    # own 5, received 6, 7, 8 (all above), F = 1: trimmed_mean drops 6 and 8; wmsr drops only 8
    args = ([6, 7, 8], [0.25, 0.25, 0.25], 0.25, 1)
    assert row("trimmed_mean", 5.0, *args)[0] == 0.75 * 5 + 0.25 * 7 == 5.5
    assert row("wmsr", 5.0, *args)[0] == 0.5 * 5 + 0.25 * 6 + 0.25 * 7 == 5.75


def test_median_of_own_and_received_values_unweighted():
    assert row("median", 5.0, [1, 9, 4], [0.125, 0.5, 0.125], 0.25, 1)[0] == 4.5  # (4 + 5) / 2
    assert row("median", 5.0, [1, 9], [0.125, 0.5], 0.375, 1)[0] == 5.0
    assert row("median", 5.0, [1, 2, 3, 100], [0.125] * 4, 0.5, 0)[0] == 3.0
    assert row("median", 5.0, [], [], 1.0, 1)[0] == 5.0


def test_median_with_fewer_than_2f_values_keeps_the_robots_own():
    """Too few received values to outvote F faulty ones: its own value, exactly (the even pool of its own and one
    byzantine value would average halfway to it)."""
    assert row("median", 5.0, [1e6], [0.5], 0.5, 1)[0] == 5.0  # was 0.5 * 5 + 0.5 * 1e6
    assert row("median", 5.0, [1e6, 1e6, 6.0], [0.25] * 3, 0.25, 2)[0] == 5.0  # was 0.5 * 6 + 0.5 * 1e6
    # 2F values and more: the median of the pool, within the healthy values
    assert row("median", 5.0, [1e6, 6.0], [0.25] * 2, 0.5, 1)[0] == 6.0
    assert row("median", 5.0, [1e6, 1e6, 6.0, 7.0], [0.125] * 4, 0.5, 2)[0] == 7.0
    assert row("median", 5.0, [1e6, 6.0, 8.0], [0.25] * 3, 0.25, 1)[0] == 0.5 * 6 + 0.5 * 8  # even pool: 0.5a + 0.5b
    assert row("median", 5.0, [1e6], [0.5], 0.5, 0)[0] == 0.5 * 5 + 0.5 * 1e6  # F = 0: the plain median


def test_median_f_comes_from_the_faults_not_from_team_trim():
    adjacency = ~np.eye(3, dtype=bool)
    byzantine = faults_of(team(robots=3, faults=[{"robot": 2, "kind": "byzantine", "from": 0, "value": 1e6}]))
    assert rule_f("median", 0, adjacency, byzantine) == 1
    assert rule_f("median", 3, adjacency, ()) == 0
    assert rule_f("trimmed_mean", 2, adjacency, byzantine) == 2 and rule_f("wmsr", 0, adjacency, byzantine) == 0
    assert rule_f("mean", 2, adjacency, byzantine) == 0


def test_a_median_robot_that_hears_only_the_byzantine_one_keeps_its_value():
    """3 robots, complete graph, robot 2 byzantine (1e6, F = 1): robot 0's link from robot 1 delivered nothing, so it
    hears one value, fewer than 2F: it keeps its value exactly; robot 1 hears both: the median of 2, 4 and 1e6."""
    weights = np.full((3, 3, 1), 1.0 / 3.0)
    adjacency = ~np.eye(3, dtype=bool)
    use = adjacency.copy()
    use[0, 1] = False
    own = np.array([[4.0], [2.0], [1e6]])
    neighbour = np.broadcast_to(own[None, :, :], (3, 3, 1)).copy()  # every link carries its sender's value
    faults = faults_of(team(robots=3, faults=[{"robot": 2, "kind": "byzantine", "from": 0, "value": 1e6}]))
    out = aggregate_team("median", weights, adjacency, use, neighbour, own, rule_f("median", 0, adjacency, faults))
    assert out[0, 0] == 4.0 and out[1, 0] == 4.0  # robot 0 was 0.5 * 4 + 0.5 * 1e6


def test_rows_are_per_coordinate():
    # M = 2: coordinate 0 as in the trimmed-mean example above, coordinate 1 with its order reversed
    received = np.array([[1, 7], [9, 4], [4, 9], [7, 1]], dtype=float)
    weights = np.array([[0.125, 0.125], [0.25, 0.375], [0.375, 0.25], [0.125, 0.125]])
    out = aggregate_row("trimmed_mean", [5.0, 5.0], received, weights, [0.125, 0.125], 1)
    assert out.tolist() == [4.875, 4.875]
    out = aggregate_row("median", [5.0, 0.0], received, weights, [0.125, 0.125], 1)
    assert out.tolist() == [5.0, 4.0]  # the medians of 5, 1, 9, 4, 7 and of 0, 7, 4, 9, 1


def test_values_of_links_not_in_use_are_not_counted_and_their_weight_goes_to_the_robot():
    """Robot 0 hears 1, 2, 3 (weights 0.25 each, own 0.25); the link from 3 delivered nothing this round and holds
    a stale 1e300: its weight joins robot 0's own before the rule, and its value is never read."""
    weights = np.full((4, 4, 1), 0.25)
    adjacency = ~np.eye(4, dtype=bool)
    use = adjacency.copy()
    use[0, 3] = False
    neighbour = np.zeros((4, 4, 1))
    neighbour[0, 1, 0], neighbour[0, 2, 0], neighbour[0, 3, 0] = 2.0, 6.0, 1e300
    own = np.array([[4.0], [2.0], [6.0], [0.0]])
    _, received, _, own_weight = row_inputs(weights, adjacency, use, neighbour, own, 0)
    assert received.tolist() == [[2.0], [6.0]] and own_weight.tolist() == [0.5]
    # wmsr, F = 1: 2 below (dropped), 6 above (dropped): own value; trimmed_mean F = 1 with 2 values: own value
    for rule in ("wmsr", "trimmed_mean"):
        assert aggregate_team(rule, weights, adjacency, use, neighbour, own, 1)[0, 0] == 4.0
    # F = 0: 0.5 * 4 + 0.25 * 2 + 0.25 * 6; median of 4, 2, 6
    assert aggregate_team("trimmed_mean", weights, adjacency, use, neighbour, own, 0)[0, 0] == 4.0
    assert aggregate_team("median", weights, adjacency, use, neighbour, own, 0)[0, 0] == 4.0
    neighbour[0, 2, 0] = 10.0
    assert aggregate_team("trimmed_mean", weights, adjacency, use, neighbour, own, 0)[0, 0] == 5.0
    assert aggregate_team("median", weights, adjacency, use, neighbour, own, 0)[0, 0] == 4.0


# ------------------------------------------------------------------------------------- row rule == team kernel


def random_team_arrays(g: np.random.Generator, n: int, m: int, ties: bool):
    adjacency = g.random((n, n)) < 0.7
    np.fill_diagonal(adjacency, False)
    raw = g.random((n, n, m)) * adjacency[:, :, None] + np.eye(n)[:, :, None] * (0.1 + g.random((n, 1, m)))
    weights = raw / raw.sum(axis=1, keepdims=True)
    use = adjacency & (g.random((n, n)) < 0.8)
    values = g.normal(size=(n, n, m)) * 3
    own = g.normal(size=(n, m)) * 3
    if ties:
        values, own = np.round(values), np.round(own)
    neighbour = np.where(use[:, :, None], values, np.where(g.random((n, n, 1)) < 0.5, np.inf, np.nan))
    return weights, adjacency, use, neighbour, own


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("trim", [0, 1, 2, 3])
@pytest.mark.parametrize("ties", [False, True])
def test_the_team_kernel_is_the_row_rule_bit_for_bit(rule, trim, ties):
    g = np.random.default_rng(trim * 10 + ties)
    for n, m in [(2, 1), (5, 1), (7, 3), (9, 2), (12, 4)]:
        weights, adjacency, use, neighbour, own = random_team_arrays(g, n, m, ties)
        team_out = aggregate_team(rule, weights, adjacency, use, neighbour, own, trim)
        for i in range(n):
            expected = aggregate_row(rule, *row_inputs(weights, adjacency, use, neighbour, own, i), trim)
            assert np.array_equal(team_out[i], expected), (n, m, i)


@pytest.mark.parametrize("rule", RULES)
def test_the_parallel_driver_agrees_with_the_serial_one_for_any_thread_count(rule, monkeypatch):
    g = np.random.default_rng(5)
    weights, adjacency, use, neighbour, own = random_team_arrays(g, 40, 3, ties=True)
    serial = aggregate_team(rule, weights, adjacency, use, neighbour, own, 2)
    monkeypatch.setattr(kernels, "PARALLEL_ENTRIES", 1)
    previous = numba.get_num_threads()
    try:
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(threads)
            assert np.array_equal(aggregate_team(rule, weights, adjacency, use, neighbour, own, 2), serial)
    finally:
        numba.set_num_threads(previous)


# ------------------------------------------------------------------------------------------- through the Mixer


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_the_mixer_aggregates_exactly_the_values_its_links_would_mix(rule, stale):
    """With delays and drops: the row rule applied to the links the mean rule would mix this round (the arrived
    ones, or every link holding a value under stale=latest) gives the Mixer's output, every round."""
    conf = team(robots=6, graph="complete", delay={"max": 2}, drop=0.4, stale=stale, aggregate=rule, trim=1)
    net = build_network(conf, 2, 0)
    mixer = Mixer(net, conf, 11)
    g = np.random.default_rng(3)
    history = {}  # iteration -> thetas sent (the link's value is the sender's theta of its send iteration)
    for iteration in range(12):
        thetas = np.round(g.normal(size=(6, 2)) * 4)
        history[iteration] = thetas
        mixed = mixer.mix(thetas, iteration)
        sent = mixer.used_sent
        for i in range(6):
            links = [j for j in range(6) if j != i and sent[i, j] >= 0]
            received = np.array([history[sent[i, j]][j] for j in links]).reshape(-1, 2)
            weights = np.array([net.weights[i, j] for j in links]).reshape(-1, 2)
            idle = np.zeros(2)
            for j in range(6):
                if j != i and sent[i, j] < 0:
                    idle += net.weights[i, j]  # the silent links' weights, summed in order of j, then the robot's
            own_weight = net.weights[i, i] + idle
            expected = aggregate_row(rule, thetas[i], received, weights, own_weight, mixer.trim)
            assert np.array_equal(mixed[i], expected), (iteration, i)


def test_trimmed_mean_and_wmsr_with_f_0_are_the_mean_up_to_rounding():
    for rule in ("trimmed_mean", "wmsr"):
        conf = team(robots=5, graph="ring", aggregate=rule, trim=0, delay={"max": 1}, drop=0.2)
        plain = team(robots=5, graph="ring", delay={"max": 1}, drop=0.2)
        net = build_network(conf, 3, 0)
        a, b = Mixer(net, conf, 2), Mixer(net, plain, 2)
        thetas = np.random.default_rng(0).normal(size=(5, 3))
        for iteration in range(10):
            assert np.allclose(a.mix(thetas, iteration), b.mix(thetas, iteration), rtol=0, atol=1e-14)


# --------------------------------------------------------------------------------- the resilience property


def healthy_spread(robots: int) -> np.ndarray:
    """Six healthy robots' values, per coordinate apart (coordinate 1 runs the other way)."""
    base = np.arange(robots, dtype=float)
    return np.column_stack([base, 10.0 - 2.0 * base])


@pytest.mark.parametrize("rule", RULES)
def test_resilient_aggregates_keep_healthy_robots_within_the_healthy_range_and_reach_consensus(rule):
    """A complete graph of 7, robot 6 byzantine from the start, sending 1e9 on every parameter: with F = 1 every
    healthy robot's new value lies within the [min, max] of the healthy values each round, per coordinate, and the
    healthy robots agree."""
    faults = [{"robot": 6, "kind": "byzantine", "from": 0, "value": 1e9}]
    conf = team(robots=7, graph="complete", aggregate=rule, trim=1, faults=faults)
    mixer = Mixer(build_network(conf, 2, 0), conf, 0)
    thetas = np.vstack([healthy_spread(6), [[-3.0, 4.0]]])
    for iteration in range(40):
        before = thetas[:6]
        thetas = mixer.mix(thetas, iteration)
        assert (thetas[:6] >= before.min(axis=0)).all() and (thetas[:6] <= before.max(axis=0)).all(), iteration
    assert consensus_error(thetas[:6]) < 1e-9
    assert (np.abs(thetas[:6]) < 10).all()


def test_the_mean_is_dragged_towards_the_byzantine_value():
    """The same team with team.aggregate=mean: after one round every healthy robot is above the healthy maximum,
    and it keeps climbing towards 1e9 (by a seventh of the gap each round, on this complete graph)."""
    faults = [{"robot": 6, "kind": "byzantine", "from": 0, "value": 1e9}]
    conf = team(robots=7, graph="complete", faults=faults)
    mixer = Mixer(build_network(conf, 2, 0), conf, 0)
    thetas = np.vstack([healthy_spread(6), [[-3.0, 4.0]]])
    highest = thetas[:6].max(axis=0)
    for iteration in range(5):
        previous = thetas[:6].copy()
        thetas = mixer.mix(thetas, iteration)
        assert (thetas[:6] > highest).all() and (thetas[:6] > previous).all()
    assert (thetas[:6] > 1e9 * (1 - (6 / 7) ** 5) - 100).all()


def test_mean_is_not_a_resilient_rule():
    with pytest.raises(ValueError, match="mix_used"):
        aggregate_row("mean", [1.0], [[2.0]], [[0.5]], [0.5], 0)
