"""r-robustness (LeBlanc et al., IEEE JSAC 2013) by enumeration: known answers, the definition by brute force, the
unknown answer beyond the limit, and the resilience condition as `riskplan check` prints it and build_network warns."""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np
import pytest

from riskplan.config.faults import faults_of
from riskplan.config.schema import TeamConf
from riskplan.config.typed import typed
from riskplan.config.validate import check_team
from riskplan.engine.team.describe import describe
from riskplan.engine.team.graphs import named_adjacency
from riskplan.engine.team.network import build_network
from riskplan.engine.team.robustness import LIMIT, condition, is_robust, levels, robustness


def team(**values) -> TeamConf:
    """Typed, range-checked team settings."""
    conf = typed({"team": values}).team
    check_team(conf)
    return conf


def brute_force_robust(adjacency: np.ndarray, r: int) -> bool:
    """The definition: every pair of nonempty disjoint sets has one with a node of >= r in-neighbours outside it."""
    n = len(adjacency)

    def reachable(s: set[int]) -> bool:
        return any(sum(adjacency[v, j] for j in range(n) if j not in s) >= r for v in s)

    for labels in itertools.product((0, 1, 2), repeat=n):  # 0: neither set, 1: S1, 2: S2
        s1 = {v for v in range(n) if labels[v] == 1}
        s2 = {v for v in range(n) if labels[v] == 2}
        if s1 and s2 and not reachable(s1) and not reachable(s2):
            return False
    return True


@pytest.mark.parametrize("n", range(2, 9))
def test_the_complete_graph_is_exactly_half_n_robust(n):
    complete = named_adjacency("complete", n, directed=False)
    r = math.ceil(n / 2)
    assert robustness(complete) == r
    assert is_robust(complete, r) is True and is_robust(complete, r + 1) is False


@pytest.mark.parametrize("graph", ["ring", "line", "star"])
@pytest.mark.parametrize("n", range(4, 10))
def test_ring_line_and_star_are_1_robust_and_not_2_robust(graph, n):
    adjacency = named_adjacency(graph, n, directed=False)
    assert is_robust(adjacency, 1) is True and is_robust(adjacency, 2) is False
    assert robustness(adjacency) == 1


@pytest.mark.parametrize("n", range(2, 6))
def test_no_links_is_not_even_1_robust(n):
    empty = np.zeros((n, n), dtype=bool)
    assert robustness(empty) == 0
    assert is_robust(empty, 1) is False and is_robust(empty, 0) is True
    assert levels(empty).tolist() == [0] * (1 << n)


def test_a_directed_ring_and_a_single_robot():
    directed = named_adjacency("ring", 5, directed=True)  # strongly connected: every set hears from outside
    assert robustness(directed) == 1
    assert is_robust(np.zeros((1, 1), dtype=bool), 3) is True  # no pair of sets: vacuously
    with pytest.raises(ValueError):
        robustness(np.zeros((1, 1), dtype=bool))


def test_levels_known_values():
    # line 0 - 1 - 2, sets as bits: {0}: 0 hears 1 -> 1; {1}: 1 hears 0 and 2 -> 2; {0, 1}: 1 hears 2 -> 1;
    # {2}: 1; {0, 2}: 1; {1, 2}: 1 hears 0 -> 1; everything: 0
    line = named_adjacency("line", 3, directed=False)
    assert levels(line).tolist() == [0, 1, 2, 1, 1, 1, 1, 0]


def test_enumeration_is_the_definition_on_random_digraphs():
    g = np.random.default_rng(0)
    for _ in range(60):
        n = int(g.integers(2, 7))
        adjacency = g.random((n, n)) < g.uniform(0.2, 0.9)
        np.fill_diagonal(adjacency, False)
        largest = robustness(adjacency)
        for r in range(0, n + 1):
            assert (r <= largest) == brute_force_robust(adjacency, r), (adjacency.astype(int).tolist(), r)


def test_beyond_the_limit_the_answer_is_unknown_unless_a_robot_hears_too_few():
    n = LIMIT + 1
    complete = named_adjacency("complete", n, directed=False)
    assert robustness(complete) is None
    assert is_robust(complete, 3) is None
    ring = named_adjacency("ring", n, directed=False)
    assert is_robust(ring, 3) is False  # every robot hears 2 < 3 others
    assert is_robust(ring, 1) is True  # strongly connected
    assert robustness(named_adjacency("complete", LIMIT, directed=False)) == LIMIT // 2  # the limit itself: exact


# ---------------------------------------------------------------------------------------------- the condition


