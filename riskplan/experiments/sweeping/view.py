"""One live view of a running sweep, redrawn from the jobs' status files."""

from __future__ import annotations

import datetime as dt
import json
import os
import sys
import threading
import time
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from riskplan.experiments.sweeping.jobs import Job, job_state, locate


class SweepView:
    """One live line for a running sweep (done / running / failed / ETA), redrawn from the jobs' status files.

    On a terminal it is a rich progress bar; otherwise (CI, a pipe) one line per finished job. It writes to a
    duplicate of stderr taken before launch, so it stays on the terminal even while a job runs in this process
    and sends its own output to its folder.
    """

    def __init__(
        self,
        sweep_dir: Path,
        jobs: list[Job],
        finished: set[int],
        title: str,
        every: float = 0.5,
        total: int | None = None,
        discover=None,
        batch_progress: str | None = None,
    ):
        self.sweep_dir, self.jobs, self.finished, self.title, self.every = sweep_dir, jobs, finished, title, every
        self.todo = [i for i in range(len(jobs)) if i not in finished]
        self.discover = discover  # an optimiser's trials: found as the sweeper launches them (discover(since))
        self.total = total
        self.batch_progress = batch_progress  # a batched sweep's progress files' prefix (sweeping.batched.PROGRESS)
        self.reported: set[int] = set()
        self.stop = threading.Event()

    def __enter__(self):
        sys.stderr.flush()
        self.stream = os.fdopen(os.dup(2), "w", buffering=1)
        self.tty = self.stream.isatty()
        self.console = Console(file=self.stream, force_terminal=self.tty or None)
        self.since = time.time()
        self.bar = None
        if self.tty:
            self.bar = Progress(
                TextColumn(f"[bold]{self.title}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[state]}"),
                TimeElapsedColumn(),
                TextColumn("{task.fields[eta]}"),
                console=self.console,
                transient=False,
            )
            self.bar.__enter__()
            self.task = self.bar.add_task(self.title, total=self._total(), state="", eta="")
        self.thread = threading.Thread(target=self._loop, name="riskplan-sweep-view", daemon=True)
        self.thread.start()
        return self

    def _loop(self) -> None:
        while not self.stop.wait(self.every):
            self.refresh()

    def _total(self) -> int:
        return max(self.total or 0, len(self.todo))

    def refresh(self) -> None:
        """Read the jobs' status files and redraw."""
        try:
            if self.discover is not None:
                known = {job.path for job in self.jobs}
                for job in self.discover(self.since):
                    if job.path not in known:
                        self.jobs.append(job)
                        self.todo.append(len(self.jobs) - 1)
            if any(self.jobs[i].path is None for i in self.todo):
                locate(self.sweep_dir, self.jobs)
            counts = {"pending": 0, "running": 0, "done": 0, "failed": 0}
            for i in self.todo:
                state, status = job_state(self.jobs[i], self.since)
                counts[state] += 1
                if state in ("done", "failed") and i not in self.reported:
                    self.reported.add(i)
                    self._finished_line(i, state, status)
            ended = counts["done"] + counts["failed"]
            elapsed = time.time() - self.since
            done, total = self._iterations()
            if total:  # a batch: its runs end together, so its iterations measure progress
                completed = self._total() * done / total
            else:
                completed, done, total = ended, ended, self._total()
            eta = f"ETA {dt.timedelta(seconds=round(elapsed / done * (total - done)))}" if 0 < done < total else ""
            state = f"running {counts['running']} · failed {counts['failed']}" + (
                f" · skipped {len(self.finished)} finished before" if self.finished else ""
            )
            if self.bar is not None:
                self.bar.update(self.task, completed=completed, total=self._total(), state=state, eta=eta)
        except Exception:
            pass

    def _iterations(self) -> tuple[int, int]:
        """A batched sweep's iterations done and in all, summed over its parts' files (0, 0 otherwise)."""
        if self.batch_progress is None:
            return 0, 0
        done, total = 0, 0
        for part in self.sweep_dir.glob(f"{self.batch_progress}.*.json"):
            try:
                if part.stat().st_mtime < self.since - 2:
                    continue
                record = json.loads(part.read_text())
                done, total = done + int(record["done"]), max(total, int(record["total"]))
            except (OSError, ValueError, KeyError, TypeError):
                continue
        return done, total

    def _finished_line(self, i: int, state: str, status: dict | None) -> None:
        job = self.jobs[i]
        seconds = (status or {}).get("seconds")
        took = f" ({seconds:.1f} s)" if isinstance(seconds, (int, float)) else ""
        if state == "failed":
            line = f"[red]failed[/red] {escape(job.shown)}: {escape(str((status or {}).get('error')))}"
        else:
            line = f"done {escape(job.shown)}{took}"
        if self.bar is not None:
            if state == "failed":
                self.bar.console.print(line, markup=True, highlight=False)
        else:
            self.console.print(
                f"[{len(self.reported)}/{self._total()}] {line}", markup=True, highlight=False, soft_wrap=True
            )

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()
        self.refresh()
        if self.bar is not None:
            self.bar.__exit__(*exc)
        self.stream.close()
        return False
