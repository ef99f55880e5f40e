"""summary.parquet (one row per job), and the table and failure lines printed at the end of a sweep."""

from __future__ import annotations

import json
import os
import shlex
import signal
import sys
from pathlib import Path

import pandas as pd
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from riskplan.experiments.sweep_worker import foreign_run, is_finished, read_status, refusal, repeats_line
from riskplan.experiments.sweeping.grid import ParsedOnce
from riskplan.experiments.sweeping.jobs import SUMMARY, Job, Outcome
from riskplan.run.columns import frame_to_parquet
from riskplan.run.evaluation import degenerate_findings
from riskplan.run.run_files import SUMMARY as RUN_SUMMARY
from riskplan.util import lock
from riskplan.util.errors import one_line
from riskplan.util.paths import atomic_path

FIGURES = ("mean", "cvar", "value_at_risk")


EXTRA_CVARS = ("cvar_0.05", "cvar_0.1", "cvar_0.2")


def summarize(jobs: list[Job]):
    """One row per job: its overrides as columns, final figures with 95% intervals, wall time, status, error,
    `degenerate` (the run's degenerate findings, riskplan.run.evaluation.diagnose, as "check: message" lines, or
    None), and `duplicate_of`: for a finished job whose config and seed repeat an earlier finished job's (the same
    `run_identity`, as two trials of an optimiser that drew the same values), that job's name (one sample), else
    None."""
    rows = []
    first_done: dict[str, str] = {}  # run identity -> the first finished job of it
    parse = ParsedOnce()
    for job in jobs:
        row: dict = {"job": job.name}
        row.update(_override_columns(job.overrides, parse))
        state, error, status, summary = _job_state(job)
        row.update(_figures(summary or {}))
        row["wall_time"] = (
            float(status["seconds"])
            if status and state == "done" and isinstance(status.get("seconds"), (int, float))
            else float("nan")
        )
        row["train_time"] = (summary or {}).get("wall_time", float("nan"))
        row["status"] = state
        row["error"] = error
        row["degenerate"] = (
            "\n".join(f"{f['check']}: {f['message']}" for f in degenerate_findings(summary or {})) or None
        )
        row["duplicate_of"] = None
        if state == "done" and job.sha:
            first = first_done.setdefault(job.sha, job.name)
            row["duplicate_of"] = first if first != job.name else None
        row["path"] = str(job.path) if job.path is not None else None
        rows.append(row)
    return _table(rows)


def _job_state(job: Job) -> tuple[str, str | None, dict | None, dict | None]:
    """A job's state, its error, its status.json and its summary.json (None when it has none, or another process
    owns its folder)."""
    status = read_status(job.path) if job.path is not None else None
    holder = lock.holder(job.path) if job.path is not None else None
    if holder is not None and holder != os.getpid():  # whatever its status says, that process owns it now
        error = f"running in another process (pid {holder or 'unknown'}); re-run the sweep when that process has ended"
        return "running", error, None, None
    if job.path is None or status is None:
        return "not run", job.invalid or "not started: the sweep stopped before it", status, None
    if status.get("config_sha") != job.sha:
        problem = foreign_run(job.path, job.sha, status)
        if problem is not None:  # the job left the folder to that run: a failure of this launch's
            return "failed", refusal(job.path, problem), status, None
        return "not run", "its folder holds a failed run of another config", status, None
    if status.get("status") == "done" and is_finished(job.path, job.sha, status):
        try:
            return "done", None, status, json.loads((job.path / RUN_SUMMARY).read_text())
        except (OSError, ValueError) as err:
            return "failed", f"unreadable summary.json: {err}", status, None
    if status.get("status") == "done":
        return "failed", "finished, but some of its files are missing or unreadable; re-run the sweep", status, None
    if status.get("status") == "running":
        return "interrupted", "killed while running; re-run the sweep to resume it", status, None
    if status.get("status") == "interrupted":  # a signal stopped it after a checkpoint (Ctrl-C, preemption)
        return "interrupted", f"{status.get('error')}; re-run the sweep to resume it", status, None
    return "failed", status.get("error") or "no error recorded", status, None


