"""Terminal progress for long work (rich), kept out of the computing code."""

from __future__ import annotations

import contextlib
import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

console = Console(stderr=True)


class TrainingBar:
    """Iteration bar showing the latest mean and CVaR; a context manager yielding the progress callback."""

    def __enter__(self):
        self._bar = Progress(
            TextColumn("[bold]train"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[stats]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=console,
            transient=True,
            disable=not (sys.stderr.isatty() or console.is_jupyter),  # a live bar on a terminal or in a notebook
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


@contextlib.contextmanager
def silent():
    """No progress output."""
    yield None
