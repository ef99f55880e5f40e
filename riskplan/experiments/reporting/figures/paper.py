"""Figs. 1-4 of the paper's Section V: sampled paths, CVaR per iteration, centralized vs team, consensus error.

From a reproduction (`naming.is_reproduction`) Figs. 1-2 draw the paper's pair, risk-neutral against risk-averse,
under the paper's titles. From any other runs they draw every group, one curve (or panel of paths) per condition,
named by what differs between them, under plain titles.
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from riskplan.engine.step import starts
from riskplan.engine.world import world_map
from riskplan.experiments.reporting.collect import PALETTE, Collection, Group
from riskplan.experiments.reporting.figures.drawing import (
    CENTRAL_COLOUR,
    SOURCE_COLOUR,
    WIDEST,
    FigureSpec,
    curve_table,
    integer_iterations,
    legend,
    legend_below,
    new_figure,
    outer,
    paired_table,
    panel_grid,
    panel_title,
    plot_band,
    seeds_text,
)
from riskplan.experiments.reporting.figures.naming import (
    MAX_PANELS,
    Layout,
    Panel,
    is_reproduction,
    layout,
    names,
    seeded,
)
from riskplan.experiments.reporting.figures.world_picture import world_key
from riskplan.experiments.reporting.labels import measure_name, team_name
from riskplan.run.build import build_setup

MAX_PATHS = 5  # sampled paths per policy in Fig. 1
OVERLAID = 2  # Fig. 1 draws this many policies in one world; more get a panel each
WORLD_SIDE = 3.7  # inches: the side of a square world's axes in Fig. 1; a world of another shape keeps its area
TALLEST = 5.5  # inches: the most height a world's axes take, however tall the world
MARGIN = 0.9  # inches beside the axes for the tick and axis labels
FEW_TEAMS = 4  # Fig. 3 compares this many teams with the centralized run in one panel each of mean and CVaR


def risk_name(g: Group) -> str:
    """'risk-neutral', 'risk-averse (CVaR β=0.1)' or the other measures by name ('Wang (η=0.5)'): the legend of
    the paper's Figs. 1-2."""
    return measure_name(g)


def _world_map(config: dict) -> dict | None:
    try:
        setup = build_setup(config)
    except Exception:
        return None
    return world_map(setup.world, starts(setup))


def draw_world(ax, world: dict, labels: bool = True) -> None:
    """Grid, risky region shaded grey, obstacles dark, sources as stars, start cells as circles."""
    w, h = world["width"], world["height"]
    img = np.zeros((h, w))
    img[np.asarray(world["risky"], bool).T] = 1
    img[np.asarray(world["obstacles"], bool).T] = 2
    ax.imshow(
        img,
        origin="lower",
        extent=(-0.5, w - 0.5, -0.5, h - 0.5),
        interpolation="nearest",
        cmap=ListedColormap(["#FFFFFF", "#C9C9C9", "#3A3A3A"]),
        vmin=0,
        vmax=2,
        zorder=0,
    )
    ax.set_xticks(np.arange(-0.5, w, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, h, 1), minor=True)
    step = 1 if max(w, h) <= 12 else 2 if max(w, h) <= 24 else 5
    ax.set_xticks(np.arange(0, w, step))
    ax.set_yticks(np.arange(0, h, step))
    ax.grid(False, which="major")
    ax.grid(True, which="minor", color="#9A9A9A", lw=0.35, alpha=0.6)
    ax.tick_params(which="minor", length=0)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(-0.5, h - 0.5)
    ax.set_aspect("equal")
    if labels:
        ax.set_xlabel("x (cell)")
        ax.set_ylabel("y (cell)")
    for side in ("top", "right"):
        ax.spines[side].set_visible(True)
    sx = [s["x"] for s in world["sources"]]
    sy = [s["y"] for s in world["sources"]]
    ax.plot(sx, sy, ls="none", marker="*", ms=17, color=SOURCE_COLOUR, mec="black", mew=0.7, zorder=5, label="source")
    for j, s in enumerate(world["sources"]):
        ax.annotate(
            f"{j + 1}",
            (s["x"], s["y"]),
            xytext=(7, 6),
            textcoords="offset points",
            fontsize=8,
            fontweight="bold",
            zorder=6,
        )
    cells = np.array(world["start"], dtype=float).reshape(-1, 2)
    ax.plot(  # alike in shape only to beyond's grid maximum: another marker, nothing to share
        cells[:, 0],
        cells[:, 1],
        ls="none",
        marker="o",
        ms=9,
        mfc="white",
        mec="black",
        mew=1.2,
        zorder=5,
        label="start",
    )


