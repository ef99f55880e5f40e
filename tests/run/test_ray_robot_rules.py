"""team.backend=ray, one robot's row (`riskplan.run.ray_robot.RobotCore`, no Ray needed) in the rounds where it
departs from a synchronous schedule: stale=latest across consensus rounds (the Mixer's stamp l R + r), and a median
robot that hears too few values to outvote its faulty neighbours. Known answers, driven by hand."""

from __future__ import annotations

import numpy as np
import pytest

import riskplan
from riskplan.run.build import build_setup
from riskplan.run.ray_robot import RobotCore, Step

SMALL = ["train.samples=400", "train.eval_episodes=1000", "train.bootstrap=40", "train.paths=1"]


def cores_of(*overrides: str) -> list[RobotCore]:
    """The robots of a 3-robot complete paper_team on the Ray backend, each at its initial state."""
    conf = riskplan.compose(["experiment=paper_team", "team.backend=ray", "team.graph=complete", *SMALL, *overrides])
    setup = build_setup(conf)
    return [RobotCore(setup, i) for i in range(setup.robots)]


def step_of(l: int, m: int) -> Step:
    """A Step with a zero gradient (the consensus part does not look at the episodes)."""
    stats = {"mean": 0.0, "cvar": 0.0, "value_at_risk": 0.0, "std": 0.0, "objective": 0.0}
    return Step(l, np.zeros(1), np.zeros(m), 0.1, stats, 1)


def test_stale_latest_mixes_each_links_newest_message_of_any_round():
    """2 rounds, stale=latest: iteration 0 is delivered in full; in iteration 1 robot 0 gets its neighbours' round-0
    messages only. In round 1 each link's newest message is then round 0 of iteration 1 (stamp 1 R + 0 = 2), not
    round 1 of iteration 0 (stamp 1), as the simulated Mixer's latest_stamp decides."""
    cores = cores_of("team.consensus_rounds=2", "team.stale=latest", "team.staleness=1")
    m = cores[0].m
    values = [np.array([10.0, 20.0]), np.array([30.0, -40.0]), np.array([50.0, 60.0])]
    for i, core in enumerate(cores):  # iteration 0: every round delivered to everyone
        core.s["theta"] = values[i].copy()
    for r in range(2):
        messages = [core.send(0, r, values[i], None) for i, core in enumerate(cores)]
        for core in cores:
            for message in messages:
                core.receive(message)
        values = [core.mix(0, r, values[i], None)[0] for i, core in enumerate(cores)]
    begun = [core.begin(step_of(1, m))[0] for core in cores]
    round0 = [core.send(1, 0, begun[i], None) for i, core in enumerate(cores)]
    for message in round0:
        cores[0].receive(message)
    mixed, _, _ = cores[0].mix(1, 0, begun[0], None)
    late = [core.send(1, 1, begun[i], None) for i, core in enumerate(cores)]  # round 1: robot 0 gets none of it
    assert all(message.iteration == 1 and message.round == 1 for message in late)
    assert cores[0].waiting_for(1, 1) == []  # round-1 messages of iteration 0 are within team.staleness=1
    out, _, staleness = cores[0].mix(1, 1, mixed, None)
    weights = cores[0].in_weights
    expected = cores[0].own_weight * mixed + weights[0] * round0[1].theta + weights[1] * round0[2].theta
    np.testing.assert_allclose(out, expected, rtol=1e-15, atol=0)
    assert staleness == 0.0  # iteration 1's messages (it mixed iteration 0's round-1 ones before: staleness 1)


@pytest.mark.filterwarnings("ignore:team.aggregate=median with F=1")  # 3 robots are not 3-robust: known
def test_a_median_robot_that_hears_only_the_byzantine_one_keeps_its_value():
    """Robot 2 byzantine (1e6), so median's F = 1. In iteration 1 robot 0 hears robot 2 only (robot 1's message is
    late; its iteration-0 one, already mixed, is within team.staleness): one value, fewer than 2F, so it keeps its
    own exactly. It averaged halfway to 1e6 before."""
    cores = cores_of(
        "team.aggregate=median", "team.staleness=1", "team.faults=[{robot: 2, kind: byzantine, from: 0, value: 1e6}]"
    )
    m = cores[0].m
    assert [core.trim for core in cores] == [1, 1, 1]
    values = [core.begin(step_of(0, m))[0] for core in cores]
    messages = [core.send(0, 0, values[i], None) for i, core in enumerate(cores)]
    for core in cores:
        for message in messages:
            core.receive(message)
    assert np.array_equal(values[0], values[1])  # theta0: the median of theta0, theta0 and 1e6 is theta0
    assert np.array_equal(cores[0].mix(0, 0, values[0], None)[0], values[0])
    own = np.array([3.0, -7.0])
    byzantine = cores[2].send(1, 0, np.zeros(m), None)
    assert byzantine.theta.tolist() == [1e6, 1e6]
    cores[0].receive(byzantine)
    assert cores[0].waiting_for(1, 0) == []
    out, _, _ = cores[0].mix(1, 0, own, None)
    assert out.tolist() == own.tolist()
