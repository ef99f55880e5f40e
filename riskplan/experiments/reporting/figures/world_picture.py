"""The world as a picture, before any run (`riskplan check --draw PATH`) and in a finished run's report: its cells
(obstacles, a map's unknown cells, each region, risky ones hatched), what the start can reach within the horizon,
each source with its signal's contours, the start cells and the shortest path from a start to each source.

Axes are in cells, and for a map world also in the map frame's metres (top and right). A world wider or taller than
MAX_SHOWN cells is drawn in blocks of k x k cells, each showing the most telling of its cells (an obstacle before
unknown space, before a risky region, ...), so that a one-cell wall stays visible on a warehouse map; the figure
itself is never larger than WIDEST inches (1,880 px at the files' 200 dpi) on either side.
"""

from __future__ import annotations

import json
import math
import textwrap
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, PathPatch
from matplotlib.path import Path as MplPath
from matplotlib.ticker import MaxNLocator

from riskplan.config.schema import MapUnknown, WorldConf
from riskplan.config.typed import typed
from riskplan.engine.reachability import distances, shortest_path, source_distances
from riskplan.engine.step import RunSetup
from riskplan.engine.world import World
from riskplan.experiments.reporting.collect import Collection
from riskplan.experiments.reporting.figures.drawing import (
    SOURCE_COLOUR,
    STYLE,
    WIDEST,
    FigureSpec,
    figure_bytes,
    literal,
    new_figure,
)
from riskplan.run import maps
from riskplan.run.build import build_setup
from riskplan.util.errors import BadInput
from riskplan.util.paths import write_atomic

FORMATS = ("png", "svg", "pdf")  # --draw's file types, by the path's suffix
MAX_SHOWN = 480  # cells along the picture's longest side; a larger world is drawn in blocks
SIGMAS = (1.0, 2.0, 3.0)  # a signal's contours: where it falls to exp(-n^2/2) of its peak, n "sigmas" out
CONTOUR_STYLES = ("-", "--", ":")
SOURCE_COLOURS = (SOURCE_COLOUR, "#0072B2", "#009E73", "#CC79A7", "#E69F00", "#56B4E9")  # a source's star, lines
OBSTACLE = "#3A3A3A"  # as Fig. 1
UNKNOWN = "#9C8FB5"
FREE = "#FFFFFF"
SAFE_REGIONS = ("#CDE8C4", "#C4DDF0", "#F3E7B3", "#E3D3EC")
RISKY_REGIONS = ("#F5B7A5", "#F2A7C4", "#F6C98E")
BEYOND_GREY = 0.72  # cells beyond the horizon are blended with this grey ...
BEYOND_SHARE = 0.45  # ... by this share
RISKY_HATCH = "#8C2D04"
REACH_COLOUR = "#1F4E99"  # the outline of what the start can reach
LEGEND_BELOW = 1.6  # a world this many times wider than tall gets its legend below
MAX_NAMED = 4  # groups a world's caption names
MAX_WORLDS = 8  # worlds the report draws (a sweep over world.horizon has one per value)


@dataclass(frozen=True)
class Cells:
    """The picture's cells as classes (indexed [x, y]), each class's colour, legend label and hatch, in order of
    importance: a block of cells shows its most important one (the largest class)."""

    classes: np.ndarray  # (W, H) int
    open: int  # classes below this are ground a robot may stand on (free, regions), greyed beyond the horizon
    colours: tuple[str, ...]
    labels: tuple[str, ...]
    hatched: tuple[bool, ...]  # risky regions


@dataclass(frozen=True)
class Picture:
    """What the picture shows, in cells: a built world's, or a map's alone (no world: nothing placed on it)."""

    cells: Cells
    metres: tuple[float, float, float] | None  # a map world's (metres per cell, origin x, origin y)
    title: str
    world: World | None = None  # its sources, starts and horizon
    reachable: np.ndarray | None = None  # (W, H) bool: within `horizon` moves of a start
    nearest: np.ndarray | None = None  # (M,) the start cell nearest each source
    moves: np.ndarray | None = None  # (M,) its distance in moves, -1 for no path
    paths: tuple[np.ndarray, ...] = ()  # per source: a shortest path's cells from that start (empty: none)