def _paths(g: Group):
    """The first run's sampled paths of its final headline policy (at most MAX_PATHS), or None."""
    run = g.first
    t = run.run.trajectories
    if t is None or t.empty:
        return None
    t = t.loc[(t.policy == "final") & (t.robot == run.headline)]
    return t if not t.empty else None


def _draw_paths(ax, g: Group, colour: str, name: str, shift: float = 0.0) -> None:
    t = _paths(g)
    if t is None:
        return
    episodes = sorted(t.episode.unique())[:MAX_PATHS]
    for k, ep in enumerate(episodes):
        p = t.loc[t.episode == ep].sort_values("step")
        jitter = shift + (k - (len(episodes) - 1) / 2) * 0.05
        x, y = p.x.to_numpy(float) + jitter, p.y.to_numpy(float) + jitter
        ax.plot(x, y, "-", color=colour, lw=1.3, alpha=0.85, zorder=3, label=name if k == 0 else f"_{name} {ep}")
        ax.plot(
            x[-1:],
            y[-1:],
            ls="none",
            marker="s",
            ms=6,
            color=colour,
            mec="white",
            mew=0.8,
            zorder=7,
            label=f"_end {name} {ep}",
        )


def world_axes(world: dict, side: float = WORLD_SIDE) -> tuple[float, float]:
    """Inches (width, height) of a world's axes drawn at its aspect (equal cells): the area of a square world's
    axes of `side`, within WIDEST less the labels' MARGIN and within TALLEST; a figure sized to them leaves no empty
    band beside a wide or a tall world."""
    ratio = world["width"] / world["height"]
    width = min(side * math.sqrt(ratio), WIDEST - MARGIN, TALLEST * ratio)
    return width, width / ratio


MARKS = [
    Line2D([], [], ls="none", marker="s", ms=6, color="#555555", label="end point"),
    Line2D([], [], ls="none", marker="*", ms=12, color=SOURCE_COLOUR, mec="black", label="source"),
    Line2D([], [], ls="none", marker="o", ms=7, mfc="white", mec="black", label="start"),
    Patch(facecolor="#C9C9C9", edgecolor="#9A9A9A", label="risky region"),
]


def fig_paths(collected: Collection) -> FigureSpec | str:
    """Fig. 1: the world and sampled paths of the final policies: the paper's pair in one world (a reproduction's
    runs), or each group's in a world of its own."""
    paper = is_reproduction(collected)
    if paper:
        groups = [g for g in collected.paper_pair() if g is not None]
        called = [risk_name(g) for g in groups]
    else:
        groups = [g for g in collected.groups if _paths(g) is not None]
        called = names(groups)
    if not groups:
        return "no runs"
    left_out = max(0, len(groups) - MAX_PANELS)
    groups, called = groups[:MAX_PANELS], called[:MAX_PANELS]
    worlds: dict[str, dict | None] = {}
    for g in groups:
        key = world_key(g.config)
        if key not in worlds:
            worlds[key] = _world_map(g.config)
    if any(w is None for w in worlds.values()):
        return "the world of the runs could not be rebuilt from their config"
    colours = [g.color for g in groups]
    if len(set(colours)) < len(colours):
        colours = [PALETTE[i % len(PALETTE)] for i in range(len(groups))]
    if len(groups) <= OVERLAID and len(worlds) == 1:
        fig = _paths_in_one_world(next(iter(worlds.values())), groups, called, colours)
        panels = ""
    else:
        fig = _paths_panels(worlds, groups, called, colours)
        panels = " One panel per group." + (f" {left_out} more groups are not drawn." if left_out else "")
    world = next(iter(worlds.values()))
    sources = ", ".join(f"{s['name']} ({s['x']}, {s['y']})" for s in world["sources"])
    return FigureSpec(
        "fig1_paths",
        "Fig. 1 — grid world and sampled paths" if paper else "Sampled paths of the final policies",
        f"The grid world (risky region grey, sources {sources} as stars, start circled) and "
        f"{MAX_PATHS} sampled paths of each final policy (the first seed's run), end points as squares. Paths are "
        f"jittered slightly so overlapping ones stay visible.{panels}",
        fig,
        paper=paper,
    )