def _figures(summary: dict) -> dict:
    """A job's final figures with their intervals, its level, risky fraction and sources reached (NaN without)."""
    row = {}
    for name in FIGURES:
        figure = summary.get(name) or {}
        row[name] = figure.get("value", float("nan"))
        row[f"{name}_low"] = figure.get("low", float("nan"))
        row[f"{name}_high"] = figure.get("high", float("nan"))
    for name in EXTRA_CVARS:
        row[name] = (summary.get(name) or {}).get("value", float("nan"))
    row["beta"] = summary.get("beta", float("nan"))
    row["risky_fraction"] = summary.get("risky_fraction", float("nan"))
    reached = summary.get("source_reached") or {}
    for name, value in reached.items() if isinstance(reached, dict) else ():
        row[f"reached_{name}"] = value
    return row


def _table(rows: list[dict]):
    """The rows as a frame: the sources reached right after risky_fraction, mixed columns as text."""
    frame = pd.DataFrame(rows)
    reached = [c for c in frame.columns if str(c).startswith("reached_")]
    if reached:  # right after risky_fraction, whichever job first had them
        rest = [c for c in frame.columns if c not in reached]
        at = rest.index("risky_fraction") + 1
        frame = frame[rest[:at] + reached + rest[at:]]
    for column in frame.columns:  # a column mixing numbers and text is stored as text
        kinds = {type(v) for v in frame[column] if v is not None and v == v}
        if len(kinds) > 1 and not kinds <= {int, float, bool}:
            frame[column] = frame[column].map(lambda v: None if v is None else str(v))
    return frame


def _override_columns(overrides: list[str], parse: ParsedOnce | None = None) -> dict:
    """{key: value} of a job's overrides; numbers stay numbers, lists and dicts become their JSON text."""
    out = {}
    for o in (parse or ParsedOnce())(overrides):
        value = o.value()
        if isinstance(value, (list, dict)):
            value = json.dumps(value)
        elif value is not None and not isinstance(value, (int, float, bool, str)):
            value = str(value)
        out[o.key_or_group] = value
    return out


def write_summary(frame, path: Path) -> None:
    """Write summary.parquet atomically (no half file, and no temp file left on a full disk)."""
    with atomic_path(path) as tmp:
        frame_to_parquet(frame, tmp)


def varying_columns(frame) -> list[str]:
    """The override columns whose value differs between jobs (all of them if none differs)."""
    fixed = {
        "job",
        "trial",
        "status",
        "error",
        "degenerate",
        "duplicate_of",
        "path",
        "beta",
        "wall_time",
        "train_time",
        "risky_fraction",
        *EXTRA_CVARS,
        *[f"{n}{s}" for n in FIGURES for s in ("", "_low", "_high")],
    }
    overrides = [c for c in frame.columns if c not in fixed and not str(c).startswith("reached_")]
    varying = [c for c in overrides if frame[c].astype(str).nunique() > 1]
    return varying or overrides[:3]


