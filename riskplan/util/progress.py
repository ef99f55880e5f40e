"""Terminal progress for long work (rich), kept out of the computing code."""

from __future__ import annotations

import contextlib
import sys
import time

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

console = Console(stderr=True)


class TrainingBar:
    """Iteration bar showing the latest mean and CVaR; a context manager yielding the progress callback."""

    def __enter__(self):
        self._bar = _live(
            TextColumn("[bold]train"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[stats]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
        self._bar.__enter__()
        self._task = None
        return self.update

    def update(self, done: int, total: int, row: dict) -> None:
        """Advance to `done` of `total` iterations."""
        if self._task is None:
            self._task = self._bar.add_task("train", total=total, completed=0, stats="")
        stats = f"mean {row['mean']:9.1f}  CVaR {row['cvar']:9.1f}"
        self._bar.update(self._task, completed=done, total=total, stats=stats)

    def __exit__(self, *exc):
        return self._bar.__exit__(*exc)


class PhaseBars:
    """A bar for each phase of a long command as it comes (`riskplan report`: loading runs, making and drawing
    figures); a context manager yielding the progress callback progress(phase, done, total).

    No refresh thread (rich's auto-refresh): the report forks its workers while the bars are up, and a thread
    holding the terminal's lock at a fork would leave that lock held in the child. The bars redraw when told, at
    most every REDRAW seconds, and when a phase completes."""

    REDRAW = 0.1

    def __enter__(self):
        self._bar = _live(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), auto=False
        )
        self._bar.__enter__()
        self._tasks: dict[str, TaskID] = {}
        self._drawn = 0.0
        return self.update

    def update(self, phase: str, done: int, total: int) -> None:
        """`done` of `total` in `phase` (a new phase gets its own bar)."""
        if phase not in self._tasks:
            self._tasks[phase] = self._bar.add_task(phase, total=total)
        self._bar.update(self._tasks[phase], completed=done, total=total)
        now = time.monotonic()
        if now - self._drawn >= self.REDRAW or done >= total:
            self._drawn = now
            self._bar.refresh()

    def __exit__(self, *exc):
        return self._bar.__exit__(*exc)


def _live(*columns, auto: bool = True) -> Progress:
    """A transient progress display on stderr, live on a terminal or in a notebook (`auto`: rich's refresh
    thread); nothing elsewhere (a log, a pipe, CI)."""
    return Progress(
        *columns,
        console=console,
        transient=True,
        auto_refresh=auto,
        disable=not (sys.stderr.isatty() or console.is_jupyter),
    )


@contextlib.contextmanager
def silent():
    """No progress output."""
    yield None
