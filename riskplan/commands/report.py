"""`riskplan report` (figures, tables and report.html from finished runs) and `riskplan landscape`."""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import math
from pathlib import Path

import typer

from riskplan.commands.common import (
    CONFIG_DIR_HELP,
    INPUT,
    OVERRIDES_HELP,
    PASS_THROUGH,
    bad_input_exits,
    path_option,
    reject_hydra_flags,
    with_config_dirs,
)
from riskplan.experiments.output_manifest import WriteFailed, claim_output
from riskplan.run.run_files import RUN_LOG
from riskplan.util.errors import BadInput, one_line


def parse_floats(text: str, where: str, counts: tuple[int, ...]) -> list[float]:
    """'a,b,...' -> floats, with one of the allowed counts."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if len(values) not in counts:
        raise BadInput(where, f"got '{text}'; expected {' or '.join(str(c) for c in counts)} comma-separated numbers")
    return values


@contextlib.contextmanager
def write_errors_exit():
    """A file that cannot be written at run time (a full disk, ...): one line on stderr and exit code 1."""
    try:
        yield
    except WriteFailed as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(1) from None


def register(app: typer.Typer) -> None:
    """Add `report` and `landscape` to the riskplan app."""
    app.command("report")(bad_input_exits(report))
    app.command("landscape", context_settings=PASS_THROUGH)(bad_input_exits(landscape))


def report(
    paths: list[str] | None = typer.Argument(
        None,
        metavar="DIRS",
        help="Run, sweep, reproduce or landscape directories (searched recursively). "
        "Default: the newest folder in outputs/reproduce/.",
        show_default=False,
    ),
    out: str | None = typer.Option(
        None,
        "--out",
        help="Where to write report.html, report.csv, runs.csv and the figures: a new or empty "
        "directory, or one a previous report wrote (it holds .riskplan-manifest.json). "
        "Default: DIR/report for one input DIR, else outputs/reports/<timestamp>/.",
        metavar="DIR",
    ),
    formats: str = typer.Option("png,pdf", "--format", help="Figure files to write: any of png,pdf,svg."),
) -> None:
    """Figures (the paper's Figs. 1-4 and more), tables and a self-contained report.html from finished runs."""
    from riskplan.experiments.reporting import check_formats, default_out, latest_reproduction, write_report
    from riskplan.util.progress import PhaseBars

    fmts = check_formats(formats)
    inputs = [path_option(p, "DIRS", INPUT) for p in paths] if paths else [latest_reproduction()]
    target = out if out is not None else default_out(inputs)  # a str: an empty --out stays empty, refused
    with write_errors_exit(), PhaseBars() as progress:
        result = write_report(inputs, target, fmts, key="--out", progress=progress)
    _print_report(result)


def _print_report(result) -> None:
    """What `riskplan report` made: the runs skipped or rebuilt, the counts, and the page."""
    collected = result.collection
    for broken in collected.broken:
        typer.echo(f"skipped {broken.path}: {broken.reason}", err=True)
    for r in collected.runs:
        if r.rebuilt:
            typer.echo(f"rebuilt tables of {r.path} from run.mcap")
        if r.log_cut:
            typer.echo(
                f"warning: {r.path / RUN_LOG} is cut short (it lacks the end every finished log has); the run is "
                f"reported from its tables, but Foxglove cannot open the log whole",
                err=True,
            )
    for name, why in result.skipped.items():  # a figure that failed is a fault to see here, not only in the page
        if why.startswith("failed:"):
            typer.echo(one_line(f"warning: figure {name} {why}"), err=True)
    repeats = f", {len(collected.duplicates)} duplicate (counted once)" if collected.duplicates else ""
    typer.echo(
        f"{len(collected.runs)} run(s) in {len(collected.groups)} group(s), {len(collected.landscapes)} landscape(s), "
        f"{len(collected.broken)} skipped{repeats}; {len(result.figures)} figures"
    )
    typer.echo(f"report: {result.page}")


def landscape(
    overrides: list[str] | None = typer.Argument(None, help=OVERRIDES_HELP + CONFIG_DIR_HELP, show_default=False),
    out: str | None = typer.Option(
        None,
        "--out",
        help="Output directory: a new or empty one, or one a previous landscape wrote. Default: "
        "outputs/landscapes/<timestamp>_<experiment>/.",
        metavar="DIR",
    ),
    points: int = typer.Option(41, "--points", help="Grid points per axis."),
    episodes: int = typer.Option(
        4000, "--episodes", help="Episodes per grid point (the same streams at every point: common random numbers)."
    ),
    theta_range: str = typer.Option(
        "-20,60", "--range", help="LO,HI for both axes, or LO,HI,LO,HI. Write --range=-20,60 when LO is negative."
    ),
    axes: str = typer.Option(
        "0,1",
        "--axes",
        help="The two theta components to vary, by index in theta, which lists a weight per entry of "
        "policy.features in its order (signals: one per source); the others stay at train.theta0.",
    ),
) -> None:
    """Evaluate mean and CVaR of the total reward on a grid of two theta components of a features policy (common
    random numbers, seeded)."""
    from riskplan.experiments.landscape import LANDSCAPES_ROOT, check_grid, compute_landscape
    from riskplan.run.build import build_setup
    from riskplan.run.compose import compose, parse_overrides

    args = with_config_dirs(list(overrides or []))
    reject_hydra_flags(args, "riskplan check prints the composed config")
    _check_options(args)
    _check_no_hydra_dirs(parse_overrides(args))
    if points < 2:
        raise BadInput("--points", f"got {points}; expected at least 2 grid points per axis")
    if episodes < 1:
        raise BadInput("--episodes", f"got {episodes}; expected at least 1 episode per grid point")
    if out is not None:
        claim_output(out, "landscape", "--out")  # early: a bad --out is refused before the config is composed
    cfg = compose(args)
    ranges, pair = _theta_ranges(theta_range), _theta_axes(axes)
    check_grid(build_setup(cfg), points, episodes, ranges, pair, typed=theta_range)  # the policy, memory, time
    target = (
        Path(out) if out is not None else (LANDSCAPES_ROOT / f"{dt.datetime.now():%Y-%m-%d_%H-%M-%S}_{cfg.experiment}")
    )
    claim_output(target, "landscape", "--out")
    typer.echo(f"landscape directory: {target}")
    with write_errors_exit():
        path = compute_landscape(
            cfg, target, points=points, episodes=episodes, ranges=ranges, axes=pair, overrides=args, key="--out"
        )
    typer.echo(_landscape_line(json.loads((path / "summary.json").read_text()), points, episodes, path))


def _check_options(args: list[str]) -> None:
    """An option riskplan landscape does not know: typer passes it on among the overrides (PASS_THROUGH)."""
    for arg in args:
        if arg.startswith("-"):
            raise BadInput(
                f"option '{arg}'",
                "is not known to riskplan landscape; give Hydra overrides (key=value) and --out, --points, "
                "--episodes, --range, --axes, -cd",
            )


def _check_no_hydra_dirs(parsed: list) -> None:
    """hydra.run.dir and hydra.sweep.dir: a landscape runs no Hydra job, and --out says where it goes."""
    for override in parsed:
        key = override.key_or_group
        if key.split(".")[:2] in (["hydra", "run"], ["hydra", "sweep"]):
            raise BadInput(
                key,
                "riskplan landscape writes where --out says (default outputs/landscapes/<timestamp>_<experiment>/), "
                "not into Hydra's directories; give --out DIR",
            )


def _theta_ranges(text: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """--range: LO,HI for both axes or LO,HI,LO,HI, finite, with LO < HI on each."""
    bounds = parse_floats(text, "--range", (2, 4))
    ranges = ((bounds[0], bounds[1]), (bounds[-2], bounds[-1]))
    if not all(math.isfinite(v) for v in bounds):
        raise BadInput("--range", f"got '{text}'; expected finite numbers, e.g. --range=-20,60")
    if not all(lo < hi for lo, hi in ranges):
        raise BadInput("--range", f"got '{text}'; expected LO < HI on each axis, e.g. --range=-20,60")
    return ranges


def _theta_axes(text: str) -> tuple[int, int]:
    """--axes: two whole theta indices."""
    pair = parse_floats(text, "--axes", (2,))
    if any(not math.isfinite(v) or v != int(v) for v in pair):
        raise BadInput("--axes", f"got '{text}'; expected two whole theta indices, e.g. 0,1")
    return int(pair[0]), int(pair[1])


def _landscape_line(summary: dict, points: int, episodes: int, path: Path) -> str:
    """The closing line of `riskplan landscape`: the grid, its speed and the best mean and CVaR."""
    best = summary["best"]

    def at(name: str) -> str:
        if best[name]["theta"] is None or best[name]["value"] is None:
            return "n/a (no finite value on the grid)"
        theta = ", ".join(f"{t:g}" for t in best[name]["theta"])
        return f"{best[name]['value']:.1f} at theta=({theta})"

    rate = f"{summary['episodes_per_s'] / 1e6:.2f} M" if summary.get("episodes_per_s") is not None else "n/a"
    return (
        f"{points}x{points} grid x {episodes} episodes in {summary['seconds']:.2f} s "
        f"({rate} episodes/s): max mean {at('mean')}; "
        f"max CVaR_{summary['beta']:g} {at('cvar')} -> {path}"
    )
