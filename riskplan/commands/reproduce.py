"""`riskplan reproduce`: every experiment of the paper's Section V, then the report (the work is riskplan.experiments.reproduction's)."""

from __future__ import annotations

import typer

from riskplan.commands.common import PASS_THROUGH, bad_input_exits, check_out_dir, jobs_option

# --seeds' defaults, here rather than in riskplan.experiments.reproduction: --help does not import it
SEEDS = 10
QUICK_SEEDS = 2


def register(app: typer.Typer) -> None:
    """Add `reproduce` to the riskplan app."""
    app.command("reproduce", context_settings=PASS_THROUGH)(bad_input_exits(reproduce_command))


def reproduce_command(
    overrides: list[str] | None = typer.Argument(
        None,
        show_default=False,
        help="Plain overrides for every experiment (no sweeps), e.g. train.samples=3000 world.horizon=24.",
    ),
    out: str | None = typer.Option(
        None,
        "--out",
        metavar="DIR",
        help="Where to put it (default: outputs/reproduce/<timestamp>/). An "
        "existing reproduction is completed: finished jobs are skipped.",
    ),
    quick: bool = typer.Option(
        False, "--quick", help="Fewer iterations, episodes and seeds: a first look in well under a minute."
    ),
    seeds: int | None = typer.Option(
        None,
        "--seeds",
        min=1,
        show_default=False,
        help=f"Seeds per condition (default {SEEDS}, {QUICK_SEEDS} with --quick).",
    ),
    jobs: int | None = jobs_option(
        "Run the sweeps job by job, this many at once (a worker process per job); without it, each sweep trains "
        "as batches."
    ),
    formats: str = typer.Option("png,pdf", "--format", help="Figure files of the report: any of png,pdf,svg."),
    batch: bool = typer.Option(
        False,
        "--batch",
        help="Train each sweep as batches (riskplan sweep --batch), the default: the same numbers as job by job "
        "(--jobs N), as quick or quicker (docs/sweeps.md).",
    ),
    paper_only: bool = typer.Option(
        False,
        "--paper-only",
        help="Section V alone (Figs. 1-4: single/ and team/), without the studies beyond the paper and the "
        "landscape: about a third of the jobs.",
    ),
) -> None:
    """Run every experiment of the paper's Section V (several seeds each) and the studies beyond it, then the
    report. It says how long it expects to take before it starts, and the stage and overall ETA as it goes."""
    from riskplan.experiments.reproduction import reproduce
    from riskplan.experiments.timing import process_started

    seeds = seeds or (QUICK_SEEDS if quick else SEEDS)
    raise typer.Exit(
        reproduce(
            check_out_dir(out),
            quick,
            seeds,
            jobs,
            formats,
            list(overrides or []),
            since=process_started(),
            paper_only=paper_only,
            batch=True if batch else None,
        )
    )
