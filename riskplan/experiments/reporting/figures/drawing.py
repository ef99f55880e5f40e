"""What every figure of the report shares: the style, the figure and its grid of panels, curves with their bands,
and the files a figure is saved to.

Figures are made with matplotlib's object API on an Agg canvas, so nothing touches pyplot's global state. Curves
over several seeds are the across-seed mean with a 95% t band; single-seed curves have no band.
"""

from __future__ import annotations

import contextlib
import gc
import io
import math
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from PIL import Image

from riskplan.experiments.reporting.collect import Group, RunInfo
from riskplan.experiments.reporting.stats import band

STYLE = {
    "font.family": "DejaVu Sans",
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "legend.fontsize": 7.5,
    "legend.frameon": False,
    "xtick.labelsize": 8,
    "ytick.labelsize": 8,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "grid.linewidth": 0.5,
    "lines.linewidth": 1.6,
    "savefig.dpi": 200,
    "savefig.bbox": "tight",
    "pdf.fonttype": 42,
    "svg.fonttype": "none",
    "svg.hashsalt": "riskplan",  # the SVG's element ids from the content, not uuid4: the same figure, the same file
}
WIDEST = 9.4  # inches: 1,880 px at the files' 200 dpi, the widest a figure may be
SOURCE_COLOUR = "#D55E00"  # vermillion stars (the paper's red)
ROBOT_COLOURS = ("#E69F00", "#56B4E9", "#009E73", "#CC79A7", "#0072B2", "#D55E00", "#F0E442", "#999999")
CENTRAL_COLOUR = "#000000"  # the centralized run beside teams


@dataclass
class FigureSpec:
    """A figure of the report: file stem, title, caption and the matplotlib figure."""

    name: str
    title: str
    caption: str
    figure: Figure
    study: str = ""  # the study of riskplan reproduce it belongs to (collect.STUDIES), or "" for the main runs
    paper: bool = False  # one of the paper's figures, drawn from a reproduction's runs (Section V)


def literal(text: str) -> str:
    """A user's text (a name, a value) drawn as typed: matplotlib would read $...$ in it as mathtext, drawing $x$ as
    an italic x, or failing on $\\nosuchcmd$ and losing the figure."""
    return text.replace("$", r"\$")