def _paths_in_one_world(world: dict, groups: list[Group], called: list[str], colours: list[str]):
    """Fig. 1 for a few groups on one world: their paths side by side in it, one legend below."""
    width, height = world_axes(world)
    entries = len(groups) + len(MARKS)
    ncols = 3 if width + MARGIN >= 6 else 2  # a wide world's figure: its legend in fewer rows
    fig, axes = new_figure(max(width + MARGIN, 4.6), height + 0.55 + 0.24 * math.ceil(entries / ncols) + 0.1)
    ax = axes[0, 0]
    draw_world(ax, world)
    handles = []
    for gi, (g, name, colour) in enumerate(zip(groups, called, colours)):
        _draw_paths(ax, g, colour, name, shift=(gi - (len(groups) - 1) / 2) * 0.16)
        handles.append(Line2D([], [], color=colour, lw=1.6, label=seeded(name, g.first.seed)))
    legend_below(fig, handles + MARKS, ncols=ncols)
    return fig


def _paths_panels(worlds: dict, groups: list[Group], called: list[str], colours: list[str]):
    """Fig. 1 for more groups or worlds: a panel each, sharing their axes when every world has the same size."""
    same = len({(w["width"], w["height"]) for w in worlds.values()}) == 1
    width, height = world_axes(next(iter(worlds.values())), side=2.7) if same else (2.7, 2.7)
    fig, axes = panel_grid(len(groups), (width + 0.4, height + 0.5), extra=0.3, sharex=same, sharey=same)
    for ax, g, name, colour in zip(axes, groups, called, colours):
        draw_world(ax, worlds[world_key(g.config)], labels=not same)
        _draw_paths(ax, g, colour, name)
        panel_title(ax, seeded(name, g.first.seed))
    if same:
        outer(axes, "x (cell)", "y (cell)")
    legend_below(fig, MARKS, ncols=4)
    return fig


def _level(groups: list[Group]) -> str:
    betas = {g.beta for g in groups}
    return f"{betas.pop():g}" if len(betas) == 1 else "\\beta"


def draw_curves(lay: Layout, column: str, ylabel: str, log: bool = False, panel: tuple = (3.0, 2.5)):
    """A metrics column per iteration of every group of a layout: one panel with the legend beside it, or small
    multiples with one legend (or each panel's title) naming the groups."""
    if lay.single:
        fig, grid = new_figure(5.0, 3.2)
        axes = [grid[0, 0]]
    else:
        fig, axes = panel_grid(len(lay.panels), panel, sharex=True, sharey=True)
    drawn = 0
    for ax, p in zip(axes, lay.panels):
        for g, name, colour in zip(p.groups, p.names, p.colours):
            table = curve_table(g.runs, column)
            if log and not np.any(table.to_numpy(float) > 0):
                continue
            plot_band(ax, table, colour, name, log=log)
            drawn += 1
        if log:
            ax.set_yscale("log")
        if p.title and not lay.single:
            panel_title(ax, p.title)
        integer_iterations(ax)
    outer(axes, "iteration", ylabel)
    if lay.shared and drawn:
        handles = [Line2D([], [], color=c, lw=1.6, label=n) for n, c in lay.legend().items()]
        if len(handles) > 1 or lay.single:
            legend(fig, handles)
    return fig, drawn


def fig_cvar(collected: Collection) -> FigureSpec | str:
    """Fig. 2: CVaR of the total reward per iteration: the paper's pair (a reproduction), or every group."""
    paper = is_reproduction(collected)
    if paper:
        groups = [g for g in collected.paper_pair() if g is not None]
        lay = Layout([Panel(groups, [risk_name(g) for g in groups], [g.color for g in groups])])
    else:
        groups = list(collected.groups)
        lay = layout(groups)
    if not groups:
        return "no runs"
    level = _level(groups)
    shown = "β" if level == "\\beta" else level
    ylabel = f"CVaR$_{{{level}}}$ of total reward" + (" (each group's β)" if level == "\\beta" else "")
    fig, _ = draw_curves(lay, "cvar", ylabel)
    seeds = f"the across-seed mean ({seeds_text(groups)}) with a 95% band"
    if paper:
        missing = "" if len(groups) == 2 else " (only one of the two policies is among these runs)"
        return FigureSpec(
            "fig2_cvar",
            "Fig. 2 — CVaR of the total reward, risk-neutral vs risk-averse",
            f"CVaR at level {shown} of the total reward of each iteration's training episodes{missing}: {seeds}.",
            fig,
            paper=True,
        )
    return FigureSpec(
        "fig2_cvar",
        "Learning curves: CVaR of the total reward",
        f"CVaR at level {shown} of the total reward of each iteration's training episodes, one curve per group: "
        f"{seeds}.{lay.note()}",
        fig,
    )


