"""The engine loop's effects (riskplan.engine.loop.Recorder): each run's rows into its run.mcap, its checkpoints
when due, progress, and the signals, for a run alone and for every run of a batch alike.

A `Driver` is one run's files around the loop: run.mcap opened fresh or at its checkpoint, the rows, the
checkpoints, then the evaluation and the finished files. The `Recorder` hands each iteration to its run's Driver,
keeps each run's share of the loop's time, and between rounds checkpoints every live run and stops when a signal
came. A run alone lets its failure stop the command; a batch (`isolate`) keeps each failure with its run.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numba

from riskplan.engine.step import RunSetup, Statistics, TrainState, initial_state
from riskplan.run import cost
from riskplan.run.checkpoint import load_checkpoint, save_checkpoints
from riskplan.run.columns import from_rows, sorted_by
from riskplan.run.evaluation import evaluate, sample_paths, summarize
from riskplan.run.metrics_rows import statistics_rows
from riskplan.run.run_directory import reopen_log, start_log, write_finished
from riskplan.util.interrupt import StopSignals
from riskplan.util.limits import cpu_count

STOP_ENV = "RISKPLAN_TEST_STOP_AFTER_ITERATION"  # SIGSTOP after logging this iteration, so a test can SIGKILL there
SETTLE_SECONDS = 0.2  # after that stop, for a signal sent meanwhile to be handled (tests only)


class Driver:
    """One simulated run's files around the engine's loop: run.mcap opened fresh or at its checkpoint, each
    iteration's rows, checkpoints and progress, then the evaluation and the finished files. The caller holds the
    directory's lock."""

    def __init__(self, setup: RunSetup, out: Path, resume: bool, progress=None):
        self.setup, self.out, self.progress = setup, out, progress
        self.entered = time.perf_counter()
        self.compiles = cost.compiles()
        if resume:
            self.state = load_checkpoint(out, setup)
            self.log, self.rows = reopen_log(out, setup, self.state.iteration)
        else:
            self.log, self.rows = start_log(out, setup), []
            self.state = initial_state(setup)
        self.saved = self.resumed_at = self.state.iteration
        self.total = setup.params.train.iterations
        self.results: tuple | None = None  # (metrics, evaluation, trajectories, summary) once evaluated

    @property
    def trained(self) -> bool:
        return self.state.iteration >= self.total

    def record(self, state: TrainState, rows: list[dict]) -> None:
        """An iteration done: its rows into run.mcap (durable before the next), and progress. The recorder takes
        the checkpoint when one is due, at the end of the round."""
        self.state = state
        self.rows.extend(rows)
        self.log.iteration(rows)
        if self.progress:
            self.progress(state.iteration, self.total, rows[-1])

    @property
    def due(self) -> bool:
        """Whether the state is one to checkpoint: every train.checkpoint_every iterations, and the last."""
        every, at = self.setup.params.train.checkpoint_every, self.state.iteration
        return self.saved != at and (at % every == 0 or at == self.total)

    @property
    def pauses_for_tests(self) -> bool:
        """STOP_ENV: whether the iteration it names was just logged (and checkpointed if due): the process then
        stops itself (SIGSTOP), once for all the runs of its batch, so that a test can act on it there."""
        return os.environ.get(STOP_ENV) == str(self.state.iteration - 1)

    def evaluate(self, train_seconds: float) -> dict:
        """The final policies on fresh episodes, the sampled paths and summary.json's figures."""
        setup, state = self.setup, self.state
        metrics = sorted_by(from_rows(self.rows), "iteration", "robot")
        evaluation = evaluate(setup, state.thetas)
        trajectories = sample_paths(setup, state.thetas)
        summary = summarize(setup, state, evaluation, metrics, train_seconds, self.resumed_at)
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

    def finish(self, seconds: float | None = None, share: float | None = None, durable: bool = True) -> dict:
        """The finished run's files (after run.mcap closed), summary.json last; returns the summary. A whole run
        calibrates the time estimates of sweeps and reproductions on this machine (riskplan.run.cost) with its wall
        seconds since it opened (a batch gives each run its part of the batch's time, on all cores), unless numba
        compiled a kernel meanwhile: then its seconds are mostly the compiler's. `durable=False`: the files are not
        synced one by one (a batch syncs its file systems once)."""
        metrics, evaluation, trajectories, summary = self.results
        write_finished(self.out, self.setup, metrics, evaluation, trajectories, summary, durable)
        if not self.resumed_at and cost.compiles() == self.compiles:
            seconds = time.perf_counter() - self.entered if seconds is None else seconds
            share = numba.get_num_threads() / cpu_count() if share is None else share
            cost.record(cost.setup_steps(self.setup), seconds, share)
        return summary