def new_figure(width: float, height: float, ncols: int = 1, nrows: int = 1, **kw) -> tuple[Figure, np.ndarray]:
    """A constrained-layout figure with a (nrows x ncols) array of axes, never wider than WIDEST."""
    fig = Figure(figsize=(min(width, WIDEST), height), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def panel_grid(count: int, panel: tuple[float, float], extra: float = 0.0, **kw) -> tuple[Figure, list]:
    """Small multiples: `count` panels of about `panel` inches (width, height) in rows of at most 4, shared axes
    (the kw of Figure.subplots), the unused cells of the last row removed. `extra`: inches of height for a legend
    below. The panels shrink so that the figure stays within WIDEST."""
    ncols = count if count <= 3 else 2 if count == 4 else 3 if count <= 9 else 4
    nrows = math.ceil(count / ncols)
    width = min(panel[0] * ncols + 0.4, WIDEST)
    scale = min(1.0, (width - 0.4) / (panel[0] * ncols))
    fig, axes = new_figure(width, panel[1] * scale * nrows + 0.3 + extra, ncols=ncols, nrows=nrows, **kw)
    flat = list(axes.flat)
    for ax in flat[count:]:
        ax.remove()
    if kw.get("sharex") and count < len(flat):  # the panels above a removed cell show their x tick labels
        for ax in flat[count - ncols : count]:
            if ax in fig.axes:
                ax.xaxis.set_tick_params(labelbottom=True)
    return fig, flat[:count]


def panel_title(ax, text: str) -> None:
    """A small multiple's title, wrapped to its panel's width."""
    ax.set_title(textwrap.fill(text, PANEL_TITLE, break_on_hyphens=False))


def outer(axes: list, xlabel: str | None, ylabel: str | None) -> None:
    """Axis labels on the outer panels of a grid only: x along the bottom of each column, y on the first column."""
    for ax in axes:
        spec = ax.get_subplotspec()
        if xlabel is not None and (spec.is_last_row() or not _below(ax, axes)):
            ax.set_xlabel(xlabel)
        if ylabel is not None and spec.is_first_col():
            ax.set_ylabel(ylabel)


def _below(ax, axes: list) -> bool:
    """Whether a panel of the grid sits below ax in its column."""
    spec = ax.get_subplotspec()
    column, row = spec.colspan.start, spec.rowspan.start
    return any(o.get_subplotspec().colspan.start == column and o.get_subplotspec().rowspan.start > row for o in axes)


PANEL_TITLE = 36  # characters of a line of a small multiple's title
LEGEND_LINE = 34  # characters of a legend entry's line; a longer name wraps


def _labels(handles: list) -> list[str]:
    return [textwrap.fill(h.get_label(), LEGEND_LINE, break_on_hyphens=False) for h in handles]


def legend_right(fig: Figure, handles: list, **kw) -> None:
    """The figure's legend beside its panels, outside them (constrained layout makes room)."""
    fig.legend(handles=handles, labels=_labels(handles), loc="outside right upper", **kw)


def legend_below(fig: Figure, handles: list, ncols: int | None = None, **kw) -> None:
    """The figure's legend under its panels, outside them."""
    ncols = ncols or min(len(handles), 3) or 1
    fig.legend(handles=handles, labels=_labels(handles), loc="outside lower center", ncols=ncols, **kw)


def legend(fig: Figure, handles: list) -> None:
    """A few short entries in a row below the panels, more beside them."""
    if len(handles) <= 4:
        wide = sum(len(h.get_label()) for h in handles) > 60
        legend_below(fig, handles, ncols=2 if wide and len(handles) > 2 else len(handles))
    else:
        legend_right(fig, handles)


def integer_iterations(ax) -> None:
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def seeds_text(groups: list[Group]) -> str:
    """'3 seeds', '2-5 seeds per group' or 'one seed': how many runs each curve pools."""
    counts = sorted({len(g.runs) for g in groups})
    if not counts:
        return "no seeds"
    if counts == [1]:
        return "one seed (no band)"
    if len(counts) == 1:
        return f"{counts[0]} seeds" + (" per group" if len(groups) > 1 else "")
    return f"{counts[0]}–{counts[-1]} seeds per group"


def curve_table(runs: list[RunInfo], column: str, robot: int | None = None) -> pd.DataFrame:
    """(iteration x run) table of a metrics column for the headline (or given) robot of each run."""
    series = {i: r.metrics_of(robot).set_index("iteration")[column].astype(float) for i, r in enumerate(runs)}
    return pd.DataFrame(series).sort_index()


def paired_table(group: Group, reference: Group, value) -> pd.DataFrame:
    """(iteration x seed) table of value(run's headline rows, reference's headline rows of the same seed)."""
    by_seed = {r.seed: r for r in reference.runs}
    series = {}
    for r in group.runs:
        if r.seed in by_seed:
            mine = r.metrics_of().set_index("iteration")
            theirs = by_seed[r.seed].metrics_of().set_index("iteration")
            series[r.seed] = value(mine, theirs)
    return pd.DataFrame(series).sort_index()


def plot_band(ax, table: pd.DataFrame, colour: str, label: str, style: str = "-", log: bool = False, **kw):
    """The across-seed mean (one line, labelled) and its 95% band (unlabelled) of a curve table; kw go to the line
    (markers, z-order)."""
    stats = band(table, log=log)
    (line,) = ax.plot(stats.index.to_numpy(), stats["mean"].to_numpy(), style, color=colour, label=label, **kw)
    if table.shape[1] > 1:
        ax.fill_between(
            stats.index.to_numpy(),
            stats["low"].to_numpy(),
            stats["high"].to_numpy(),
            color=colour,
            alpha=0.18,
            lw=0,
            label="_band " + label,
            zorder=line.get_zorder() - 0.5,
        )
    return line


def errorbar(ax, x: tuple, y: tuple, colour: str, label: str, marker: str = "o") -> None:
    """A point (x, y) with its intervals: (value, low, high) each, missing bounds drawn without a bar (a bootstrap
    interval that misses its point draws no bar on that side)."""
    xerr = np.clip(np.nan_to_num(np.array([[x[0] - x[1]], [x[2] - x[0]]])), 0.0, None)
    yerr = np.clip(np.nan_to_num(np.array([[y[0] - y[1]], [y[2] - y[0]]])), 0.0, None)
    ax.errorbar(
        [x[0]],
        [y[0]],
        xerr=xerr,
        yerr=yerr,
        ls="none",
        marker=marker,
        ms=6,
        color=colour,
        mec="white",
        mew=0.6,
        elinewidth=0.9,
        capsize=2,
        label=label,
    )


def faulty_robots(run: RunInfo) -> set[int]:
    """The robots of a run that were faulty at any iteration (metrics' healthy column; none before it existed)."""
    m = run.run.metrics
    if "healthy" not in m:
        return set()
    return {int(r) for r in m.loc[(m.robot >= 0) & ~m.healthy.astype(bool), "robot"].unique()}


def pooled_rewards(g: Group) -> np.ndarray:
    """The headline policy's evaluation rewards of every seed of a group."""
    return np.concatenate([r.eval_of().total_reward.to_numpy(float) for r in g.runs])


# ------------------------------------------------------------------------------------------------ files
PAGE_DPI = 130  # report.html's inline images: lighter than the 200-dpi files, sharp on screen


def figure_files(spec: FigureSpec, formats: list[str]) -> dict[str, bytes] | str:
    """The figure's files as bytes, {format: bytes}, and its image for the page ("page": PNG at PAGE_DPI); or,
    when matplotlib fails to draw it, the reason (one figure failing never aborts the report)."""
    try:
        with matplotlib.rc_context(STYLE), uncollected():
            # in the order given: each draw re-runs the constrained layout from where the last one left it, so
            # the bytes of a format depend on what was drawn before
            files = {fmt: figure_bytes(spec.figure, fmt) for fmt in formats}
            png = files["png"] if "png" in files else figure_bytes(spec.figure, "png")
        files["page"] = _downscale(png, PAGE_DPI / STYLE["savefig.dpi"])
    except Exception as err:
        return f"failed: {type(err).__name__}: {err}"
    return files


@contextlib.contextmanager
def uncollected() -> Iterator[None]:
    """No cyclic garbage collection in the block (the collector as it was after): building or drawing figures
    allocates objects by the hundred thousand, and the collections they set off walked the survivors again and
    again (0.5 s of a quick reproduction's make_figures, 0.3 s of its drawing); the next collection frees what
    the block left."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def figure_bytes(figure: Figure, fmt: str) -> bytes:
    """The figure as a file's bytes (png, svg or pdf), reproducibly (no dates); draw it inside STYLE's context."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format=fmt, metadata=_metadata(fmt))
    return buffer.getvalue()


def _downscale(png: bytes, scale: float) -> bytes:
    """The PNG resampled by `scale`: cheaper than drawing the figure a third time at the smaller dpi.

    A box filter (pixel area averages) keeps text as sharp as a render at that dpi and the PNG as small; Lanczos'
    ringing made the page half as heavy again. The alpha channel goes: the figures are opaque (white).
    """
    image = Image.open(io.BytesIO(png)).convert("RGB")
    size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
    buffer = io.BytesIO()
    image.resize(size, Image.BOX).save(buffer, format="png", dpi=(PAGE_DPI, PAGE_DPI))
    return buffer.getvalue()


def _metadata(fmt: str) -> dict | None:
    """Reproducible files: no creation dates."""
    if fmt == "pdf":
        return {"CreationDate": None, "ModDate": None}
    if fmt == "svg":
        return {"Date": None}
    if fmt == "png":
        return {"Software": None}
    return None
