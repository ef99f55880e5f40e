"""Stopping cleanly on SIGINT or SIGTERM (Ctrl-C, a scheduler's preemption or requeue): the signal is noted, the
run finishes the iteration in progress, writes a checkpoint and stops with `Interrupted`; a second signal stops at
once, as the signal would have without riskplan (the same signal again within REPEAT_SECONDS is the same stop: a
terminal's Ctrl-C reaches a sweep's worker both directly and through its driver). Where a job runner handles SIGUSR2 itself (submitit requeues a
SLURM job on it before its time limit), riskplan checkpoints and records the job first, then hands the signal to
that handler (`Interrupted.end`)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
import time
import typing

SIGNALS = (signal.SIGINT, signal.SIGTERM)
REPEAT_SECONDS = 1.0  # the same signal again within it is one stop, not a second (a person presses again later)
HANDED_ON = signal.SIGUSR2  # caught only while a Python handler (submitit's) has it: that handler runs after


class Interrupted(BaseException):
    """A run stopped by a signal after checkpointing its last finished iteration (a BaseException, as
    KeyboardInterrupt is, so that no `except Exception` swallows it)."""

    def __init__(self, signum: int, finished: int):
        self.signum, self.finished = int(signum), int(finished)
        super().__init__(f"interrupted by {self.name} after {self.finished} iterations, all checkpointed")

    @property
    def name(self) -> str:
        """SIGINT or SIGTERM."""
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        """The shell's code for a process ended by the signal: 130 for SIGINT, 143 for SIGTERM."""
        return 128 + self.signum

    def end(self) -> typing.NoReturn:
        """End this process as the signal would have, once its runs are checkpointed and recorded: SIGUSR2 goes to
        the handler it was meant for (submitit's, which requeues the job and exits); any signal ends it with its
        exit code, leaving no result behind."""
        if self.signum == HANDED_ON and callable(signal.getsignal(HANDED_ON)):
            signal.raise_signal(HANDED_ON)
        raise SystemExit(self.exit_code)


class StopSignals(contextlib.AbstractContextManager):
    """While active (in the main thread; elsewhere signals cannot be caught and this does nothing), SIGINT and
    SIGTERM set `received` instead of stopping the process; the previous handlers come back on exit."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, object] = {}
        self._at = 0.0  # when `received` came (time.monotonic)

    def __enter__(self) -> StopSignals:
        self.received = pending_signal()  # one that came before (a sweep's driver setting jobs up) stops this too
        self._at = time.monotonic()
        if threading.current_thread() is threading.main_thread():
            for signum in SIGNALS:
                self._previous[signum] = signal.signal(signum, self._note)
            if callable(signal.getsignal(HANDED_ON)):
                self._previous[HANDED_ON] = signal.signal(HANDED_ON, self._note)
        return self

    def _note(self, signum: int, frame) -> None:
        if self.received is None:
            self.received, self._at = signum, time.monotonic()
            return
        if repeated(signum, self.received, self._at):
            return
        self._restore()  # a second signal: what it would have done without riskplan, now
        os.kill(os.getpid(), signum)

    def _restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def __exit__(self, *exc) -> None:
        self._restore()

    def check(self, finished: int) -> None:
        """Interrupted(signal, finished iterations) once a signal was received: call it where stopping loses
        nothing. (A SIGUSR2 goes on to its job runner's handler from there: Interrupted.end.)"""
        if self.received is not None:
            raise Interrupted(self.received, finished)


def repeated(signum: int, first: int, at: float) -> bool:
    """Whether `signum` repeats the signal `first` noted at `at` (time.monotonic) closely enough to be the same stop."""
    return signum == first and time.monotonic() - at < REPEAT_SECONDS


@contextlib.contextmanager
def sigint_blocked():
    """SIGINT held back in this thread while the block runs. A process started in the block inherits the mask: a
    Ctrl-C while it starts (seconds of imports, before it handles signals) waits for it to let SIGINT in, instead of
    printing a traceback from the middle of an import. This process still takes a Ctrl-C: in another thread, or in
    this one as the block ends."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def pending_signal() -> int | None:
    """The signal an active StopSignals of this process has noted and not yet acted on (None: none)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    owner = getattr(signal.getsignal(signal.SIGINT), "__self__", None)
    return owner.received if isinstance(owner, StopSignals) else None


class DriverSignals(StopSignals):
    """StopSignals for a process that waits on others (a sweep's driver). The first SIGINT or SIGTERM is noted; a
    SIGTERM, and with `passes_sigint` a SIGINT (to workers of riskplan's own pools, which take a repeat for the same
    stop: a terminal's Ctrl-C reaches them directly too), is passed on to its local workers, which checkpoint and
    stop, so the launch ends by itself; a SIGINT sent to the driver's pid alone stops them as well. With `raise_at_once` (jobs on a cluster, which go on without the driver) the driver
    stops waiting at once (KeyboardInterrupt). A second signal stops the driver at once."""

    def __init__(self, raise_at_once: bool, passes_sigint: bool = False) -> None:
        super().__init__()
        self.raise_at_once = raise_at_once
        self.passed = SIGNALS if passes_sigint else (signal.SIGTERM,)

    def _note(self, signum: int, frame) -> None:
        first = self.received is None
        super()._note(signum, frame)
        if first and signum in self.passed:
            for pid in descendants(os.getpid()):
                with contextlib.suppress(OSError):
                    os.kill(pid, signum)
        if first and self.raise_at_once:
            raise KeyboardInterrupt


def die_with_parent() -> None:
    """SIGKILL for this process when the thread that forked or spawned it ends, however it ended (Linux's
    PR_SET_PDEATHSIG; elsewhere nothing): a child must never outlive its parent, waiting on a pipe no one reads.
    The caller checks its parent afterwards, for one that died just before."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def descendants(pid: int) -> list[int]:
    """The live processes below `pid` (children, grandchildren, ...), from /proc; [] where there is none."""
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else ():
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    parents[int(entry)] = int(stat.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found, frontier = [], [pid]
    while frontier:
        children = [child for child, parent in parents.items() if parent in frontier]
        found += children
        frontier = children
    return found