def picture_of(setup: RunSetup) -> Picture:
    """The picture of a built set-up's world: reachability and paths by riskplan.engine.reachability."""
    world = setup.world
    conf = setup.params.world
    found = maps.read_map(conf)
    unknown = None if found is None else maps.load_layout(conf, found).unknown
    reachable = distances(world.next_cell, world.starts, world.horizon) >= 0
    by_start = source_distances(world, world.starts)  # (starts, sources), -1 for no path
    ranked = np.where(by_start < 0, np.iinfo(np.int64).max, by_start)
    best = ranked.argmin(axis=0)
    nearest = world.starts[best]
    moves = by_start[best, np.arange(world.sources)]
    paths = tuple(
        shortest_path(world, int(start), int(cell)) if d >= 0 else np.empty(0, np.int64)
        for start, cell, d in zip(nearest, world.source_cells, moves)
    )
    shape = (world.width, world.height)
    region_of = world.region_of.reshape(shape)
    regions = [(name, bool(world.region_risky[r]), region_of == r) for r, name in enumerate(world.region_names)]
    metres, title = _frame(found, f"{world.width} × {world.height} cells, horizon K = {world.horizon}")
    return Picture(
        cells=_cells(world.obstacle.reshape(shape), unknown, conf.map_unknown, regions),
        metres=metres,
        title=title,
        world=world,
        reachable=reachable.reshape(shape),
        nearest=nearest,
        moves=moves,
        paths=paths,
    )


def map_alone(conf: WorldConf, found: maps.MapFile, why: str) -> Picture:
    """The picture of a map's cells alone (free, unknown, occupied), nothing placed on it: for placing the start
    and the sources when they are what the config gets wrong (`why`)."""
    layout = maps.load_layout(conf, found)
    width, height = layout.size
    metres, title = _frame(found, f"{width} × {height} cells, the map alone ({why})")
    return Picture(cells=_cells(layout.occupied, layout.unknown, conf.map_unknown, []), metres=metres, title=title)


def _frame(found: maps.MapFile | None, size: str) -> tuple[tuple[float, float, float] | None, str]:
    """(metres per cell, origin x, origin y) of a map's frame, or None, and the picture's title."""
    if found is None:
        return None, f"The world: {size}"
    # a turned map (yaw) has no metre axes: its frame's x and y do not run along the cells'
    metres = (found.cell_size, found.origin[0], found.origin[1]) if found.origin[2] == 0 else None
    turned = "" if metres else f", turned {found.origin[2]:g} rad (no metre axes)"
    return metres, f"{Path(found.shown).name}: {size}, {found.cell_size:g} m per cell{turned}"


def _cells(blocked: np.ndarray, unknown: np.ndarray | None, unknown_as: MapUnknown, regions: list) -> Cells:
    """Free 0, each region (safe ones first, then risky), unknown, obstacle: the classes and their looks.
    `regions`: (name, risky, (W, H) cells) each; `blocked`: (W, H) cells no robot enters."""
    classes = np.zeros(blocked.shape, dtype=np.int64)
    colours, labels, hatched = [FREE], ["free"], [False]
    safe = risky = 0
    for name, is_risky, cells in sorted(regions, key=lambda region: region[1]):
        classes[cells] = len(colours)
        if is_risky:
            colours.append(RISKY_REGIONS[risky % len(RISKY_REGIONS)])
            risky += 1
        else:
            colours.append(SAFE_REGIONS[safe % len(SAFE_REGIONS)])
            safe += 1
        labels.append(f"region '{literal(name)}'" + (" (risky)" if is_risky else ""))
        hatched.append(is_risky)
    open_classes = len(colours)
    if unknown is not None and unknown.any():
        classes[unknown] = len(colours)
        colours.append(UNKNOWN)
        labels.append(f"unknown (world.map_unknown={unknown_as.value})")
        hatched.append(False)
    classes[blocked if unknown is None else blocked & ~unknown] = len(colours)  # blocked unknown cells: as unknown
    colours.append(OBSTACLE)
    labels.append("obstacle")
    hatched.append(False)
    return Cells(classes, open_classes, tuple(colours), tuple(labels), tuple(hatched))


