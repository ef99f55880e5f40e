"""`riskplan check`: compose and validate a config, run nothing; print it, the world, the team and Assumptions 5-6."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from riskplan.commands.common import (
    CONFIG_DIR_HELP,
    OVERRIDES_HELP,
    PASS_THROUGH,
    bad_input_exits,
    reject_hydra_flags,
    with_config_dirs,
)
from riskplan.util.errors import BadInput
from riskplan.util.paths import check_output_file


def register(app: typer.Typer) -> None:
    """Add `check` to the riskplan app."""
    app.command(context_settings=PASS_THROUGH)(bad_input_exits(check))


def check(
    overrides: list[str] | None = typer.Argument(None, help=OVERRIDES_HELP + CONFIG_DIR_HELP, show_default=False),
    draw: str | None = typer.Option(
        None,
        "--draw",
        metavar="PATH",
        help="Also draw the world to PATH (.png, .svg or .pdf): obstacles, unknown cells, regions, sources and their "
        "signals, the starts, the cells reachable within the horizon, and a shortest path to each source.",
    ),
) -> None:
    """Compose and validate a config without running it; print it, the world, the team and Assumptions 5-6."""
    from omegaconf import OmegaConf

    from riskplan.engine.team.describe import describe
    from riskplan.run.build import build_setup
    from riskplan.run.compose import compose

    args = with_config_dirs(list(overrides or []))
    reject_hydra_flags(args, "check prints the composed config itself")
    if draw is not None:  # matplotlib only when asked to draw: check stays fast without it
        from riskplan.experiments.reporting.figures.world_picture import draw_format

        draw = check_output_file(draw, "--draw", ".png, .svg or .pdf")
        _check_replaceable(draw, draw_format(draw))
    cfg = compose(args, validate=False)
    try:
        setup = build_setup(cfg)
    except BadInput as err:
        if draw is None:
            raise
        from riskplan.experiments.reporting.figures.world_picture import map_drawn_instead

        raise map_drawn_instead(cfg, draw, err) from None
    typer.echo(OmegaConf.to_yaml(cfg).rstrip())
    typer.echo("")
    typer.echo(_describe_world(setup))
    power = cfg.train.step_size.power
    holds = 0.5 < power <= 1.0 and cfg.train.step_size.initial > 0  # eps = 0: the sum of the steps is 0
    typer.echo(
        f"Assumption 6 (sum eps = inf, sum eps^2 < inf): {'holds' if holds else 'FAILS'} "
        f"(eps_l = {cfg.train.step_size.initial} / (1 + l/{cfg.train.step_size.decay})^{power})"
    )
    typer.echo(describe(setup.network, setup.params.team))
    if draw is not None:
        from riskplan.experiments.reporting.figures.world_picture import picture_of, write_picture

        write_picture(picture_of(setup), draw)
        typer.echo(f"world drawn: {draw}")
    typer.echo("config OK")


# How a picture of each --draw format begins, and what its first KB holds: a file riskplan could have drawn
SIGNATURES = {"png": (b"\x89PNG\r\n\x1a\n", b""), "pdf": (b"%PDF-", b""), "svg": (b"<", b"<svg")}


def _check_replaceable(path: Path, fmt: str) -> None:
    """BadInput for a --draw path riskplan would not write over: a symbolic link (the picture is renamed into place,
    so it would replace the link, not write its target), and a file that is not a picture of the path's format,
    which would be lost. A new path, an empty file and a picture (one drawn before) are written."""
    if path.is_symlink():
        raise BadInput(
            "--draw",
            f"{path} is a symbolic link (to {os.readlink(path)}); the picture would replace the link, not write its "
            f"target: give the target's own path",
        )
    if not path.exists():
        return
    if path.is_file():  # not a FIFO or a socket, whose opening would wait for a writer
        try:
            with path.open("rb") as file:
                head = file.read(1024)
        except OSError as err:
            raise BadInput("--draw", f"{path} cannot be read ({err.strerror}); give a new path") from None
        start, marker = SIGNATURES[fmt]
        if not head or (head.startswith(start) and marker in head):
            return
    raise BadInput(
        "--draw",
        f"{path} exists and is not a {fmt.upper()} picture; --draw replaces only a picture (one it drew before): "
        f"give a new path, or move the file",
    )


def _describe_world(setup) -> str:
    """A few lines on the world: grid, start, sources, regions, the cells of positions given in metres, and each
    source's reach (a warning for one theta0 rarely reaches)."""
    from riskplan.run.build import reach_lines

    world = setup.world
    lines = [
        f"world: {world.width}x{world.height} grid, horizon K={world.horizon}, "
        f"{int(world.obstacle.sum())} obstacle cells, stop at source: {world.stop_at_source}"
    ]
    for j, name in enumerate(world.source_names):
        x, y = world.xy(world.source_cells[j])
        kind = "static" if world.source_motion[j] == 0 else f"random walk p={world.source_motion[j]:g}"
        lines.append(f"  source {j} '{name}' at ({x}, {y}), {kind}, peak signal {world.source_amplitude[j]:.3g}")
    for r, name in enumerate(world.region_names):
        count = int((world.region_of == r).sum())
        lines.append(f"  region {r} '{name}': {count} cells{', risky' if world.region_risky[r] else ''}")
    for placed in world.placements:
        metres = ", ".join(f"{v:g}" for v in placed.metres)
        became = f"rect {list(placed.cells)}" if len(placed.cells) == 4 else f"cell {tuple(placed.cells)}"
        lines.append(f"  {placed.key}: {{metres: [{metres}]}} -> {became}")
    lines += [f"  {line}" for line in reach_lines(setup)]
    return "\n".join(lines)
