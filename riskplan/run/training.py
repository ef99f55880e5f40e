"""Centralized and distributed policy-gradient training (eqs. 4, 11, 14), checkpoints, final evaluation.

One loop serves both: a centralized run is a team of one robot whose consensus step is the identity.
Iteration l: every robot i simulates W_l episodes at its own theta^i_l (all robots in one kernel call),
estimates its gradient (Algorithm 1 for CVaR, REINFORCE for the mean), then
    theta^i_{l+1} = sum_j A^{ij} theta^j_{t^{ij}(l)} + eps_l Delta^i          (eq. 14; N = 1 gives eq. 11)
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from riskplan.config.schema import Backend, Order, RiskConf, RiskplanConf
from riskplan.config.typed import as_dict
from riskplan.engine import rng
from riskplan.engine.risk_measures import summary_stats
from riskplan.engine.rollout import simulate
from riskplan.engine.team.convergence import consensus_error
from riskplan.engine.team.kernels import Links, mix_linked
from riskplan.run import cost
from riskplan.run.build import Setup, build_setup, logit_bound, starts
from riskplan.run.checkpoint import State, load_checkpoint, save_checkpoint
from riskplan.run.columns import from_rows, sorted_by
from riskplan.run.evaluation import AVERAGE, NumericalTrouble, check_finite, evaluate, sample_paths, summarize
from riskplan.run.gradients import gradients
from riskplan.run.ray_team import prepare_ray_resume, train_ray
from riskplan.run.record import RunLog, metrics_row
from riskplan.run.run_directory import logged_rows, reopen_log, start_log, write_finished
from riskplan.run.run_files import has_finished
from riskplan.run.schedules import samples_at, step_size
from riskplan.util.collector import resume_collection
from riskplan.util.interrupt import StopSignals
from riskplan.util.limits import cpu_count
from riskplan.util.lock import hold
from riskplan.util.paths import check_output_dir

if TYPE_CHECKING:
    from riskplan.run.results import Run

STOP_ENV = "RISKPLAN_TEST_STOP_AFTER_ITERATION"  # SIGSTOP after logging this iteration, so a test can SIGKILL there


def iterate(setup: Setup, state: State) -> tuple[State, list[dict]]:
    """One iteration of the team loop: rollouts, gradients, consensus, step. Returns the new state and rows."""
    params = setup.params
    started = time.perf_counter()
    l, thetas = state.iteration, state.thetas
    n, beta = setup.robots, params.risk.beta
    episodes = samples_at(l, params.train)
    batch = simulate(
        setup.world, setup.kernel, thetas, starts(setup), rng.robot_keys(params.seed, rng.TRAIN, l, n), episodes
    )
    z = batch.total_reward.reshape(n, episodes)
    scores = batch.score.reshape(n, episodes, -1)
    check_finite(f"iteration {l}: an episode's total reward", z)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite results are caught just below, in one line
        stats = summary_stats(z, beta)
        check_finite(f"iteration {l}: the statistics of the total reward", *stats.values())
        grads, levels, stats["objective"] = np.empty(thetas.shape), np.empty(n), np.empty(n)
        for risk, robots in risk_groups(params):  # one group, all robots, unless team.risk gives robots their own
            grads[robots], levels[robots], stats["objective"][robots] = gradients(
                z[robots], scores[robots], risk, l, stats, robots, params.train.baseline, beta
            )
        check_finite(f"iteration {l}: the objective of the total reward", stats["objective"])
        eps = step_size(l, params.train.step_size)
        new_thetas = consensus_step(setup, thetas, grads, eps, l)
    if not (np.all(np.isfinite(grads)) and np.all(np.isfinite(new_thetas))):
        raise NumericalTrouble(
            f"iteration {l}: theta or its gradient is not finite (theta={_shown(thetas)}, "
            f"gradient={_shown(grads)}); lower train.step_size.initial"
        )
    if not math.isfinite(logit_bound(setup.world, new_thetas, setup.policy)):
        raise NumericalTrouble(
            f"iteration {l}: the new theta={_shown(new_thetas)} overflows the softmax "
            f"(theta . features is not finite); lower train.step_size.initial"
        )
    healthy = setup.mixer.healthy(l)  # team.faults: the averages and the consensus error are the healthy robots'
    ok = slice(None) if healthy.all() else healthy
    error = consensus_error(thetas[ok]) if setup.team else math.nan
    seconds = time.perf_counter() - started
    rows = _robot_rows(l, stats, thetas, grads, eps, error, episodes, seconds, levels, healthy)
    if setup.team:
        average = summary_stats(z[ok].ravel(), beta) | {"objective": stats["objective"][ok].sum()}  # team objective
        level = levels[0] if np.all(levels == levels[0]) else math.nan
        count = episodes * int(healthy.sum())
        average_theta, average_grad = thetas[ok].mean(axis=0), grads[ok].mean(axis=0)
        rows.append(
            metrics_row(l, AVERAGE, average, average_theta, average_grad, eps, error, count, seconds, level, True)
        )
    return State(l + 1, new_thetas, setup.mixer.snapshot(), state.rows + rows), rows  # copied when read


def risk_groups(params: RiskplanConf) -> list[tuple[RiskConf, slice | np.ndarray]]:
    """The robots that share a risk node, as (node, index into the robot axis): one group of all robots (a slice,
    so the default path copies nothing) unless team.risk gives robots nodes of their own."""
    if params.team.risk is None:
        return [(params.risk, slice(None))]
    groups: dict[str, tuple[RiskConf, list[int]]] = {}
    for i, node in enumerate(params.team.risk):
        groups.setdefault(json.dumps(as_dict(node), sort_keys=True), (node, []))[1].append(i)
    return [(node, np.array(robots)) for node, robots in groups.values()]


def _shown(values: np.ndarray) -> str:
    """An array for a one-line message: every number when few (the paper's theta), else a summary (a table)."""
    values = np.asarray(values, dtype=float)
    return str(values.tolist()) if values.size <= 16 else np.array2string(values, threshold=8, max_line_width=10**6)


def consensus_step(setup: Setup, thetas: np.ndarray, grads: np.ndarray, eps: float, l: int) -> np.ndarray:
    """Eq. (14) combine-then-adapt, A theta + eps Delta (default), adapt-then-combine, A (theta + eps Delta), or
    gradient tracking, A theta + eps y with y the robot's tracker of the average gradient (consensus.Mixer.track)."""
    if setup.params.team.order == Order.gradient_tracking and setup.team:
        mixed, tracker = setup.mixer.track(thetas, grads, l)
        return mixed + eps * tracker
    adapt_first = setup.params.team.order == Order.adapt_then_combine
    mixed = thetas + eps * grads if adapt_first else thetas
    for round_index in range(setup.params.team.consensus_rounds if setup.team else 0):
        mixed = setup.mixer.mix(mixed, l, round_index)
    return mixed if adapt_first else mixed + eps * grads


def train(
    config, out_dir: str | Path, *, resume: bool = False, progress: Callable[[int, int, dict], None] | None = None
) -> Run:
    """Train, evaluate and record one experiment into out_dir; with resume, continue from its checkpoint. Returns
    the Run, its tables read back from the files just written (`train_summary` skips that).

    `config` is a composed config (or a Setup built from one). The directory is locked for the whole run: a second
    process writing it gets BadInput naming this one's pid. A fresh run refuses a directory that holds another run.
    """
    setup = config if isinstance(config, Setup) else build_setup(config)
    summary = train_summary(setup, out_dir, resume=resume, progress=progress)
    from riskplan.run.results import finished_run  # lazy: pandas, for the Run's tables; train_summary needs none

    return finished_run(Path(out_dir), setup.config, summary)


def train_summary(
    config, out_dir: str | Path, *, resume: bool = False, progress: Callable[[int, int, dict], None] | None = None
) -> dict:
    """`train`, returning summary.json's dict instead of the Run: what `riskplan train` and sweep jobs need, and
    without pandas."""
    setup = config if isinstance(config, Setup) else build_setup(config)
    out = Path(out_dir)
    check_output_dir(out, str(out))
    out.mkdir(parents=True, exist_ok=True)
    with hold(out):
        return _train_locked(setup, out, resume, progress)


def _train_locked(setup: Setup, out: Path, resume: bool, progress) -> dict:
    """train() under the directory's lock."""
    if setup.params.team.backend == Backend.ray:  # each robot a Ray actor: riskplan.run.ray_team
        return train_ray(setup, out, resume, progress)
    entered = time.perf_counter()
    if resume:
        state = load_checkpoint(out, setup)
        log, rows = reopen_log(out, setup, state.iteration)
        state = replace(state, rows=rows)
        setup.mixer.restore(state.mixer)
    else:
        log = start_log(out, setup)
        state = State(0, np.tile(setup.theta0, (setup.robots, 1)), setup.mixer.state(), [])
    total = setup.params.train.iterations
    every = setup.params.train.checkpoint_every
    resumed_at = state.iteration
    load_kernels(setup, state)  # numba's cache, before the loop: wall_time is the loop's own
    resume_collection()  # the start-up is over: a command that paused the collector for it gets it back here
    wall = time.perf_counter()
    with log, StopSignals() as stop:  # SIGINT or SIGTERM: checkpoint the iteration in progress, then Interrupted
        while state.iteration < total:
            state, rows = iterate(setup, state)
            log.iteration(rows)
            saved = state.iteration % every == 0 or state.iteration == total
            if saved:
                _checkpoint(log, out, state)
            if progress:
                progress(state.iteration, total, rows[-1])
            if os.environ.get(STOP_ENV) == str(state.iteration - 1):
                os.kill(os.getpid(), signal.SIGSTOP)
            if stop.received and not saved:
                _checkpoint(log, out, state)  # the iteration a signal cut short is kept
            stop.check(state.iteration)
        train_seconds = time.perf_counter() - wall
        metrics = sorted_by(from_rows(state.rows), "iteration", "robot")
        evaluation = evaluate(setup, state.thetas)
        trajectories = sample_paths(setup, state.thetas)
        summary = summarize(setup, state, evaluation, metrics, train_seconds)
        if resumed_at:  # wall_time is this process's part of the loop; the run line says so
            summary["resumed_at"] = resumed_at
        stop.check(state.iteration)  # before the final files: a resumed run evaluates again
        log.trajectories(trajectories)
        log.evaluation(evaluation)
        log.summary(summary)
    write_finished(out, setup, metrics, evaluation, trajectories, summary)
    if not resumed_at:  # a whole run calibrates the time estimates of sweeps and reproductions on this machine
        cost.record(cost.setup_steps(setup), time.perf_counter() - entered, numba.get_num_threads() / cpu_count())
    return summary


def load_kernels(setup: Setup, state: State) -> None:
    """Load the compiled kernels an iteration runs from numba's cache (a few tenths of a second, once per process)
    by running them on one episode with throwaway keys, and the synchronous team's mixing kernel on a copy of
    theta: no state changes and no number drawn here is used."""
    cells = starts(setup)[:1]
    simulate(setup.world, setup.kernel, state.thetas[:1], cells, np.zeros(1, dtype=np.uint64), 1)
    if setup.team and state.thetas.shape[1] > 1:
        mix_linked(setup.network, Links(setup.network), state.thetas.copy(), state.thetas.copy())


def _checkpoint(log: RunLog, out: Path, state: State) -> None:
    """The log of every checkpointed iteration is on disk before the checkpoint is."""
    log.sync()
    save_checkpoint(out, state)


def prepare_resume(config, out: Path) -> tuple[Setup, bool]:
    """The Setup of a run to resume, after every check of its config, checkpoint and log (nothing is written), and
    whether the run is finished already (its checkpoint is at train.iterations and its tables are there)."""
    setup = build_setup(config)
    if setup.params.team.backend == Backend.ray:
        return setup, prepare_ray_resume(setup, out)
    state = load_checkpoint(out, setup)
    logged_rows(out / "run.mcap", state.iteration, setup.robots)
    done = state.iteration == setup.params.train.iterations and has_finished(out)
    return setup, done


def _robot_rows(l, stats, thetas, grads, eps, error, samples, seconds, levels, healthy) -> list[dict]:
    """`metrics_row` of every robot i (stats[k][i], thetas[i], grads[i], levels[i], healthy[i]): the same dicts,
    copies of one template with the values every robot shares, filled in column by column."""
    n, m = thetas.shape
    if n <= 4:  # a centralized run or a small team: one metrics_row each is quicker
        return [
            metrics_row(
                l,
                i,
                {k: v[i] for k, v in stats.items()},
                thetas[i],
                grads[i],
                eps,
                error,
                samples,
                seconds,
                levels[i],
                healthy[i],
            )
            for i in range(n)
        ]
    template = metrics_row(
        l, 0, {k: 0.0 for k in stats}, np.zeros(m), np.zeros(1), eps, error, samples, seconds, levels[0], True
    )
    columns = {
        "robot": range(n),
        "healthy": np.asarray(healthy, dtype=bool).tolist(),
        **{k: np.asarray(v, dtype=float).tolist() for k, v in stats.items()},
        **{f"theta_{j}": column for j, column in enumerate(np.asarray(thetas, dtype=float).T.tolist())},
        "grad_norm": _norms(grads),
        "beta_l": np.asarray(levels, dtype=float).tolist(),
    }
    rows = [template.copy() for _ in range(n)]
    for key, column in columns.items():  # existing keys: the template's order stays
        for row, value in zip(rows, column):
            row[key] = value
    return rows


def _norms(vectors: np.ndarray) -> list[float]:
    """np.linalg.norm of each row, bit for bit: that is sqrt(x.dot(x)), and numpy's vecdot (numpy >= 2) takes each
    row's dot product by the very function x.dot(x) calls (the dtype's dot, a BLAS ddot)."""
    if hasattr(np, "vecdot"):
        return np.sqrt(np.vecdot(vectors, vectors)).tolist()
    return [math.sqrt(x.dot(x)) for x in vectors]
