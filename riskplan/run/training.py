"""The simulated backend's driver: riskplan.engine.step's iteration in a loop, with what a run needs around it
(the run directory and its lock, run.mcap, checkpoints, signals, progress), then the final evaluation and files.

One loop serves both: a centralized run is a team of one robot whose consensus step is the identity.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from riskplan.config.schema import Backend
from riskplan.engine.step import Setup, TrainState, initial_state, simulator, starts, step
from riskplan.engine.team.kernels import Links, mix_linked
from riskplan.run import cost
from riskplan.run.build import build_setup
from riskplan.run.checkpoint import State, load_checkpoint, save_checkpoint
from riskplan.run.columns import from_rows, sorted_by
from riskplan.run.evaluation import evaluate, sample_paths, summarize
from riskplan.run.metrics_rows import statistics_rows
from riskplan.run.ray_team import prepare_ray_resume, train_ray
from riskplan.run.run_directory import logged_rows, reopen_log, start_log, write_finished
from riskplan.run.run_files import has_finished
from riskplan.util.collector import resume_collection
from riskplan.util.interrupt import StopSignals
from riskplan.util.limits import cpu_count
from riskplan.util.lock import hold
from riskplan.util.paths import check_output_dir

if TYPE_CHECKING:
    from riskplan.run.results import Run

STOP_ENV = "RISKPLAN_TEST_STOP_AFTER_ITERATION"  # SIGSTOP after logging this iteration, so a test can SIGKILL there


def iterate(setup: Setup, state: State, batch=None) -> tuple[State, list[dict]]:
    """One iteration of the team (riskplan.engine.step), timed, and its metrics rows. `batch`: the iteration's
    episodes when a batched sweep ran them already."""
    started = time.perf_counter()
    new, statistics = step(setup, TrainState(state.iteration, state.thetas, state.mixer), batch)
    rows = statistics_rows(statistics, time.perf_counter() - started)
    return State(new.iteration, new.thetas, new.mixer, state.rows + rows), rows  # copied when read


def train(
    config, out_dir: str | Path, *, resume: bool = False, progress: Callable[[int, int, dict], None] | None = None
) -> Run:
    """Train, evaluate and record one experiment into out_dir; with resume, continue from its checkpoint. Returns
    the Run, its tables read back from the files just written (`train_summary` skips that).

    `config` is a composed config (or a Setup built from one). The directory is locked for the whole run: a second
    process writing it gets BadInput naming this one's pid. A fresh run refuses a directory that holds another run.
    """
    setup = config if isinstance(config, Setup) else build_setup(config, needs_ray=not resume)
    summary = train_summary(setup, out_dir, resume=resume, progress=progress)
    from riskplan.run.results import finished_run  # lazy: pandas, for the Run's tables; train_summary needs none

    return finished_run(Path(out_dir), setup.config, summary)


def train_summary(
    config, out_dir: str | Path, *, resume: bool = False, progress: Callable[[int, int, dict], None] | None = None
) -> dict:
    """`train`, returning summary.json's dict instead of the Run: what `riskplan train` and sweep jobs need, and
    without pandas."""
    setup = config if isinstance(config, Setup) else build_setup(config, needs_ray=not resume)
    out = Path(out_dir)
    check_output_dir(out, str(out))
    out.mkdir(parents=True, exist_ok=True)
    with hold(out):
        return _train_locked(setup, out, resume, progress)


def _train_locked(setup: Setup, out: Path, resume: bool, progress) -> dict:
    """train() under the directory's lock."""
    if setup.params.team.backend == Backend.ray:  # each robot a Ray actor: riskplan.run.ray_team
        return train_ray(setup, out, resume, progress)
    run = Driver(setup, out, resume, progress)
    load_kernels(setup, run.state)  # numba's cache, before the loop: wall_time is the loop's own
    resume_collection()  # the start-up is over: a command that paused the collector for it gets it back here
    wall = time.perf_counter()
    with run.log, StopSignals() as stop:  # SIGINT or SIGTERM: checkpoint the iteration in progress, then Interrupted
        while not run.trained:
            run.record(*iterate(setup, run.state), stop)
            stop.check(run.state.iteration)
        run.evaluate(time.perf_counter() - wall)
        stop.check(run.state.iteration)  # before the final files: a resumed run evaluates again
        run.log_results()
    return run.finish()


