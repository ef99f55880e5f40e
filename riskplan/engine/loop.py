"""The training loop, the engine's own, over a batch of runs (PureJaxRL's `make_train`): `make_train(setups)` reads
the frozen set-ups once and returns `train(states, recorder) -> states`, which runs every run to its
train.iterations, R = 1 for a run alone.

An iteration of the batch, for the runs at the same iteration l, is a few calls for all of them:
  1. rollouts: one kernel call over every robot of every run, each from its own streams (`step.batched_rollouts`);
  2. the finiteness of the episodes, one check over the whole block;
  3. the statistics (mean, VaR, CVaR, std): one `summary_stats` call per distinct beta over all its rows;
  4. the gradients: one `gradients` call per distinct risk node (measure, its parameters, beta, baseline) over
     all the robots that share it, whichever run they belong to;
  5. each run's consensus step, fault rules and checks (`step.advance`: the Mixer is a run's own).
Every statistic and gradient is computed row by row, so a run's numbers are bit for bit those of `step.step` alone
(tests/engine/test_loop.py checks it for every measure, beta and team in one batch).

Effects go through one `Recorder`: the loop hands it each run's new state and Statistics, and a run whose
estimates or recording fail is handed to `Recorder.failed` and leaves the batch; the others go on. The loop holds
no files, clocks of its own beyond the iteration's time, or signals: the recorder checks those between rounds.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol

import numpy as np

from riskplan.config.typed import as_dict
from riskplan.engine.gradients import gradients
from riskplan.engine.risk_measures import summary_stats
from riskplan.engine.schedules import step_size
from riskplan.engine.step import (
    Estimates,
    NumericalTrouble,
    RunSetup,
    Statistics,
    TrainState,
    advance,
    batch_episodes,
    check_finite,
    check_step,
    risk_groups,
    step,
)


class Recorder(Protocol):
    """Where the loop's results go (riskplan.run.recorder.Recorder writes runs' files)."""

    def iteration(self, run: int, state: TrainState, statistics: Statistics, seconds: float) -> None:
        """Run `run` finished an iteration: its next state and what it measured, in `seconds` (its share)."""

    def failed(self, run: int, error: Exception) -> None:
        """Run `run` stopped on `error` (it leaves the batch); may re-raise it to stop everything."""

    def round_done(self, runs: Sequence[int], states: Sequence[TrainState]) -> Sequence[int]:
        """Every live run did one more iteration (the place to checkpoint and stop on a signal); returns the runs
        that failed meanwhile (they leave the batch)."""


class _Rows(NamedTuple):
    """Where a run's robots sit in one iteration's block of episodes, and which gradient calls they join."""

    start: int  # the run's first row in the block
    stop: int
    groups: list[tuple[str, object, np.ndarray]]  # (the risk node's key, the node, robot positions in the run)


def make_train(setups: Sequence[RunSetup]) -> Callable[[Sequence[TrainState], Recorder], list[TrainState]]:
    """The training function of a batch of runs that share a world, a policy and W_l (step.batch_key)."""
    setups = tuple(setups)
    totals = [setup.params.train.iterations for setup in setups]
    solo = [not setup.team and not setup.params.team.faults for setup in setups]  # advance_solo steps them together
    nodes = [_risk_nodes(setup) for setup in setups]  # the gradient calls each run's robots join, read once

    def train(states: Sequence[TrainState], recorder: Recorder) -> list[TrainState]:
        states = list(states)
        live = [r for r, state in enumerate(states) if state.iteration < totals[r]]
        while live:
            failed: set[int] = set()
            for runs in _by_iteration(live, states):
                started = time.perf_counter()
                outcomes = iterate(setups, nodes, solo, runs, states)
                seconds = (time.perf_counter() - started) / len(runs)  # the batch's calls, shared out
                for r, outcome in zip(runs, outcomes):
                    try:
                        if isinstance(outcome, Exception):
                            raise outcome
                        recorder.iteration(r, *outcome, seconds)
                        states[r] = outcome[0]
                    except Exception as err:  # this run alone: a non-finite estimate, a disk that refuses its rows
                        failed.add(r)
                        recorder.failed(r, err)
            live = [r for r in live if r not in failed]
            failed.update(recorder.round_done(live, states))
            live = [r for r in live if r not in failed and states[r].iteration < totals[r]]
        return states

    return train


def iterate(
    setups, nodes, solo: list[bool], runs: list[int], states: list[TrainState]
) -> list[tuple[TrainState, Statistics] | Exception]:
    """One iteration of the runs `runs` (all at the same iteration): each run's (next state, Statistics), or the
    exception that stopped it."""
    l = states[runs[0]].iteration
    if len(runs) == 1:  # a run alone: the engine's step itself
        r = runs[0]
        return [_attempt(lambda: step(setups[r], states[r]))]
    group = [setups[r] for r in runs]
    z, scores, bounds = batch_episodes(group, l, [states[r].thetas for r in runs])
    rows = [_Rows(a, b, nodes[r]) for r, a, b in zip(runs, bounds[:-1], bounds[1:])]
    outcomes = batch_estimates(group, l, z, scores, rows)
    lone = [k for k, r in enumerate(runs) if solo[r] and not isinstance(outcomes[k], Exception)]
    if lone:
        stepped = advance_solo(
            [setups[runs[k]] for k in lone], [states[runs[k]] for k in lone], [outcomes[k] for k in lone]
        )
        for k, outcome in zip(lone, stepped):
            outcomes[k] = outcome
    return [
        _attempt(lambda r=r, e=outcome: advance(setups[r], states[r], e)) if isinstance(outcome, Estimates) else outcome
        for r, outcome in zip(runs, outcomes)
    ]


def advance_solo(setups, states: list[TrainState], estimates: list[Estimates]) -> list:
    """step.advance for runs of one robot each and no faults, as one array step: theta_l + eps_l Delta (eq. 11)
    for all of them, the checks over the block, each run's Statistics. The Mixer of such a run never holds a
    message, so its state passes through. A run whose step is not finite gets check_step's NumericalTrouble."""
    l = states[0].iteration
    thetas = np.concatenate([state.thetas for state in states])
    grads = np.concatenate([e.grads for e in estimates])
    eps = [step_size(l, setup.params.train.step_size) for setup in setups]
    with np.errstate(over="ignore", invalid="ignore"):  # a theta that overflows is caught just below, run by run
        new = thetas + np.array(eps)[:, None] * grads
    fine = np.isfinite(grads).all(axis=1) & np.isfinite(new).all(axis=1)
    if not (fine.all() and math.isfinite(setups[0].policy.logit_bound(new))):  # the runs share their policy
        fine[:] = False  # rare: each run's own check finds the culprit and says it in its words
    outcomes = []
    for k, (setup, state, e) in enumerate(zip(setups, states, estimates)):
        own = new[k : k + 1]
        if not fine[k]:
            try:
                check_step(setup, l, state.thetas, e.grads, own)
            except NumericalTrouble as trouble:
                outcomes.append(trouble)
                continue
        statistics = Statistics(l, state.thetas, e, eps[k], math.nan, setup.mixer.healthy(l), None)
        outcomes.append((TrainState(l + 1, own, state.mixer), statistics))
    return outcomes


