"""Many simulated runs as one program: the engine's loop over the batch (riskplan.engine.loop.make_train: one
kernel call, one statistics call per beta and one gradient call per risk node each iteration, for every run that
shares a world and W_l), with each run's rows, checkpoints and files through the recorder exactly as it would have
them alone (riskplan.run.recorder).

A run's numbers do not depend on its batch: its episodes come from its own counter-based streams, the kernel
treats every policy of a call apart, and the statistics and gradients are computed row by row, so a run in a batch
is bit for bit the same run alone. A run that fails (bad input, a non-finite estimate, a disk that refuses its
files) is reported and leaves the batch; the others go on. A signal checkpoints every run at its iteration and
stops them all (Interrupted), and each resumes to the numbers of an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from riskplan.engine.loop import make_train
from riskplan.engine.step import RunSetup
from riskplan.run.checkpoint import can_sync_file_systems, sync_file_systems
from riskplan.run.recorder import Driver, Recorder
from riskplan.run.training import load_kernels
from riskplan.util.collector import resume_collection
from riskplan.util.interrupt import StopSignals
from riskplan.util.lock import hold_lock


@dataclass
class BatchRun:
    """One run of a batch: what to train and where, then what became of it."""

    setup: RunSetup
    out: Path
    resume: bool = False
    summary: dict | None = None  # once finished
    seconds: float | None = None  # once finished: its own time, its share of the loop and its own evaluation and files
    error: BaseException | None = None  # why it stopped alone
    driver: Driver | None = field(default=None, repr=False)


def train_batch(
    runs: list[BatchRun],
    progress: Callable[[int, int], None] | None = None,
    locked: bool = False,
    between: Callable[[], None] | None = None,
) -> list[BatchRun]:
    """Train `runs` (simulated backend, one world and sample schedule: riskplan.engine.step.batch_key) together,
    each under its directory's lock (`locked`: the caller's process holds them); returns them with their summary
    or error. `progress(done, total)` is called as iterations finish, over all runs (one that could not open
    counts as done); `between()` before each run's evaluation (where a part of a sweep takes freed cores).
    Interrupted (after every run's checkpoint) when a signal stops the batch."""
    with contextlib.ExitStack() as stack, StopSignals() as stop:
        active = [run for run in runs if _open(run, stack, locked)]
        if active:
            load_kernels(active[0].setup, active[0].driver.state)
        resume_collection()  # the start-up is over (riskplan.util.collector), as for a run alone
        recorder = Recorder([run.driver for run in active], stop, isolate=True, progress=progress)
        unopened = sum(run.setup.params.train.iterations for run in runs if run.driver is None)
        recorder.done, recorder.total = recorder.done + unopened, recorder.total + unopened
        make_train([run.setup for run in active])([run.driver.state for run in active], recorder)
        grouped = can_sync_file_systems() and len(active) > 1  # the finished files synced once, not run by run
        for run, error, seconds in zip(active, recorder.errors, recorder.seconds):
            run.error = error
            if error is None:
                if between:
                    between()
                _isolated(run, lambda run=run, seconds=seconds: _finish(run, seconds, stop, not grouped))
        finished = [run for run in active if run.summary is not None]
        if grouped and finished:
            _sync_finished(finished)
    return runs


def _open(run: BatchRun, stack: contextlib.ExitStack, locked: bool = False) -> bool:
    """Lock the run's directory (unless the caller holds it) and open its log (fresh or at its checkpoint); False,
    with its error, if it cannot."""
    try:
        run.out.mkdir(parents=True, exist_ok=True)
        if not locked:
            stack.enter_context(hold_lock(run.out))
        run.driver = Driver(run.setup, run.out, run.resume)
        stack.enter_context(run.driver.log)
    except Exception as err:  # this run alone: bad input, an unreadable checkpoint, a directory another holds
        run.error, run.driver = err, None
        return False
    return True


def _isolated(run: BatchRun, work: Callable[[], None]) -> None:
    """Do `work` for one run; an error stops that run alone (its log is closed when the batch ends). A signal
    (Interrupted, a BaseException) stops the batch."""
    try:
        work()
    except Exception as err:
        run.error = err


def _sync_finished(runs: list[BatchRun]) -> None:
    """The finished runs' files made durable together (one syncfs per file system); a disk that refuses fails
    them, since their files may not have reached it."""
    try:
        sync_file_systems([run.out for run in runs])
    except OSError as err:
        for run in runs:
            run.error, run.summary = err, None


def _finish(run: BatchRun, train_seconds: float, stop: StopSignals, durable: bool = True) -> None:
    """Evaluate a trained run and write its files (run.mcap closes first, as for a run alone); its calibration
    record is its part of the batch's time. `durable=False`: its files are synced with the batch's (train_batch),
    before the caller records the run as done."""
    started = time.perf_counter()
    run.driver.evaluate(train_seconds)
    stop.check(run.driver.state.iteration)
    run.driver.log_results()
    run.driver.log.close(durable)  # before the files, as a run alone closes it; the batch's exit closes it again
    run.summary = run.driver.finish(train_seconds + time.perf_counter() - started, durable=durable)
    run.seconds = train_seconds + time.perf_counter() - started