class Driver:
    """One simulated run's I/O around the engine's step: run.mcap opened fresh or at its checkpoint, each
    iteration's rows, checkpoints and progress, then the evaluation and the finished files. The same for a run
    alone (`train`) and a run in a batch (riskplan.run.batch); the caller holds the directory's lock."""

    def __init__(self, setup: Setup, out: Path, resume: bool, progress=None):
        self.setup, self.out, self.progress = setup, out, progress
        self.entered = time.perf_counter()
        self.compiles = cost.compiles()
        if resume:
            state = load_checkpoint(out, setup)
            self.log, rows = reopen_log(out, setup, state.iteration)
            self.state = replace(state, rows=rows)
        else:
            self.log = start_log(out, setup)
            self.state = State(*initial_state(setup), [])
        self.resumed_at = self.state.iteration
        self.total = setup.params.train.iterations
        self.results: tuple | None = None  # (metrics, evaluation, trajectories, summary) once evaluated

    @property
    def trained(self) -> bool:
        return self.state.iteration >= self.total

    def record(self, state: State, rows: list[dict], stop: StopSignals) -> None:
        """An iteration done: its rows into run.mcap, a checkpoint when one is due (or a signal came), progress."""
        self.state = state
        self.log.iteration(rows)
        saved = state.iteration % self.setup.params.train.checkpoint_every == 0 or state.iteration == self.total
        if saved:
            self.checkpoint()
        if self.progress:
            self.progress(state.iteration, self.total, rows[-1])
        if os.environ.get(STOP_ENV) == str(state.iteration - 1):
            os.kill(os.getpid(), signal.SIGSTOP)
        if stop.received and not saved:
            self.checkpoint()  # the iteration a signal cut short is kept

    def checkpoint(self) -> None:
        """The log of every checkpointed iteration is on disk before the checkpoint is."""
        self.log.sync()
        save_checkpoint(self.out, self.state)

    def evaluate(self, train_seconds: float) -> dict:
        """The final policies on fresh episodes, the sampled paths and summary.json's figures."""
        setup, state = self.setup, self.state
        metrics = sorted_by(from_rows(state.rows), "iteration", "robot")
        evaluation = evaluate(setup, state.thetas)
        trajectories = sample_paths(setup, state.thetas)
        summary = summarize(setup, state, evaluation, metrics, train_seconds)
        if self.resumed_at:  # wall_time is this process's part of the loop; the run line says so
            summary["resumed_at"] = self.resumed_at
        self.results = (metrics, evaluation, trajectories, summary)
        return summary

    def log_results(self) -> None:
        """The evaluation's records into run.mcap (before it closes)."""
        _, evaluation, trajectories, summary = self.results
        self.log.trajectories(trajectories)
        self.log.evaluation(evaluation)
        self.log.summary(summary)

    def finish(self, seconds: float | None = None, share: float | None = None) -> dict:
        """The finished run's files (after run.mcap closed), summary.json last; returns the summary. A whole run
        calibrates the time estimates of sweeps and reproductions on this machine (riskplan.run.cost) with its wall
        seconds since it opened (a batch gives each run its part of the batch's time, on all cores), unless numba
        compiled a kernel meanwhile: then its seconds are mostly the compiler's."""
        metrics, evaluation, trajectories, summary = self.results
        write_finished(self.out, self.setup, metrics, evaluation, trajectories, summary)
        if not self.resumed_at and cost.compiles() == self.compiles:
            seconds = time.perf_counter() - self.entered if seconds is None else seconds
            share = numba.get_num_threads() / cpu_count() if share is None else share
            cost.record(cost.setup_steps(self.setup), seconds, share)
        return summary


def load_kernels(setup: Setup, state: State) -> None:
    """Load the compiled kernels an iteration runs from numba's cache (a few tenths of a second, once per process)
    by running them on one episode with throwaway keys, and the synchronous team's mixing kernel on a copy of
    theta: no state changes and no number drawn here is used."""
    cells = starts(setup)[:1]
    simulator(setup)(setup.world, setup.kernel, state.thetas[:1], cells, np.zeros(1, dtype=np.uint64), 1)
    if setup.team and state.thetas.shape[1] > 1:
        mix_linked(setup.network, Links(setup.network), state.thetas.copy(), state.thetas.copy())


def prepare_resume(config, out: Path) -> tuple[Setup, bool]:
    """The Setup of a run to resume, after every check of its config, checkpoint and log (nothing is written), and
    whether the run is finished already (its checkpoint is at train.iterations and its tables are there)."""
    setup = build_setup(config, needs_ray=False)
    if setup.params.team.backend == Backend.ray:  # Ray only if a robot has iterations left (prepare_ray_resume)
        return setup, prepare_ray_resume(setup, out)
    state = load_checkpoint(out, setup)
    logged_rows(out / "run.mcap", state.iteration, setup.robots)
    done = state.iteration == setup.params.train.iterations and has_finished(out)
    return setup, done
