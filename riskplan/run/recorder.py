"""The engine loop's effects (riskplan.engine.loop.Recorder): each run's rows into its run.mcap, its checkpoints
when due, progress, and the signals, for a run alone and for every run of a batch alike.

A `Driver` is one run's files around the loop: run.mcap opened fresh or at its checkpoint, the rows, the
checkpoints, then the evaluation and the finished files. The `Recorder` hands each iteration to its run's Driver,
keeps each run's share of the loop's time, and between rounds checkpoints every live run and stops when a signal
came. A run alone lets its failure stop the command; a batch (`isolate`) keeps each failure with its run.

A checkpoint's commit (its fsyncs, the rename) runs in a thread of its own while the loop computes the next
iterations (`Commits`): an fsync is a millisecond on a local disk and tens on a cluster's network file system, and
the loop need not wait for it. One commit is in flight at a time; the next one, a signal's stop, a test's pause and
the end of the loop (`Recorder.drain`) wait for it first, so what a kill leaves is always a checkpoint whose log is
on disk (the one before, at worst), as before.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numba

from riskplan.engine.step import RunSetup, Statistics, TrainState, initial_state
from riskplan.run import cost
from riskplan.run.checkpoint import detached, load_checkpoint, save_checkpoints
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


class Commits:
    """The recorder's checkpoints committed in a background thread, one commit at a time (save_checkpoints reads
    detached states and fsyncs the logs' descriptors alone, so the loop may write on meanwhile)."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._runs: list[int] = []
        self._errors: list[Exception | None] = []

    def start(self, runs: list[int], drivers: list[Driver]) -> None:
        """Commit the drivers' checkpoints (of `runs`) in the background; the caller waited for the one before."""
        outs, logs, states = [d.out for d in drivers], [d.log for d in drivers], [detached(d.state) for d in drivers]

        def commit() -> None:
            try:
                self._errors = save_checkpoints(outs, states, logs)
            except Exception as err:  # save_checkpoints gives each run its own; this is a fault of the whole commit
                self._errors = [err] * len(outs)

        self._runs, self._errors = runs, [None] * len(runs)
        self._thread = threading.Thread(target=commit, name="riskplan-checkpoint", daemon=True)
        self._thread.start()

    def wait(self) -> list[tuple[int, Exception]]:
        """Wait for the commit in flight; the runs whose checkpoint it could not write, with their errors."""
        if self._thread is None:
            return []
        self._thread.join()
        self._thread = None
        return [(r, error) for r, error in zip(self._runs, self._errors) if error is not None]


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
        self.commits = Commits()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        """Never leave a commit running past the loop (a failure or a signal leaves it the run's checkpoint)."""
        self.commits.wait()

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
            failed += self.drain()  # the test finds the checkpoint of the iteration it stopped at on disk
            os.kill(os.getpid(), signal.SIGSTOP)
            # a signal the test sent while this process stood still may reach one of numba's threads, whose
            # handler call lets the main thread look later than this round: it is taken before the check below
            time.sleep(SETTLE_SECONDS)
        if self.stop.received is not None:
            failed += self._checkpoint([r for r in runs if r not in failed and not self._saved(r)])
            failed += self.drain()
            self.stop.check(min((states[r].iteration for r in runs if r not in failed), default=0))
        return failed

    def drain(self) -> list[int]:
        """Wait for the checkpoint commit in flight (the loop's end calls it before the runs' final files); the runs
        whose checkpoint failed, each handed to `failed` (a run alone raises its error)."""
        return self._failed(self.commits.wait())

    def _checkpoint(self, runs: list[int]) -> list[int]:
        """Checkpoint the runs, each after its log, in the background (Commits): a batch's as one group commit
        (riskplan.run.checkpoint.save_checkpoints: two syncs of the disk for all of them, not three fsyncs each).
        First the commit before is waited for: the runs it failed (each handed to `failed`) are returned, and leave
        the batch with the checkpoint before theirs."""
        if not runs:  # the commit in flight goes on under the next iterations
            return []
        failed = self.drain()
        runs = [r for r in runs if r not in failed]
        if runs:
            self.commits.start(runs, [self.drivers[r] for r in runs])
            for r in runs:  # saved as far as the loop is concerned: a failure is handed over when it is known
                self.drivers[r].saved = self.drivers[r].state.iteration
        return failed

    def _failed(self, errors: list[tuple[int, Exception]]) -> list[int]:
        for r, error in errors:
            self.failed(r, error)
        return [r for r, _ in errors]

    def _saved(self, run: int) -> bool:
        return self.drivers[run].saved == self.drivers[run].state.iteration