def test_the_condition_on_a_complete_graph_holds_and_says_why():
    conf = team(
        robots=7,
        graph="complete",
        aggregate="wmsr",
        trim=1,
        faults=[{"robot": 6, "kind": "byzantine", "from": 0, "value": 1e6}],
    )
    result = condition(build_network(conf, 2, 0).adjacency, conf.aggregate, conf.trim, faults_of(conf))
    assert result.met is True and result.warning is None
    text = "\n".join(result.lines)
    assert "needs 3-robust; the graph is 4-robust, not 5-robust" in text and "holds" in text
    assert "sufficient for W-MSR" in text and "LeBlanc" in text and "IEEE JSAC" in text
    assert "robot 6 byzantine from iteration 0 (value 1e+06)" in text


def test_a_graph_that_is_not_robust_enough_warns_once_when_the_network_is_built():
    conf = team(robots=6, graph="ring", aggregate="trimmed_mean", trim=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        network = build_network(conf, 2, 0)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "\n" not in message and "not 3-robust" in message and "team.trim=1" in message
    assert "FAILS" in describe(network, conf)


def test_too_many_faulty_neighbours_break_the_f_local_condition():
    faults = [{"robot": 0, "kind": "crash", "from": 0}, {"robot": 1, "kind": "stuck", "from": 0}]
    conf = team(robots=7, graph="complete", aggregate="trimmed_mean", trim=1, faults=faults)
    with pytest.warns(UserWarning, match="a healthy robot has 2 faulty in-neighbours"):
        network = build_network(conf, 2, 0)
    text = describe(network, conf)
    assert "F-local faults: at most 2 faulty in-neighbours per healthy robot (F = 1): FAILS" in text


def test_no_warning_for_a_robust_graph_or_for_the_mean():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_network(team(robots=8, graph="complete", aggregate="trimmed_mean", trim=1), 2, 0)
        mean = team(robots=4, graph="ring", faults=[{"robot": 1, "kind": "byzantine", "from": 0, "value": 9.0}])
        network = build_network(mean, 2, 0)
        build_network(team(robots=4, graph="ring"), 2, 0)
    assert "team.aggregate=mean has no resilience" in describe(network, mean)


def test_describe_prints_the_condition_only_for_faults_or_a_resilient_aggregate():
    plain = team(robots=4, graph="ring")
    assert "resilience" not in describe(build_network(plain, 2, 0), plain)
    resilient = team(robots=5, graph="complete", aggregate="wmsr", trim=1)
    assert "(2F+1)-robustness: needs 3-robust; the graph is 3-robust, not 4-robust" in describe(
        build_network(resilient, 2, 0), resilient
    )


def test_beyond_the_limit_check_says_unknown():
    n = LIMIT + 5
    conf = team(robots=n, graph="complete", aggregate="wmsr", trim=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # unknown is not a failure: no warning
        network = build_network(conf, 2, 0)
    text = describe(network, conf)
    assert f"not computed above the enumeration limit of {LIMIT} robots (N = {n}): unknown" in text


@pytest.mark.parametrize("aggregate,trim", [("trimmed_mean", 1), ("wmsr", 1), ("median", 0)])
@pytest.mark.parametrize(
    "lossy,named",
    [
        ({"drop": 0.5}, "team.drop=0.5"),
        ({"delay": {"max": 2}}, "team.delay.max=2"),
        ({"switching": {"enabled": True}}, "team.switching"),
    ],
)
def test_with_drops_delays_or_switching_the_verdict_is_of_the_full_graph_and_a_round_may_hear_fewer(
    aggregate, trim, lossy, named
):
    """`riskplan check` judges the static graph; a round under drops, delays or switching hears only some links,
    so the verdict says so, and what still holds (the rule's safety) and what does not (consensus)."""
    faults = [{"robot": 2, "kind": "byzantine", "from": 0, "scale": 100.0}]
    conf = team(robots=5, graph="complete", aggregate=aggregate, trim=trim, faults=faults, **lossy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # median with the default team.trim=0 says nothing; fine either way
        text = describe(build_network(conf, 2, 0), conf)
    assert "the graph is 3-robust, not 4-robust (exact: enumeration, N = 5 <= 20): holds on the full graph" in text
    assert "(F = 1): holds on the full graph" in text
    warning = next(line for line in text.splitlines() if line.startswith("  warning: "))
    assert f"with {named} a round hears only the links that deliver in it" in warning
    assert "fewer than 2F+1 values" in warning and "consensus is not guaranteed" in warning
    assert "safety still holds" in warning
    safe = {"trimmed_mean": "2F or fewer values keeps its own", "wmsr": "however few", "median": "fewer than 2F values"}
    assert safe[aggregate] in warning
    reliable = team(robots=5, graph="complete", aggregate=aggregate, trim=trim, faults=faults)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        text = describe(build_network(reliable, 2, 0), reliable)
    assert "warning:" not in text and "on the full graph" not in text and ": holds" in text