def _team_colours(teams: list[Group]) -> list[str]:
    """The teams' colours, none of them the centralized run's black."""
    own = [g.color for g in teams]
    if len(set(own)) == len(own) and CENTRAL_COLOUR not in own:
        return own
    palette = [c for c in PALETTE if c != CENTRAL_COLOUR]
    return [palette[i % len(palette)] for i in range(len(teams))]


def _central(ax, central: Group, column: str, style: str, label: str = "centralized") -> None:
    """The centralized run's curve: black, open circles every tenth of the run, over the teams' curves."""
    iterations = central.first.metrics_of().iteration.nunique()
    plot_band(
        ax,
        curve_table(central.runs, column),
        CENTRAL_COLOUR,
        label,
        style,
        marker="o",
        ms=3.5,
        mfc="white",
        mew=1.0,
        markevery=max(1, iterations // 10),
        zorder=3,
    )


def fig_team(collected: Collection) -> FigureSpec | str:
    """Fig. 3: mean and CVaR per iteration, the centralized run against each team, and their difference."""
    central, teams = collected.team_comparison()
    if not teams:
        return "no team (distributed) runs"
    paper = is_reproduction(collected)
    colours = _team_colours(teams)
    level = _level(teams)
    shown = "each group's β" if level == "\\beta" else level
    if len(teams) <= FEW_TEAMS:
        fig, how = _few_teams(central, teams, colours, f"CVaR$_{{{level}}}$ of total reward")
    else:
        fig, how = _many_teams(central, teams, colours)
    return FigureSpec(
        "fig3_team",
        "Fig. 3 — mean and CVaR, centralized vs distributed" if paper else "Teams against the centralized run",
        f"{how} Distributed: the network average over all robots' episodes (N·W_i of them); centralized: one robot "
        f"with W episodes. CVaR at level {shown}; across-seed means ({seeds_text(teams)}).",
        fig,
        paper=paper,
    )


def _few_teams(central: Group | None, teams: list[Group], colours: list[str], cvar_label: str):
    """Fig. 3 for up to FEW_TEAMS teams: (a) mean and (b) CVaR of each against the centralized run, (c) their
    difference; the figure and the caption's first sentences."""
    called = names(teams) if len(teams) > 1 else [team_name(teams[0])]
    panels = 3 if central is not None else 2
    fig, axes = new_figure(3.1 * panels, 3.1, ncols=panels)
    for ax, column, ylabel, title in (
        (axes[0, 0], "mean", "mean total reward", "(a) mean"),
        (axes[0, 1], "cvar", cvar_label, "(b) CVaR"),
    ):
        for g, name, colour in zip(teams, called, colours):
            plot_band(ax, curve_table(g.runs, column), colour, name)
        if central is not None:
            _central(ax, central, column, "--")
        ax.set(xlabel="iteration", ylabel=ylabel, title=title)
        integer_iterations(ax)
    handles = [Line2D([], [], color=c, lw=1.6, label=n) for n, c in zip(called, colours)]
    if central is None:
        legend_below(fig, handles, ncols=min(len(handles), 4))
        return fig, "(a) The mean and (b) the CVaR of the total reward per iteration."
    handles.append(Line2D([], [], color=CENTRAL_COLOUR, ls="--", marker="o", ms=3.5, mfc="white", label="centralized"))
    handles += _difference(axes[0, 2], central, teams, colours)
    legend_below(fig, handles, ncols=min(len(handles), 4))
    return fig, (
        "(a) The mean and (b) the CVaR of the total reward per iteration, the centralized run dashed with "
        "circles; (c) the team minus the centralized run, seed by seed (mean with a 95% band; zero inside the "
        "band: no difference the seeds can tell)."
    )


def _many_teams(central: Group | None, teams: list[Group], colours: list[str]):
    """Fig. 3 for more teams: small multiples of mean (solid) and CVaR (dashed), each with the centralized run;
    the figure and the caption's first sentence."""
    lay = layout(teams, most=FEW_TEAMS, palette=tuple(c for c in PALETTE if c != CENTRAL_COLOUR))
    fig, axes = panel_grid(len(lay.panels), (3.0, 2.5), extra=0.3, sharex=True, sharey=True)
    faceted = not all(len(p.groups) == 1 for p in lay.panels)
    for ax, p in zip(axes, lay.panels):
        for g, name, own in zip(p.groups, p.names, p.colours):
            colour = own if faceted else colours[teams.index(g)]
            plot_band(ax, curve_table(g.runs, "mean"), colour, name)
            plot_band(ax, curve_table(g.runs, "cvar"), colour, f"_{name} CVaR", "--")
        if central is not None:
            _central(ax, central, "mean", "-", "_centralized mean")
            _central(ax, central, "cvar", "--", "_centralized CVaR")
        panel_title(ax, p.title if p.title else ", ".join(p.names))
        integer_iterations(ax)
    outer(axes, "iteration", "total reward")
    handles = [
        Line2D([], [], color="#555555", lw=1.6, label="mean"),
        Line2D([], [], color="#555555", ls="--", lw=1.6, label=f"CVaR$_{{{_level(teams)}}}$"),
    ]
    if central is not None:
        handles.append(Line2D([], [], color=CENTRAL_COLOUR, marker="o", ms=3.5, mfc="white", label="centralized"))
    if faceted:
        handles += [Line2D([], [], color=c, lw=1.6, label=n) for n, c in lay.legend().items()]
    legend_below(fig, handles, ncols=min(len(handles), 5))
    how = (
        "Mean (solid) and CVaR (dashed) of the total reward per iteration"
        + (", the centralized run in black with circles." if central is not None else ".")
        + lay.note()
    )
    return fig, how


def _difference(ax, central: Group, teams: list[Group], colours: list[str]) -> list[Line2D]:
    """Panel (c) of Fig. 3: each team's mean and CVaR minus the centralized run's, seed by seed; the legend's
    entries for its line styles."""
    for g, colour in zip(teams, colours):
        for column, style in (("mean", "-"), ("cvar", ":")):
            diff = paired_table(
                g, central, lambda m, c, col=column: m[col].astype(float) - c[col].reindex(m.index).astype(float)
            )
            if diff.empty:  # no seed in common: the difference of the means, without a band
                diff = (
                    curve_table(g.runs, column).mean(axis=1) - curve_table(central.runs, column).mean(axis=1)
                ).to_frame()
            plot_band(ax, diff, colour, f"_{g.label} {column}", style)
    ax.axhline(0.0, color=CENTRAL_COLOUR, lw=0.8)
    ax.set(xlabel="iteration", ylabel="team − centralized", title="(c) difference")
    integer_iterations(ax)
    return [
        Line2D([], [], color="#555555", lw=1.6, label="(c) mean"),
        Line2D([], [], color="#555555", ls=":", lw=1.6, label="(c) CVaR"),
    ]


def fig_consensus(collected: Collection) -> FigureSpec | str:
    """Fig. 4: consensus error max ||theta^i - theta^j|| per iteration, log scale, every team group."""
    teams = [g for g in collected.groups if g.team]
    if not teams:
        return "no team (distributed) runs"
    paper = is_reproduction(collected)
    lay = layout(teams)
    if len(teams) == 1:
        lay.panels[0].names = [team_name(teams[0])]
    fig, drawn = draw_curves(lay, "consensus_error", r"consensus error $\max_{i,j}\,\|\theta^i-\theta^j\|$", log=True)
    if not drawn:
        return "the team runs log no positive consensus error"
    return FigureSpec(
        "fig4_consensus",
        "Fig. 4 — consensus error" if paper else "Consensus error",
        "The largest distance between two robots' parameters at each iteration (log scale; the geometric mean "
        f"across seeds ({seeds_text(teams)}) with a 95% band). Iterations where all robots agree exactly (error 0) "
        f"are not drawn on the log axis.{lay.note()}",
        fig,
        paper=paper,
    )