def batch_estimates(setups, l: int, z: np.ndarray, scores: np.ndarray, rows: list[_Rows]) -> list:
    """step.estimate for every run of a batch from one block of episodes (z (T, W), scores (T, W, P)): the
    statistics by beta and the gradients by risk node, each in one call over every row that shares it. Each run's
    Estimates, or the NumericalTrouble that stopped it, with `estimate`'s message."""
    where = f"iteration {l}"
    finite = np.isfinite(z).all(axis=1)
    outcomes: list = [
        None
        if finite[run.start : run.stop].all()
        else _attempt(lambda run=run: check_finite(f"{where}: an episode's total reward", z[run.start : run.stop]))
        for run in rows
    ]
    ok = [k for k, outcome in enumerate(outcomes) if outcome is None]
    stats = {name: np.empty(len(z)) for name in ("mean", "cvar", "value_at_risk", "std", "objective")}
    grads, levels = np.empty((len(z), scores.shape[-1])), np.empty(len(z))
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite results are caught below, run by run
        for beta, members in _by_beta(setups, ok).items():
            index = _compact(np.concatenate([np.arange(rows[k].start, rows[k].stop) for k in members]))
            for name, values in summary_stats(z[index], beta, parallel=True).items():
                stats[name][index] = values
        for (node, beta, baseline), members in _by_node(setups, rows, ok).values():
            index = _compact(np.concatenate(members))
            grads[index], levels[index], stats["objective"][index] = gradients(
                z[index], scores[index], node, l, stats, index, baseline, beta
            )
    for k in ok:
        part = slice(rows[k].start, rows[k].stop)
        own = {name: values[part] for name, values in stats.items()}
        outcomes[k] = _attempt(lambda own=own, part=part: _checked(where, z[part], own, grads[part], levels[part]))
    return outcomes


