"""The engine's training loop (riskplan.engine.loop): a run alone is the engine's step iterated, and a run inside
any batch is bit for bit the same run alone, whatever else the batch holds (every registered measure, other betas,
baselines, step sizes, theta_0, seeds, teams with their own risk nodes, delays and gradient tracking); a run whose
numbers stop being finite leaves the batch alone; the recorder sees every iteration once, in order."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support import setup_of

from riskplan.engine.loop import make_train
from riskplan.engine.step import NumericalTrouble, initial_state, step
from riskplan.risk import lookup, names


class Memory:
    """A recorder that keeps everything in memory: each run's (iteration, thetas, objective) in order."""

    def __init__(self, runs: int, isolate: bool = True):
        self.seen: list[list[tuple]] = [[] for _ in range(runs)]
        self.errors: dict[int, Exception] = {}
        self.rounds, self.isolate = 0, isolate

    def iteration(self, run, state, statistics, seconds):
        assert seconds >= 0 and state.iteration == statistics.iteration + 1
        self.seen[run].append((statistics.iteration, statistics.thetas.copy(), statistics.estimates.stats.copy()))

    def failed(self, run, error):
        if not self.isolate:
            raise error
        self.errors[run] = error

    def round_done(self, runs, states):
        self.rounds += 1
        return []


def registered(name: str) -> list[str]:
    """Overrides that pick a registered measure with its parameters mid-range (a package's go under risk.params)."""
    measure = lookup(name)
    values = {p.name: (p.low if math.isfinite(p.low) else 0.0) + 0.5 for p in measure.parameters}
    if measure.built_in:
        return [f"risk.measure={name}", *(f"risk.{k}={min(v, 0.9)}" for k, v in values.items())]
    return [f"risk.measure={name}", *(f"+risk.params.{k}={v}" for k, v in values.items())]


# Runs of one world and sample schedule that differ in everything else.
OTHERS = {
    "beta": ["seed=2", "risk.beta=0.3", "train.theta0=[10,30]"],
    "neutral_no_baseline": ["seed=5", "risk=neutral", "train.baseline=false", "train.step_size.initial=0.05"],
    "soft": ["seed=6", "risk.schedule.kind=linear"],
    "team": ["seed=3", "experiment=paper_team", "team.delay.max=1", "team.drop=0.1"],
    "tracking": ["seed=4", "experiment=paper_team", "team.order=gradient_tracking"],
    "team_risk": ["seed=7", "experiment=paper_team", "team.risk=[{measure: neutral},{measure: cvar, beta: 0.2},{}]"],
}


def train_alone(setup, iterations=None):
    """The run stepped by engine.step.step, by hand: the reference."""
    state, seen = initial_state(setup), []
    while state.iteration < setup.params.train.iterations:
        state, statistics = step(setup, state)
        seen.append((statistics.iteration, statistics.thetas.copy(), statistics.estimates.stats.copy()))
    return state, seen


def assert_same(seen, want):
    assert [entry[0] for entry in seen] == [entry[0] for entry in want]
    for (_, thetas, stats), (_, want_thetas, want_stats) in zip(seen, want):
        np.testing.assert_array_equal(thetas, want_thetas)
        assert stats.keys() == want_stats.keys()
        for key in stats:
            np.testing.assert_array_equal(stats[key], want_stats[key])


def test_a_run_alone_is_the_engine_step_iterated():
    setup = setup_of("train.iterations=4")
    want_state, want = train_alone(setup)
    memory = Memory(1, isolate=False)
    (state,) = make_train([setup])([initial_state(setup)], memory)
    assert state.iteration == 4 and memory.rounds == 4
    np.testing.assert_array_equal(state.thetas, want_state.thetas)
    assert_same(memory.seen[0], want)


@pytest.mark.parametrize(
    "measure", [name if name == "cvar" else pytest.param(name, marks=pytest.mark.slow) for name in names()]
)
@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
def test_a_run_in_a_mixed_batch_is_bit_for_bit_the_run_alone(measure):
    first = setup_of("seed=11", *registered(measure))
    setups = [first, *(setup_of(*overrides) for overrides in OTHERS.values())]
    memory = Memory(len(setups))
    states = make_train(setups)([initial_state(s) for s in setups], memory)
    assert not memory.errors
    for setup, state, seen in zip(setups, states, memory.seen):
        want_state, want = train_alone(setup)
        np.testing.assert_array_equal(state.thetas, want_state.thetas)
        assert_same(seen, want)


def test_runs_at_different_iterations_and_lengths_finish_each_at_its_own():
    setups = [setup_of("train.iterations=2"), setup_of("seed=1", "train.iterations=5")]
    memory = Memory(2)
    later, _ = step(setups[1], initial_state(setups[1]))  # the second run resumes at iteration 1
    states = make_train(setups)([initial_state(setups[0]), later], memory)
    assert [s.iteration for s in states] == [2, 5]
    assert [[entry[0] for entry in seen] for seen in memory.seen] == [[0, 1], [1, 2, 3, 4]]
    assert_same(memory.seen[1], train_alone(setups[1])[1][1:])


def test_a_run_that_overflows_leaves_the_batch_and_the_others_go_on():
    setups = [setup_of(), setup_of("train.step_size.initial=1e308"), setup_of("seed=1")]
    memory = Memory(3)
    states = make_train(setups)([initial_state(s) for s in setups], memory)
    assert list(memory.errors) == [1] and isinstance(memory.errors[1], NumericalTrouble)
    assert "lower train.step_size.initial" in str(memory.errors[1])
    assert states[1].iteration < setups[1].params.train.iterations
    for r in (0, 2):
        assert states[r].iteration == setups[r].params.train.iterations
        assert_same(memory.seen[r], train_alone(setups[r])[1])


def test_a_run_alone_raises_its_failure():
    setup = setup_of("train.step_size.initial=1e308")
    with pytest.raises(NumericalTrouble, match=r"lower train\.step_size\.initial"):
        make_train([setup])([initial_state(setup)], Memory(1, isolate=False))


def test_an_error_of_the_recorder_stops_that_run_alone():
    class Refusing(Memory):
        def iteration(self, run, state, statistics, seconds):
            if run == 0 and statistics.iteration == 1:
                raise OSError(28, "No space left on device")
            super().iteration(run, state, statistics, seconds)

    setups = [setup_of(), setup_of("seed=1")]
    memory = Refusing(2)
    states = make_train(setups)([initial_state(s) for s in setups], memory)
    assert isinstance(memory.errors[0], OSError) and states[0].iteration == 1  # the refused iteration is not taken
    assert states[1].iteration == setups[1].params.train.iterations == len(memory.seen[1])