class Recorder:
    """The loop's one way out for a set of runs (riskplan.engine.loop.Recorder): run r's iterations go to
    drivers[r]; `seconds[r]` is its share of the loop's time; `errors[r]` what stopped it (with `isolate`; a run
    alone re-raises it). `progress(done, total)` counts iterations over all runs."""

    def __init__(
        self,
        drivers: Sequence[Driver],
        stop: StopSignals,
        *,
        isolate: bool = False,
        progress: Callable[[int, int], None] | None = None,
    ):
        self.drivers, self.stop, self.isolate, self.progress = list(drivers), stop, isolate, progress
        self.seconds = [0.0] * len(self.drivers)
        self.errors: list[BaseException | None] = [None] * len(self.drivers)
        self.done = sum(driver.state.iteration for driver in self.drivers)
        self.total = sum(driver.total for driver in self.drivers)

    def iteration(self, run: int, state: TrainState, statistics: Statistics, seconds: float) -> None:
        self.seconds[run] += seconds
        self.drivers[run].record(state, statistics_rows(statistics, seconds))
        self.done += 1
        if self.progress:
            self.progress(self.done, self.total)

    def failed(self, run: int, error: Exception) -> None:
        if not self.isolate:
            raise error
        self.errors[run] = error

    def round_done(self, runs: Sequence[int], states: Sequence[TrainState]) -> list[int]:
        """The round's due checkpoints; then, if a signal came, every live run's last finished iteration kept (a
        checkpoint unless it has one there) and Interrupted. Returns the runs whose checkpoint failed: they leave
        the batch."""
        failed = self._checkpoint([r for r in runs if self.drivers[r].due])
        if any(self.drivers[r].pauses_for_tests for r in runs):
            os.kill(os.getpid(), signal.SIGSTOP)
            # a signal the test sent while this process stood still may reach one of numba's threads, whose
            # handler call lets the main thread look later than this round: it is taken before the check below
            time.sleep(SETTLE_SECONDS)
        if self.stop.received is not None:
            failed += self._checkpoint([r for r in runs if r not in failed and not self._saved(r)])
            self.stop.check(min((states[r].iteration for r in runs if r not in failed), default=0))
        return failed

    def _checkpoint(self, runs: list[int]) -> list[int]:
        """Checkpoint the runs; those that failed (each handed to `failed`)."""
        errors = self._checkpoints(runs)
        for r, error in zip(runs, errors):
            if error is not None:
                self.failed(r, error)
        return [r for r, error in zip(runs, errors) if error is not None]

    def _saved(self, run: int) -> bool:
        return self.drivers[run].saved == self.drivers[run].state.iteration

    def _checkpoints(self, runs: list[int]) -> list[Exception | None]:
        """Checkpoint the runs, each after its log: a batch's as one group commit (riskplan.run.checkpoint.
        save_checkpoints: two syncs of the disk for all of them, not three fsyncs each). Each run's error, or None."""
        drivers = [self.drivers[r] for r in runs]
        errors = save_checkpoints([d.out for d in drivers], [d.state for d in drivers], [d.log for d in drivers])
        for driver, error in zip(drivers, errors):
            if error is None:
                driver.saved = driver.state.iteration
        return errors