def _checked(where: str, z: np.ndarray, stats: dict, grads: np.ndarray, levels: np.ndarray) -> Estimates:
    """A run's Estimates once its statistics and objective are finite (`estimate`'s checks, its messages)."""
    objective = stats.pop("objective")
    check_finite(f"{where}: the statistics of the total reward", *stats.values())
    check_finite(f"{where}: the objective of the total reward", objective)
    return Estimates(z.shape[1], z, stats | {"objective": objective}, grads, levels)


def _by_beta(setups, ok: list[int]) -> dict[float, list[int]]:
    """The runs `ok` by their risk.beta: one statistics call each."""
    groups: dict[float, list[int]] = {}
    for k in ok:
        groups.setdefault(setups[k].params.risk.beta, []).append(k)
    return groups


def _by_node(setups, rows: list[_Rows], ok: list[int]) -> dict[tuple, tuple[tuple, list[np.ndarray]]]:
    """The robots of the runs `ok` by what their gradient shares (risk node, beta, baseline): one call each, as
    {key: ((node, beta, baseline), [their rows in the block])}."""
    groups: dict[tuple, tuple[tuple, list[np.ndarray]]] = {}
    for k in ok:
        params = setups[k].params
        for text, node, positions in rows[k].groups:
            key = (text, params.risk.beta, params.train.baseline)
            groups.setdefault(key, ((node, params.risk.beta, params.train.baseline), []))[1].append(
                rows[k].start + positions
            )
    return groups


def _compact(index: np.ndarray) -> slice | np.ndarray:
    """A slice for rows that are one stretch (a view, no copy of the block), else the index."""
    if len(index) and index[-1] - index[0] == len(index) - 1:
        return slice(int(index[0]), int(index[-1]) + 1)
    return index


def _risk_nodes(setup: RunSetup) -> list[tuple[str, object, np.ndarray]]:
    """The risk nodes of a run's robots (one for all unless team.risk gives robots their own), each with its key
    and the positions of its robots in the run."""
    positions = np.arange(setup.robots)
    return [
        (json.dumps(as_dict(node), sort_keys=True), node, positions[members])
        for node, members in risk_groups(setup.params)
    ]


def _by_iteration(live: list[int], states: list[TrainState]) -> list[list[int]]:
    """The live runs grouped by their iteration (one kernel call each); a batch's runs usually share it."""
    groups: dict[int, list[int]] = {}
    for r in live:
        groups.setdefault(states[r].iteration, []).append(r)
    return [groups[l] for l in sorted(groups)]


def _attempt(work: Callable):
    """work(), or the Exception that stopped it: a run's failure is a value of the loop, the batch goes on."""
    try:
        return work()
    except Exception as err:
        return err
