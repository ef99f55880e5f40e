"""`riskplan sweep`: a grid of experiments through a Hydra launcher (the work is riskplan.sweeping's)."""

from __future__ import annotations

from typing import List, Optional

import typer

from riskplan.commands.common import PASS_THROUGH, bad_input_exits
from riskplan.sweeping import SWEEP_HELP, report_outcome, run_sweep


def register(app: typer.Typer) -> None:
    """Add `sweep` to the riskplan app."""
    @app.command(context_settings=PASS_THROUGH)
    @bad_input_exits
    def sweep(
        overrides: Optional[List[str]] = typer.Argument(None, help=SWEEP_HELP, show_default=False),
        jobs: Optional[int] = typer.Option(None, "--jobs", "-j", min=1, show_default=False,
                                           help="Jobs at once: joblib workers (default: the number of cores), or "
                                                "submitit's array_parallelism."),
    ) -> None:
        """Run a grid of experiments (a Hydra multirun) into outputs/sweeps/<timestamp>/, one folder per job."""
        outcome = run_sweep(list(overrides or []), jobs)
        raise typer.Exit(report_outcome(outcome))