def block_of(width: int, height: int) -> int:
    """k: the picture shows blocks of k x k cells, at most MAX_SHOWN blocks along the longer side."""
    return max(1, math.ceil(max(width, height) / MAX_SHOWN))


def blocks(values: np.ndarray, k: int) -> np.ndarray:
    """(W, H) values to (ceil(W/k), ceil(H/k)) blocks, each the largest of its cells (a partial block at the right
    or top takes what it has)."""
    if k == 1:
        return values
    w, h = values.shape
    pad = np.full((-(-w // k) * k, -(-h // k) * k), values.min(), dtype=values.dtype)
    pad[:w, :h] = values
    return pad.reshape(pad.shape[0] // k, k, pad.shape[1] // k, k).max(axis=(1, 3))


def image_of(picture: Picture, k: int) -> np.ndarray:
    """The (H', W', 3) RGB image of the cells in blocks of k, row 0 the bottom: each class's colour, greyed beyond
    the horizon (obstacles and unknown space as they are)."""
    cells = picture.cells
    classes = blocks(cells.classes, k)
    rgb = np.array([to_rgb(c) for c in cells.colours])[classes]
    if picture.reachable is None:  # the map alone: no start to reach from
        return rgb.transpose(1, 0, 2)
    beyond = (classes < cells.open) & ~blocks(picture.reachable, k)
    rgb[beyond] = (1 - BEYOND_SHARE) * rgb[beyond] + BEYOND_SHARE * BEYOND_GREY
    return rgb.transpose(1, 0, 2)


def draw_picture(picture: Picture) -> Figure:
    """The figure of a Picture: the cells, the reachable outline, signals, paths, starts and sources, a legend."""
    w, h = picture.cells.classes.shape
    k = block_of(w, h)
    below = w > LEGEND_BELOW * h
    fig, axes = new_figure(*_size(w, h, below))
    ax = axes[0, 0]
    edges = (-0.5, -(-w // k) * k - 0.5, -0.5, -(-h // k) * k - 0.5)
    ax.imshow(image_of(picture, k), origin="lower", extent=edges, interpolation="nearest", zorder=0)
    risky = [c for c, hatched in enumerate(picture.cells.hatched) if hatched]
    if risky:
        ax.add_patch(PathPatch(_cells_path(np.isin(blocks(picture.cells.classes, k), risky), k), facecolor="none",
                               edgecolor=RISKY_HATCH, hatch="////", lw=0, zorder=1))  # fmt: skip
    handles = _legend_cells(picture)
    if picture.world is not None:
        outline = _outline(blocks(picture.reachable, k), k)
        ax.add_collection(LineCollection(outline, colors=REACH_COLOUR, lw=1.2, zorder=2))
        handles += _draw_sources(ax, picture, k)
    _axes_in_cells(ax, w, h, picture.metres)
    ax.set_title(literal(textwrap.fill(picture.title, 64)))
    if below:
        legend = fig.legend(handles=handles, loc="outside lower center", ncols=2)
    else:
        legend = fig.legend(handles=handles, loc="outside right upper")
    _fit_legend(fig, legend, below)
    # the world against its legend: what its fixed aspect leaves of its slot goes to the far side, which the files'
    # tight bounding box crops (a legend below a world wider than the labels' allowance kept a band above it)
    ax.set_anchor("S" if below else "E")
    return fig


LEGEND_ROOM = (3.9, 2.6)  # inches _size keeps for the legend beside or below the world, before it is measured
LOWEST = 4.0  # inches: the figure's least height, for a world much wider than tall


def _fit_legend(fig: Figure, legend, below: bool) -> None:
    """Give the legend the room it takes, measured, instead of _size's allowance: with the world's aspect fixed, the
    allowance's spare inches were a blank band between the world and a legend of short labels."""
    box = legend.get_window_extent(fig.canvas.get_renderer())
    taken = (box.height if below else box.width) / fig.dpi + 0.2  # and a margin
    width, height = fig.get_size_inches()
    if below:
        fig.set_size_inches(width, max(height - LEGEND_ROOM[1] + taken, LOWEST))
    else:
        fig.set_size_inches(min(width - LEGEND_ROOM[0] + taken, WIDEST), height)


def _size(width: int, height: int, below: bool) -> tuple[float, float]:
    """(width, height) inches: the world's longer side 3.5-6.5 in (less where the legend needs the room), and
    room for the axes' labels and the legend, within WIDEST."""
    legend = (0.0, LEGEND_ROOM[1]) if below else (LEGEND_ROOM[0], 0.0)  # inches beside or below the world
    labels = (1.3, 1.5)  # the axes' ticks and labels, cells and metres
    longest = min(6.5, max(3.5, 0.4 * max(width, height)))
    scale = min(
        longest / max(width, height),
        (WIDEST - legend[0] - labels[0]) / width,
        (WIDEST - legend[1] - labels[1]) / height,
    )
    return width * scale + legend[0] + labels[0], max(height * scale + legend[1] + labels[1], LOWEST)


def _cells_path(mask: np.ndarray, k: int) -> MplPath:
    """The blocks set in a (W', H') mask as one path of rectangles, a row's neighbouring blocks merged into one."""
    vertices, codes = [], []
    for y in range(mask.shape[1]):
        column = np.concatenate([[False], mask[:, y], [False]])
        changes = np.flatnonzero(column[1:] != column[:-1])
        for first, end in zip(changes[::2], changes[1::2]):
            x0, x1, y0, y1 = first * k - 0.5, end * k - 0.5, y * k - 0.5, (y + 1) * k - 0.5
            vertices += [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
            codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
    return MplPath(np.array(vertices or np.zeros((0, 2))), codes or None)


def _outline(mask: np.ndarray, k: int) -> list:
    """The edges between set and unset blocks of a (W', H') mask (and the grid's border), as line segments in
    cells: the outline of what a start reaches, cell by cell."""
    padded = np.pad(mask, 1)
    segments = []
    xs, ys = np.nonzero(padded[1:, 1:-1] != padded[:-1, 1:-1])  # a vertical edge left of block (x, y)
    segments += [[(x * k - 0.5, y * k - 0.5), (x * k - 0.5, (y + 1) * k - 0.5)] for x, y in zip(xs, ys)]
    xs, ys = np.nonzero(padded[1:-1, 1:] != padded[1:-1, :-1])  # a horizontal edge below block (x, y)
    segments += [[(x * k - 0.5, y * k - 0.5), ((x + 1) * k - 0.5, y * k - 0.5)] for x, y in zip(xs, ys)]
    return segments


def _legend_cells(picture: Picture) -> list:
    """A patch for each class of cell present, and the reach's outline and grey."""
    present = set(np.unique(picture.cells.classes).tolist())
    handles = [
        Patch(facecolor=colour, edgecolor="#777777", hatch="////" if hatched else None, label=label)
        for c, (colour, label, hatched) in enumerate(
            zip(picture.cells.colours, picture.cells.labels, picture.cells.hatched)
        )
        if c in present
    ]
    if picture.world is None:
        return handles
    horizon = picture.world.horizon
    handles.append(Line2D([], [], color=REACH_COLOUR, lw=1.1, label=f"reachable within K = {horizon} moves"))
    grey = (1 - BEYOND_SHARE) * np.ones(3) + BEYOND_SHARE * BEYOND_GREY
    handles.append(Patch(facecolor=grey, edgecolor="#777777", label="beyond reach (greyed)"))
    return handles


def _draw_sources(ax, picture: Picture, k: int) -> list:
    """Each source's signal contours, its shortest path from the nearest start, its star; the starts. Legend
    handles: one per source, the contours' key and the start."""
    world = picture.world
    signals = world.signals()
    xs, ys = np.arange(0, world.width, k), np.arange(0, world.height, k)  # each block's first cell
    handles = []
    for j, name in enumerate(world.source_names):
        colour = SOURCE_COLOURS[j % len(SOURCE_COLOURS)]
        if world.source_amplitude[j] != 0 and min(len(xs), len(ys)) > 1:  # a grid one cell wide has no contours
            share = (signals[:, j] / world.source_amplitude[j]).reshape(world.width, world.height)[::k, ::k].T
            levels = [math.exp(-(n**2) / 2) for n in SIGMAS]
            ax.contour(xs, ys, share, levels=levels[::-1], colors=colour, linewidths=0.9,
                       linestyles=CONTOUR_STYLES[::-1], zorder=3)  # fmt: skip
        path = picture.paths[j]
        if path.size:
            px, py = world.xy(path)
            ax.plot(px, py, "-", color=colour, lw=2.0, alpha=0.9, zorder=4, solid_capstyle="round")
        sx, sy = world.xy(world.source_cells[j])
        ax.plot([sx], [sy], ls="none", marker="*", ms=15, color=colour, mec="black", mew=0.7, zorder=6)
        ax.annotate(f"{j + 1}", (sx, sy), xytext=(7, 6), textcoords="offset points", fontsize=8,
                    fontweight="bold", zorder=7)  # fmt: skip
        x0, y0 = world.xy(picture.nearest[j])
        reached = f"{picture.moves[j]} moves from ({x0}, {y0})" if picture.moves[j] >= 0 else "no path from a start"
        walk = ", a random walk from here" if world.source_motion[j] > 0 else ""
        label = f"{j + 1} '{literal(name)}' ({sx}, {sy}{walk}): {reached}"
        handles.append(Line2D([], [], color=colour, lw=2.0, marker="*", ms=11, mec="black", label=label))
    handles += [
        Line2D([], [], color="#555555", lw=0.9, ls=style, label=f"signal at {n:g}σ ({math.exp(-(n**2) / 2):.0%})")
        for n, style in zip(SIGMAS, CONTOUR_STYLES)
    ]
    rx, ry = world.xy(world.starts)
    ax.plot(rx, ry, ls="none", marker="o", ms=8, mfc="white", mec="black", mew=1.2, zorder=6)
    handles.append(Line2D([], [], ls="none", marker="o", ms=7, mfc="white", mec="black", label="start"))
    return handles


def _axes_in_cells(ax, width: int, height: int, metres: tuple[float, float, float] | None) -> None:
    """Cells on the bottom and left; a map's metres on the top and right (cell x spans metres origin + x * size to
    origin + (x + 1) * size, so its centre x sits at origin + (x + 1/2) * size)."""
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(-0.5, height - 0.5)
    ax.set_aspect("equal")
    ax.grid(False)
    if max(width, height) <= 24:
        step = 1 if max(width, height) <= 12 else 2
        ax.set_xticks(np.arange(0, width, step))
        ax.set_yticks(np.arange(0, height, step))
        ax.set_xticks(np.arange(-0.5, width, 1), minor=True)
        ax.set_yticks(np.arange(-0.5, height, 1), minor=True)
        ax.grid(True, which="minor", color="#9A9A9A", lw=0.35, alpha=0.6)
        ax.tick_params(which="minor", length=0)
    else:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("x (cell)")
    ax.set_ylabel("y (cell)")
    for side in ("top", "right"):
        ax.spines[side].set_visible(True)
    if metres is not None:
        size, x0, y0 = metres
        top = ax.secondary_xaxis("top", functions=(lambda c: x0 + (c + 0.5) * size, lambda m: (m - x0) / size - 0.5))
        right = ax.secondary_yaxis(
            "right", functions=(lambda c: y0 + (c + 0.5) * size, lambda m: (m - y0) / size - 0.5)
        )
        top.set_xlabel("x (m, map frame)")
        right.set_ylabel("y (m, map frame)")


def world_figure(setup: RunSetup) -> Figure:
    """The picture of a built set-up's world, in the report's style."""
    with matplotlib.rc_context(STYLE):
        return draw_picture(picture_of(setup))


# ------------------------------------------------------------------------------------------------ riskplan check
def draw_format(path: Path, key: str = "--draw") -> str:
    """The file type of a --draw path by its suffix (png, svg or pdf); anything else is bad input."""
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise BadInput(key, f"{path} has suffix '{path.suffix}'; give a path ending .png, .svg or .pdf")
    return fmt


def write_picture(picture: Picture, path: Path, key: str = "--draw") -> None:
    """A picture written to `path` (atomically: a failed write leaves no file)."""
    fmt = draw_format(path, key)
    with matplotlib.rc_context(STYLE):
        data = figure_bytes(draw_picture(picture), fmt)
    try:
        write_atomic(path, data)
    except OSError as err:
        raise BadInput(key, f"{path} cannot be written ({err.strerror}); give a path in a writable folder") from None


def map_drawn_instead(cfg, path: Path, err: BadInput, key: str = "--draw") -> BadInput:
    """check --draw on a config that fails to build: a map world whose map reads is drawn alone to `path` (to place
    the start and the sources on, which are often what fails first on a new map), and the error says so; any other
    config's error is returned as it is, as is an error in the map's own keys (world.map_cell=0 cannot be drawn) and
    one outside the world's placement (risk.beta=7): bad input then writes nothing."""
    if err.where.split(".")[:2] in (["world", "map"], ["world", "map_cell"], ["world", "map_unknown"]):
        return err
    if not err.where.startswith(("world.", "team.starts")):
        return err
    try:
        conf = typed(cfg).world
        found = maps.read_map(conf)
        picture = None if found is None else map_alone(conf, found, f"{err.where} is bad")
    except BadInput:  # the map itself, or the config's types: nothing to draw
        return err
    if picture is None:
        return err
    write_picture(picture, path, key)
    return BadInput(err.where, f"{err.problem} (the map alone is drawn to {path}, to place things on)")


# ------------------------------------------------------------------------------------------------ the report
def world_key(config: dict) -> str:
    """What makes two runs' worlds the same picture: their world and team settings."""
    return json.dumps({k: config.get(k) for k in ("world", "team")}, sort_keys=True, default=str)


def fig_world(collected: Collection) -> list[FigureSpec] | str:
    """The worlds of the runs reported, as `riskplan check --draw` draws them: a figure per distinct world (world,
    world_2, ...), in the order of the groups that ran in it."""
    worlds: dict[str, list] = {}
    for g in collected.groups:
        worlds.setdefault(world_key(g.config), []).append(g)
    specs = []
    left_out = f" {len(worlds) - MAX_WORLDS} more worlds are not drawn." if len(worlds) > MAX_WORLDS else ""
    for i, groups in enumerate(list(worlds.values())[:MAX_WORLDS]):
        try:
            setup = build_setup(groups[0].config)
        except Exception as err:
            return f"the world of {groups[0].label} could not be rebuilt from its config ({err})"
        called = ", ".join(g.label for g in groups[:MAX_NAMED]) + (", ..." if len(groups) > MAX_NAMED else "")
        caption = (
            "The world as riskplan check --draw shows it: obstacles dark, regions (risky ones hatched), the cells a "
            "start reaches within the horizon outlined (those beyond greyed), each source's signal at 1σ, 2σ and "
            f"3σ, and a shortest path from the nearest start to each source. The runs of {called}."
            + (left_out if i == MAX_WORLDS - 1 else "")
        )
        name = "world" if i == 0 else f"world_{i + 1}"
        specs.append(FigureSpec(name=name, title="The world of the runs", caption=caption, figure=world_figure(setup)))
    return specs or "no runs"
