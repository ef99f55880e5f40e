"""`riskplan sweep`: a grid of experiments through a Hydra launcher (the work is riskplan.experiments.sweeping's)."""

from __future__ import annotations

import typer

from riskplan.commands.common import CONFIG_DIR_HELP, PASS_THROUGH, bad_input_exits, jobs_option, with_config_dirs

# help texts are rich markup: "\\[" keeps a bracket that rich would take for a style tag ([optuna], [file://DIR])
SWEEP_HELP = (
    "Hydra overrides; comma lists and range(...) sweep, e.g. risk.beta=0.05,0.1,0.2 'seed=range(0,5)' "
    "team.graph=line,ring. hydra/launcher=submitit_slurm|submitit_local|ray selects a cluster launcher "
    "(default: joblib on local cores); hydra.sweep.dir=DIR re-runs a sweep into DIR, skipping the jobs "
    "that finished. hydra/sweeper=optuna 'risk.beta=interval(0.05,1)' hydra.sweeper.n_trials=12 runs "
    "an Optuna study instead of a grid (pip install 'riskplan\\[optuna]'); its trials return their CVaR."
)


def register(app: typer.Typer) -> None:
    """Add `sweep` to the riskplan app."""

    @app.command(context_settings=PASS_THROUGH)
    @bad_input_exits
    def sweep(
        overrides: list[str] | None = typer.Argument(None, help=SWEEP_HELP + CONFIG_DIR_HELP, show_default=False),
        jobs: int | None = jobs_option(
            "Run job by job, this many at once: joblib workers, or submitit's array_parallelism; with "
            "--batch on a cluster (SLURM, Ray), at least this many tasks, each a batch."
        ),
        batch: bool = typer.Option(
            False,
            "--batch",
            help="Train the jobs that share a world and sample schedule as one program, one kernel call per "
            "iteration over all their robots (every core): the default without --jobs or a launcher. The same "
            "folders and files, bit for bit the same numbers as job by job. Seeds, risk levels and parameters, step sizes, theta0 and graphs may differ. "
            "With hydra/launcher=submitit_slurm, submitit_local, ray or ray_cluster: a chunk of the runs per task.",
        ),
    ) -> None:
        """Run a grid of experiments (a Hydra multirun) into outputs/sweeps/<timestamp>/, one folder per job."""
        from riskplan.experiments.sweeping import report_outcome, run_sweep  # here: `riskplan train` starts without it
        from riskplan.run.compose import check_extras

        args = with_config_dirs(list(overrides or []))
        check_extras(args)  # a launcher, sweeper or team.backend whose extra is missing: before any folder
        outcome = run_sweep(args, jobs, batch=True if batch else None)  # None: batches unless --jobs or a launcher
        raise typer.Exit(report_outcome(outcome))
