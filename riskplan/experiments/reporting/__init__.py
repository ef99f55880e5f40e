"""`riskplan report`: figures, tables, the objective landscape and a self-contained report.html.

    build_report([Path("outputs/sweeps/...")], Path("report"), ["png", "pdf"]) -> Path("report/report.html")

The figures follow what differs between the groups of runs (one curve per β of a β sweep); they are the paper's
Figs. 1-4, under its titles, only for a reproduction's runs (reporting.figures). The report reads the runs' tables
(parquet, or rebuilt from run.mcap when missing) and never re-simulates. Broken or partial runs are listed with
the reason and skipped; a path holding no run at all is BadInput. A run whose config and seed repeat another's is
the same sample: it is counted once, listed in runs.csv as `duplicate`, with one warning.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from riskplan.experiments.output_manifest import Output, WriteFailed, claim_output
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.reporting.figures import figure_files, make_figures
from riskplan.experiments.reporting.page import render
from riskplan.experiments.reporting.parallel import Progress, sharing
from riskplan.experiments.reporting.study_tables import study_tables
from riskplan.experiments.reporting.tables import (
    comparison_table,
    csv_text,
    landscape_table,
    runs_table,
    soft_risk_table,
)
from riskplan.experiments.sweep_worker import repeats_line
from riskplan.run.results import find_runs
from riskplan.util.errors import BadInput

FORMATS = ("png", "pdf", "svg")
DEFAULT_FORMATS = ("png", "pdf")
PHASES = ("loading runs", "making figures", "drawing figures")  # what a report's progress hears, in order
PhaseProgress = Callable[[str, int, int], None]  # progress(phase, done, total)

REPRODUCE_ROOT = Path("outputs") / "reproduce"  # where riskplan reproduce claims its folders
REPORTS_ROOT = Path("outputs") / "reports"


def latest_reproduction(root: Path = REPRODUCE_ROOT) -> Path:
    """The newest folder in outputs/reproduce/ (names are timestamps; ties broken by modification time)."""
    folders = [p for p in root.iterdir() if p.is_dir()] if root.is_dir() else []
    if not folders:
        raise BadInput(
            str(root),
            "holds no reproduction; run `riskplan reproduce` first or give run or sweep "
            "directories: riskplan report DIR...",
        )
    return max(folders, key=lambda p: (p.name, p.stat().st_mtime))


def default_out(paths: list[Path]) -> Path:
    """<path>/report for one input path, else outputs/reports/<timestamp>/."""
    if len(paths) == 1:
        return paths[0] / "report"
    return REPORTS_ROOT / dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def check_formats(formats: list[str] | str, key: str = "--format") -> list[str]:
    """Normalise and validate figure formats ('png,pdf' or a list); `key` names them in a message."""
    if isinstance(formats, str):
        formats = formats.split(",")
    out = [f.strip().lower().lstrip(".") for f in formats if f.strip()]
    bad = [f for f in out if f not in FORMATS]
    if bad or not out:
        raise BadInput(
            key,
            f"got {','.join(formats) or 'nothing'}; expected a comma-separated subset of "
            f"{','.join(FORMATS)}, e.g. png,pdf",
        )
    return list(dict.fromkeys(out))


@dataclass
class Report:
    """What write_report made: the page, the collection it drew from, the figure names and those not drawn."""

    page: Path
    collection: object  # riskplan.experiments.reporting.collect.Collection
    figures: list[str]
    skipped: dict[str, str]


def build_report(
    paths: list[Path],
    out_dir: Path,
    formats: list[str] = DEFAULT_FORMATS,
    key: str = "out_dir",
    progress: PhaseProgress | None = None,
) -> Path:
    """Find the runs under `paths`, write figures, report.csv, runs.csv and report.html to out_dir; return the page.

    Raises BadInput (before writing anything) for a path that holds no run, for an unknown format, or for an
    out_dir riskplan may not write into (see riskplan.experiments.output_manifest; `key` names it in the message). Raises
    WriteFailed (an OSError, one line) when a file cannot be written: every file is written atomically.
    `progress(phase, done, total)` hears how far each long phase has come: the runs loaded (PHASES[0]), the
    figures made (PHASES[1]) and drawn (PHASES[2]); e.g. riskplan.util.progress.PhaseBars on a terminal.
    """
    return write_report(paths, out_dir, formats, key, progress).page


def check_reportable(collected, paths: list[Path]) -> None:
    """BadInput, before anything is written, when the paths hold runs but none that can be reported (each running,
    killed before its first checkpoint, or damaged) and no landscape: a report of nothing would exit 0."""
    if collected.runs or collected.landscapes or collected.studies:
        return
    first = collected.broken[0]
    more = f" ({len(collected.broken) - 1} more skipped)" if len(collected.broken) > 1 else ""
    again = f"; {first.remedy}, then report it" if first.remedy else ""  # a damaged run's reason says what to do
    raise BadInput(
        ", ".join(str(p) for p in paths), f"holds no run that can be reported: {first.path} {first.reason}{more}{again}"
    )


def write_report(
    paths: list[Path],
    out_dir: Path,
    formats: list[str] = DEFAULT_FORMATS,
    key: str = "out_dir",
    progress: PhaseProgress | None = None,
) -> Report:
    """build_report, returning what was made (for the CLI's listing)."""
    tell = progress or (lambda phase, done, total: None)
    formats = check_formats(list(formats))
    find_runs([Path(p) for p in paths])  # the inputs first (a missing path, one without runs), then --out
    previous = claim_output(out_dir, "report", key)  # before reading any run: a bad --out is refused at once
    output = Output(out_dir, "report", previous)
    # An existing out_dir is locked from the start: a second report into it is refused now, not after its work. A
    # new one is made (and locked) only as the report writes, so bad input leaves the inputs untouched; a second
    # report into it meanwhile is refused then, its files never mixed (Output's check under the lock).
    with output.locked() if Path(out_dir).is_dir() else contextlib.nullcontext():
        return _report(paths, output, formats, tell)


def _report(paths: list[Path], output: Output, formats: list[str], tell: PhaseProgress) -> Report:
    """The report's work into `output`, whose lock the caller holds."""
    collected = collect([Path(p) for p in paths], functools.partial(tell, PHASES[0]))
    check_reportable(collected, paths)
    if collected.duplicates:  # one line (the CLI shows warnings as `warning: ...`); runs.csv names each
        warnings.warn(repeats_line(len(collected.duplicates), "runs.csv lists them as duplicate"), stacklevel=3)
    specs, skipped = make_figures(collected, functools.partial(tell, PHASES[1]))
    with _drawing(
        specs, formats, skipped, functools.partial(tell, PHASES[2])
    ) as figures:  # forked children draw while this process makes the tables
        comparison = comparison_table(collected)
        _warn_degenerate(comparison)
        runs = runs_table(collected)
        landscapes = landscape_table(collected)
        soft = soft_risk_table(collected)
        studies = collect_studies(collected, study_tables)
    csvs = {"report.csv": comparison, "runs.csv": runs}  # always; the others where they hold rows
    optional = {"landscape.csv": landscapes, "soft_risk.csv": soft, **{f"{n}.csv": t for n, t in studies.items()}}
    csvs.update({name: table for name, table in optional.items() if not table.empty})
    with output.writing(
        [f"{spec.name}.{fmt}" for spec, _ in figures for fmt in formats] + list(csvs) + ["report.html"]
    ):
        for spec, files in figures:
            for fmt in formats:
                output.write(f"{spec.name}.{fmt}", files[fmt])
        for name, table in csvs.items():
            output.write(name, csv_text(table))
        output.write("report.html", render(collected, figures, skipped, comparison, runs, landscapes, soft, studies))
    return Report(output.out / "report.html", collected, [spec.name for spec, _ in figures], skipped)


def _warn_degenerate(comparison: pd.DataFrame) -> None:
    """One warning line for the groups that learned something degenerate; report.csv and the page say what and why
    (stacklevel 4: the caller of write_report, as for its own warning)."""
    degenerate = comparison["degenerate"].dropna() if "degenerate" in comparison else []
    if len(degenerate):
        warnings.warn(
            f"{len(degenerate)} group(s) learned something degenerate ({', '.join(comparison.group[degenerate.index])}):"
            " report.csv's degenerate column and the page say what and the likely cause",
            stacklevel=4,
        )


@contextlib.contextmanager
def _drawing(specs: list, formats: list[str], skipped: dict[str, str], progress: Progress) -> Iterator[list[tuple]]:
    """Every figure drawn to bytes on all CPUs (a figure's size is a fair guess of its cost): forked children start
    on entering, this process joins them on leaving, and the list yielded then holds (spec, {format: bytes}) of
    each drawn; one that failed goes into `skipped` with its reason."""
    figures: list[tuple] = []
    try:
        with sharing(
            lambda spec: figure_files(spec, formats),
            specs,
            cost=lambda spec: spec.figure.get_size_inches().prod(),
            progress=progress,
        ) as drawn:
            yield figures
    finally:
        for spec in specs:
            spec.figure.clear()
    for spec, files in zip(specs, drawn):
        if isinstance(files, str):
            skipped[spec.name] = files
        else:
            figures.append((spec, files))


def collect_studies(collected, tables) -> dict:
    """The studies' tables (name -> DataFrame, empty when absent): those of reproduce's study folders, and any the
    main runs hold themselves (a sweep over risk measures given to riskplan report), one table per study."""
    out = {}
    own = tables(collected)
    for name, table in own.items():
        parts = [table] + [tables(s.collection)[name] for s in collected.studies if s.name == name]
        parts = [t for t in parts if not t.empty]
        out[name] = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    return out


__all__ = [
    "DEFAULT_FORMATS",
    "FORMATS",
    "PHASES",
    "Report",
    "WriteFailed",
    "build_report",
    "check_formats",
    "write_report",
]