def print_table(frame, title: str, limit: int = 40) -> None:
    """The summary as a terminal table (the varying overrides, status, figures with intervals, wall time)."""
    table = Table(title=title, title_justify="left", show_edge=False, pad_edge=False)
    keys = (["trial"] if "trial" in frame.columns else []) + varying_columns(frame)
    reached = [c for c in frame.columns if str(c).startswith("reached_")]
    for key in keys:
        table.add_column(escape(one_line(str(key))), no_wrap=True)
    table.add_column("status", no_wrap=True)
    for label in ("mean [95% CI]", "CVaR [95% CI]", "VaR"):
        table.add_column(label, justify="right", no_wrap=True)
    for column in reached:
        table.add_column(escape(one_line(str(column))), justify="right", no_wrap=True)
    table.add_column("wall s", justify="right", no_wrap=True)
    for values in frame.head(limit).to_dict("records"):
        cells = [escape(one_line(str(values[k]))) for k in keys]  # a value is text, never markup
        status = values["status"]
        if status != "done":
            cells.append(f"[red]{status}[/red]")
        elif isinstance(values.get("duplicate_of"), str):  # the same sample as an earlier job: counted once
            cells.append("[yellow]duplicate[/yellow]")
        elif isinstance(values.get("degenerate"), str):  # it learned something degenerate: the lines below say what
            cells.append("[yellow]degenerate[/yellow]")
        else:
            cells.append(status)
        for name in ("mean", "cvar"):
            v, lo, hi = values[name], values[f"{name}_low"], values[f"{name}_high"]
            cells.append("" if v != v else f"{v:.1f} [{lo:.1f}, {hi:.1f}]")
        var = values["value_at_risk"]
        cells.append("" if var != var else f"{var:.1f}")
        for column in reached:
            share = values[column]
            cells.append("" if share is None or share != share else f"{share:.0%}")
        wall = values["wall_time"]
        cells.append("" if wall != wall else f"{wall:.1f}")
        table.add_row(*cells)
    console = Console() if sys.stdout.isatty() else Console(width=250)
    console.print(table)
    if len(frame) > limit:
        console.print(f"... {len(frame) - limit} more rows in {SUMMARY}")


def report_outcome(outcome: Outcome, title: str = "sweep", hint: bool = True) -> int:
    """Print the summary table and the failures; return the exit code (0, or 1 when a job failed, 128 + the
    signal when one stopped the sweep). `hint`: say how to retry or resume (the caller does otherwise)."""
    print_table(outcome.summary, f"{title}: {outcome.sweep_dir}")
    repeats = outcome.summary["duplicate_of"].notna().sum() if "duplicate_of" in outcome.summary else 0
    if repeats:
        what = "trial" if outcome.optimiser else "job"
        typer.echo(
            f"warning: {repeats_line(int(repeats), f'{SUMMARY} names the {what} each repeats in duplicate_of', what)}",
            err=True,
        )
    degenerate = outcome.summary.dropna(subset=["degenerate"]) if "degenerate" in outcome.summary else ()
    if len(degenerate):
        typer.echo(f"warning: {len(degenerate)} of {len(outcome.summary)} runs learned something degenerate:", err=True)
        for job, lines in zip(degenerate["job"], degenerate["degenerate"]):
            for line in lines.splitlines():
                typer.echo(f"  {job}: {line}", err=True)
    typer.echo(
        f"summary: {outcome.sweep_dir / SUMMARY} ({outcome.ran} launched, {outcome.skipped} skipped, "
        f"{outcome.seconds:.1f} s)"
    )
    if outcome.best:
        typer.echo(outcome.best)
    if outcome.interrupted is not None and not hint:  # the caller says how to resume (riskplan reproduce)
        return 128 + outcome.interrupted
    if outcome.interrupted is not None:  # one line: what stopped it, and the command that resumes it
        stopped = sum(1 for _, error in outcome.failed)
        typer.echo(
            f"error: interrupted by {signal.Signals(outcome.interrupted).name}: {stopped} job"
            f"{'' if stopped == 1 else 's'} did not finish (each keeps its last checkpoint); resume with riskplan "
            f"sweep {shlex.join(outcome.command)}",
            err=True,
        )
        return 128 + outcome.interrupted
    if outcome.launcher_error:
        typer.echo(f"error: {outcome.launcher_error}", err=True)
    if outcome.failed:
        typer.echo(
            f"error: {len(outcome.failed)} of {len(outcome.summary)} "
            f"{'trials' if outcome.optimiser else 'jobs'} did not finish:",
            err=True,
        )
        for name, error in outcome.failed:
            typer.echo(f"  {name}: {error}", err=True)
    if hint and not outcome.ok and outcome.command:
        what = (
            "to run the study again in this directory (a trial that draws the values of a finished one, as "
            "with a seeded sampler, is skipped)"
            if outcome.optimiser
            else "to retry the jobs that did not finish (finished ones are skipped)"
        )
        typer.echo(f"{what}: riskplan sweep {shlex.join(outcome.command)}", err=True)
    return 0 if outcome.ok else 1
