"""`riskplan export`: finished runs into MLflow or TensorBoard, or a Foxglove layout into each run directory."""

from __future__ import annotations

import functools

import typer

from riskplan.commands.common import INPUT, bad_input_exits, path_option
from riskplan.util.errors import BadInput


def register(app: typer.Typer) -> None:
    """Add `riskplan export` to the CLI."""
    app.command("export")(bad_input_exits(export))


def export(
    paths: list[str] | None = typer.Argument(
        None, metavar="DIRS", help="Run, sweep or reproduce directories (searched recursively).", show_default=False
    ),
    to: str | None = typer.Option(
        None,
        "--to",
        help="mlflow (a tracking store), tensorboard (event files), foxglove "
        "(foxglove_layout.json into each run directory) or ros2 (a rosbag2 directory per run).",
        show_default=False,
    ),
    uri: str | None = typer.Option(
        None,
        "--uri",
        help="mlflow: a tracking URI (sqlite:///mlflow.db, http://host:5000) or a file store "
        "directory, default outputs/mlruns; tensorboard: the log directory, default "
        "outputs/tensorboard; foxglove: none.",
        show_default=False,
    ),
    experiment: str = typer.Option("riskplan", "--experiment", help="The MLflow experiment to log into."),
    out: str | None = typer.Option(
        None,
        "--out",
        help="ros2: the folder for the bags, one rosbag2 directory per run (default: rosbag2/ inside each run "
        "directory).",
        show_default=False,
    ),
) -> None:
    """Replay finished runs into MLflow or TensorBoard: metrics per iteration and robot, the summary with its
    intervals, the config as parameters, seed groups as tags. A run exported before is replaced when it
    changed and left as it is otherwise; broken runs are skipped with their reason, and a run repeating another's
    config and seed is exported once."""
    from riskplan.experiments.exporting import ExportFailed, export_runs
    from riskplan.experiments.reporting import PHASES
    from riskplan.util.progress import PhaseBars

    def echo(done) -> None:
        typer.echo(f"{done.action} {done.path} -> {done.where}")

    uri = _destination(to, uri, experiment, out)
    try:
        with PhaseBars() as progress:
            loading = functools.partial(progress, PHASES[0])
            inputs = [path_option(p, "DIRS", INPUT) for p in paths or []]
            result = export_runs(inputs, to, uri, experiment=experiment, echo=echo, progress=loading)
    except ExportFailed as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(1) from None
    _print_export(result, experiment)


def _destination(to: str | None, uri: str | None, experiment: str, out: str | None) -> str | None:
    """The options checked together; the URI to export to (ros2 takes --out for it, the others --uri)."""
    if not experiment.strip():
        raise BadInput("--experiment", f"got {experiment!r}; give an MLflow experiment name, e.g. riskplan")
    target = (to or "").strip().lower()
    ros2 = target == "ros2"
    if out is not None and not ros2:
        others = (
            "--to foxglove writes into each run directory"
            if target == "foxglove"
            else "mlflow and tensorboard take --uri"
        )
        raise BadInput("--out", f"only --to ros2 writes into --out; {others}")
    if ros2 and uri is not None:
        raise BadInput("--uri", "--to ros2 writes its bags into --out DIR (default: each run directory)")
    return str(path_option(out, "--out")) if ros2 and out is not None else uri


def _print_export(result, experiment: str) -> None:
    """The runs skipped or repeated, then one line counting what was exported where."""
    for broken in result.skipped:
        typer.echo(f"skipped {broken.path}: {broken.reason}", err=True)
    for repeat in result.duplicates:
        typer.echo(
            f"duplicate {repeat.path}: the same config and seed as {repeat.of.path}; not exported (one sample)",
            err=True,
        )
    where = result.destination + (f" (experiment {experiment})" if result.target == "mlflow" else "")
    repeats = f", {len(result.duplicates)} duplicate" if result.duplicates else ""
    typer.echo(
        f"{len(result.done)} run(s) to {result.target}: {result.count('exported')} exported, "
        f"{result.count('replaced')} replaced, {result.count('unchanged')} unchanged, "
        f"{len(result.skipped)} skipped{repeats} -> {where}"
    )
    if result.skipped and not result.done:  # every run skipped: an export of nothing is no success
        typer.echo(f"error: no run was exported: each of the {len(result.skipped)} was skipped (see above)", err=True)
        raise typer.Exit(1)
