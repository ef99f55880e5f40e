"""The report's figures, drawn from the logged tables only (the report never re-simulates).

Every builder returns a `FigureSpec` (or None when the runs lack what it needs, with the reason) holding a
matplotlib `Figure` made with the object API on an Agg canvas, so nothing touches pyplot's global state.
Curves over several seeds are the across-seed mean with a 95% t band; single-seed curves have no band.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass

import matplotlib
import numpy as np
import pandas as pd
from matplotlib import patheffects
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator
from PIL import Image

from riskplan.engine.risk_measures import cvar, value_at_risk
from riskplan.engine.world import world_map
from riskplan.experiments.reporting.collect import (
    Collection,
    Group,
    RunInfo,
    fault_name,
    measure_name,
    policy_name,
    schedule_pairs,
    theta_columns,
)
from riskplan.experiments.reporting.stats import band, seed_interval
from riskplan.experiments.reporting.tables import (
    _common_beta,
    _is_central,
    _paired,
    fault_groups,
    group_row,
    hetero_groups,
    landscape_for,
    measure_groups,
    policy_groups,
    run_values,
    runs_on,
    team_objective,
)
from riskplan.run.build import build_setup, starts

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
SOURCE_COLOUR = "#D55E00"  # vermillion stars (the paper's red)
ROBOT_COLOURS = ("#E69F00", "#56B4E9", "#009E73", "#CC79A7", "#0072B2", "#D55E00", "#F0E442", "#999999")
MAX_PATHS = 5  # sampled paths per policy in Fig. 1
MAX_GROUPS = 8  # groups drawn in one panel
MAX_THETA_PANELS = 6  # theta components drawn one panel each (a tabular policy's C*5 logits are not)


@dataclass
class FigureSpec:
    """A figure of the report: file stem, title, caption and the matplotlib figure."""

    name: str
    title: str
    caption: str
    figure: Figure
    study: str = ""  # the study of riskplan reproduce it belongs to (collect.STUDIES), or "" for the main runs


def _figure(width: float, height: float, ncols: int = 1, nrows: int = 1, **kw) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def risk_name(g: Group) -> str:
    """'risk-neutral', 'risk-averse (CVaR β=0.1)' or the other measures by name ('Wang (η=0.5)'): the legend of
    Figs. 1-2 whatever else differs."""
    return measure_name(g)


def _iterations(ax) -> None:
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _seeds(runs: list[RunInfo]) -> str:
    return f" ({len(runs)} seeds)" if len(runs) > 1 else ""


def curve_table(runs: list[RunInfo], column: str, robot: int | None = None) -> pd.DataFrame:
    """(iteration x run) table of a metrics column for the headline (or given) robot of each run."""
    series = {i: r.metrics_of(robot).set_index("iteration")[column].astype(float) for i, r in enumerate(runs)}
    return pd.DataFrame(series).sort_index()


def plot_band(ax, table: pd.DataFrame, colour: str, label: str, style: str = "-", log: bool = False):
    """The across-seed mean (one line, labelled) and its 95% band (unlabelled) of a curve table."""
    stats = band(table, log=log)
    (line,) = ax.plot(stats.index.to_numpy(), stats["mean"].to_numpy(), style, color=colour, label=label)
    if table.shape[1] > 1:
        ax.fill_between(
            stats.index.to_numpy(),
            stats["low"].to_numpy(),
            stats["high"].to_numpy(),
            color=colour,
            alpha=0.18,
            lw=0,
            label="_band " + label,
        )
    return line


def _world_map(config: dict) -> dict | None:
    try:
        setup = build_setup(config)
    except Exception:
        return None
    return world_map(setup.world, starts(setup))


def draw_world(ax, world: dict) -> None:
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
    starts = np.array(world["start"], dtype=float).reshape(-1, 2)
    ax.plot(
        starts[:, 0],
        starts[:, 1],
        ls="none",
        marker="o",
        ms=9,
        mfc="white",
        mec="black",
        mew=1.2,
        zorder=5,
        label="start",
    )


def fig_paths(coll: Collection) -> FigureSpec | str:
    """Fig. 1: the world and sampled paths of the final risk-neutral and risk-averse policies."""
    neutral, averse = coll.paper_pair()
    groups = [g for g in (neutral, averse) if g is not None]
    if not groups:
        return "no runs"
    world = _world_map(groups[0].config)
    if world is None:
        return "the world of the runs could not be rebuilt from their config"
    fig, axes = _figure(4.6, 4.9)
    ax = axes[0, 0]
    draw_world(ax, world)
    handles = []
    for gi, g in enumerate(groups):
        run = g.first
        t = run.run.trajectories
        if t is None or t.empty:
            continue
        t = t.loc[(t.policy == "final") & (t.robot == run.headline)]
        episodes = sorted(t.episode.unique())[:MAX_PATHS]
        shift = (gi - (len(groups) - 1) / 2) * 0.16
        for k, ep in enumerate(episodes):
            p = t.loc[t.episode == ep].sort_values("step")
            jitter = shift + (k - (len(episodes) - 1) / 2) * 0.05
            x, y = p.x.to_numpy(float) + jitter, p.y.to_numpy(float) + jitter
            ax.plot(
                x,
                y,
                "-",
                color=g.color,
                lw=1.3,
                alpha=0.85,
                zorder=3,
                label=risk_name(g) if k == 0 else f"_{g.label} {ep}",
            )
            ax.plot(
                x[-1:],
                y[-1:],
                ls="none",
                marker="s",
                ms=6,
                color=g.color,
                mec="white",
                mew=0.8,
                zorder=7,
                label=f"_end {g.label} {ep}",
            )
        handles.append(Line2D([], [], color=g.color, lw=1.6, label=f"{risk_name(g)}, seed {run.seed}"))
    handles += [
        Line2D([], [], ls="none", marker="s", ms=6, color="#555555", label="end point"),
        Line2D([], [], ls="none", marker="*", ms=12, color=SOURCE_COLOUR, mec="black", label="source"),
        Line2D([], [], ls="none", marker="o", ms=7, mfc="white", mec="black", label="start"),
        Patch(facecolor="#C9C9C9", edgecolor="#9A9A9A", label="risky region"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=2)
    names = ", ".join(f"{s['name']} ({s['x']}, {s['y']})" for s in world["sources"])
    return FigureSpec(
        "fig1_paths",
        "Fig. 1 — grid world and sampled paths",
        f"The grid world (risky region grey, sources {names} as stars, start circled) and "
        f"{MAX_PATHS} sampled paths of each final policy, end points as squares. Paths are jittered "
        f"slightly so overlapping ones stay visible.",
        fig,
    )


def fig_cvar(coll: Collection) -> FigureSpec | str:
    """Fig. 2: CVaR of the total reward vs iteration, risk-neutral vs risk-averse."""
    neutral, averse = coll.paper_pair()
    groups = [g for g in (neutral, averse) if g is not None]
    if not groups:
        return "no runs"
    fig, axes = _figure(4.6, 3.2)
    ax = axes[0, 0]
    for g in groups:
        plot_band(ax, curve_table(g.runs, "cvar"), g.color, risk_name(g) + _seeds(g.runs))
    betas = {g.beta for g in groups}
    level = f"{betas.pop():g}" if len(betas) == 1 else "\\beta"
    ax.set_xlabel("iteration")
    _iterations(ax)
    ax.set_ylabel(f"CVaR$_{{{level}}}$ of total reward")
    ax.legend(loc="best")
    missing = "" if len(groups) == 2 else " (only one of the two policies is among these runs)"
    return FigureSpec(
        "fig2_cvar",
        "Fig. 2 — CVaR of the total reward, risk-neutral vs risk-averse",
        f"CVaR at level {level.replace(chr(92) + 'beta', 'β')} of the total reward of each iteration's "
        f"training episodes{missing}. Curves are the across-seed mean with a 95% band where there are "
        f"several seeds.",
        fig,
    )


def fig_team(coll: Collection) -> FigureSpec | str:
    """Fig. 3: mean and CVaR vs iteration, centralized vs distributed."""
    central, teams = coll.team_comparison()
    if not teams:
        return "no team (distributed) runs"
    fig, axes = _figure(4.8, 3.4)
    ax = axes[0, 0]
    for g in ([central] if central else []) + teams:
        name = "centralized" if not g.team else (f"distributed (N={g.robots})" if len(teams) == 1 else g.label)
        plot_band(ax, curve_table(g.runs, "mean"), g.color, f"{name}: mean{_seeds(g.runs)}", "-")
        plot_band(ax, curve_table(g.runs, "cvar"), g.color, f"{name}: CVaR{_seeds(g.runs)}", "--")
    ax.set_xlabel("iteration")
    _iterations(ax)
    ax.set_ylabel("total reward")
    ax.legend(loc="best", ncols=1)
    beta = teams[0].beta
    return FigureSpec(
        "fig3_team",
        "Fig. 3 — mean and CVaR, centralized vs distributed",
        f"Mean (solid) and CVaR at level {beta:g} (dashed) of the total reward per iteration. "
        f"Distributed: the network average over all robots' episodes (N·W_i of them); "
        f"centralized: one robot with W episodes.",
        fig,
    )


def fig_consensus(coll: Collection) -> FigureSpec | str:
    """Fig. 4: consensus error max ||theta^i - theta^j|| vs iteration, log scale."""
    teams = [g for g in coll.groups if g.team][:MAX_GROUPS]
    if not teams:
        return "no team (distributed) runs"
    fig, axes = _figure(4.6, 3.2)
    ax = axes[0, 0]
    drawn = 0
    for g in teams:
        table = curve_table(g.runs, "consensus_error")
        if not np.any(table.to_numpy(float) > 0):
            continue
        plot_band(
            ax,
            table,
            g.color,
            (g.label if len(teams) > 1 else f"distributed (N={g.robots})") + _seeds(g.runs),
            log=True,
        )
        drawn += 1
    if not drawn:
        return "the team runs log no positive consensus error"
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    _iterations(ax)
    ax.set_ylabel(r"consensus error $\max_{i,j}\,\|\theta^i-\theta^j\|$")
    ax.legend(loc="best")
    return FigureSpec(
        "fig4_consensus",
        "Fig. 4 — consensus error",
        "The largest distance between two robots' parameters at each iteration (log scale; the "
        "geometric mean across seeds with a 95% band where there are several). Iterations where all "
        "robots agree exactly (error 0) are not drawn on the log axis.",
        fig,
    )


def fig_orders(coll: Collection) -> FigureSpec | str:
    """Consensus error vs iteration for each team.order, one panel per set-up (the groups' other settings)."""
    order_key = "team.order"
    teams = [g for g in coll.groups if g.team]
    orders = {str(g.config.get("team", {}).get("order", "combine_then_adapt")) for g in teams}
    if len(orders) < 2:
        return "no team runs that differ in team.order"
    setups: dict[tuple, list[Group]] = {}
    for g in teams:
        rest = tuple(sorted((k, str(v)) for k, v in g.settings.items() if k != order_key))
        setups.setdefault(rest, []).append(g)
    panels = [(rest, gs) for rest, gs in setups.items() if len(gs) > 1][:3]
    if not panels:
        return "no set-up was run with more than one team.order"
    fig, axes = _figure(4.2 * len(panels), 3.2, ncols=len(panels))
    colours = dict(zip(("combine_then_adapt", "adapt_then_combine", "gradient_tracking"), ROBOT_COLOURS))
    for ax, (rest, gs) in zip(axes[0], panels):
        for g in sorted(gs, key=lambda g: str(g.config["team"].get("order"))):
            order = str(g.config["team"].get("order", "combine_then_adapt"))
            table = curve_table(g.runs, "consensus_error")
            if np.any(table.to_numpy(float) > 0):
                plot_band(ax, table, colours.get(order, g.color), order + _seeds(g.runs), log=True)
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        _iterations(ax)
        ax.set_title(
            f"N={gs[0].robots}, {gs[0].config['team'].get('graph')}"
            + "".join(
                f", {k.split('.', 1)[-1]}={v}"
                for k, v in rest
                if k in ("team.delay.max", "team.drop", "team.consensus_rounds")
            )
        )
        ax.legend(loc="best")
    axes[0, 0].set_ylabel(r"consensus error $\max_{i,j}\,\|\theta^i-\theta^j\|$")
    return FigureSpec(
        "consensus_orders",
        "Consensus error by team.order",
        "The largest distance between two robots' parameters per iteration for each order of "
        "consensus and gradient steps (combine-then-adapt is the paper's eq. 14; gradient tracking "
        "steps along a tracker of the network-average gradient). Geometric mean across seeds with a "
        "95% band; one panel per set-up.",
        fig,
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


def fig_distribution(coll: Collection) -> FigureSpec | str:
    """The distribution of the total reward per policy: ECDF with VaR and CVaR marked (full and lower tail)."""
    groups = coll.groups[:MAX_GROUPS]
    if not groups:
        return "no runs"
    fig, axes = _figure(7.2, 3.3, ncols=2)
    full, tail = axes[0]
    probs = np.unique(np.concatenate([np.linspace(0, 1, 801), np.geomspace(1e-4, 0.5, 600)]))
    top = min(0.5, max(0.3, 2 * max(g.beta for g in groups)))  # a tail, also when a beta sweep reaches 1
    lows = []
    for g in groups:
        z = pooled_rewards(g)
        if z.size == 0:
            continue
        x = np.quantile(z, probs, method="inverted_cdf")
        var, cv = value_at_risk(z, g.beta), cvar(z, g.beta)
        lows.append(cv)
        for ax in (full, tail):
            ax.plot(x, probs, color=g.color, label=g.label + _seeds(g.runs))
            ax.axvline(var, color=g.color, ls="--", lw=1.0, label=f"_VaR {g.label}")
            ax.axvline(cv, color=g.color, ls=":", lw=1.3, label=f"_CVaR {g.label}")
        tail.plot([var], [g.beta], ls="none", marker="o", ms=4, color=g.color, label=f"_beta {g.label}")
    for ax in (full, tail):
        ax.set_xlabel("total reward")
        ax.xaxis.set_major_locator(MaxNLocator(5))
    full.set_ylabel(r"empirical CDF  $P(Z \leq z)$")
    tail.set_ylim(0, top)
    zs = np.concatenate([pooled_rewards(g) for g in groups])
    tail.set_xlim(min(lows + [float(np.quantile(zs, 0.001))]), float(np.quantile(zs, top)))
    full.set_title("all episodes")
    tail.set_title(f"lower tail (P ≤ {top:g})")
    handles = [ln for ln in full.get_lines() if not ln.get_label().startswith("_")]
    handles += [
        Line2D([], [], color="#555555", ls="--", lw=1.0, label="VaR$_\\beta$"),
        Line2D([], [], color="#555555", ls=":", lw=1.3, label="CVaR$_\\beta$"),
    ]
    columns = 2 if len(handles) > 6 else min(3, len(handles))  # labels are long: many groups stack in two columns
    fig.legend(handles=handles, loc="outside lower center", ncols=columns)
    return FigureSpec(
        "reward_distribution",
        "Distribution of the total reward",
        "Empirical CDF of the total reward of each final policy on its evaluation episodes (all seeds "
        "pooled), with VaR (dashed) and CVaR (dotted) at each group's β; the right panel zooms into "
        "the lower tail that CVaR averages (dots mark (VaR, β)).",
        fig,
    )


def frontier_beta(coll: Collection) -> float:
    """The common CVaR level of the frontier: the most frequent risk.beta (ties: closest to 0.1)."""
    betas = [g.beta for g in coll.groups]
    return max(set(betas), key=lambda b: (betas.count(b), -abs(b - 0.1))) if betas else 0.1


def fig_frontier(coll: Collection) -> FigureSpec | str:
    """Risk frontier: evaluated mean vs CVaR at one common level, one point per group, beta sweeps joined."""
    if len(coll.groups) < 2:
        return "needs at least two conditions (e.g. a risk.beta sweep)"
    alpha = frontier_beta(coll)
    fig, axes = _figure(5.4, 3.4 + 0.22 * len(coll.groups))
    ax = axes[0, 0]
    points = []
    for g in coll.groups:
        row = group_row(g, beta=alpha)
        points.append((g, row))
        xerr = np.array([[row["mean"] - row["mean_low"]], [row["mean_high"] - row["mean"]]])
        yerr = np.array([[row["cvar"] - row["cvar_low"]], [row["cvar_high"] - row["cvar"]]])
        ax.errorbar(
            [row["mean"]],
            [row["cvar"]],
            xerr=np.nan_to_num(xerr),
            yerr=np.nan_to_num(yerr),
            ls="none",
            marker="D" if g.measure == "neutral" else "o",
            ms=6,
            color=g.color,
            mec="white",
            mew=0.6,
            elinewidth=0.9,
            capsize=2,
            label=g.label + _seeds(g.runs),
        )
    families: dict[tuple, list] = {}
    for g, row in points:
        if g.measure == "neutral":
            continue
        key = tuple(sorted((k, str(v)) for k, v in g.settings.items() if k != "risk.beta"))
        families.setdefault(key, []).append((g.beta, row["mean"], row["cvar"]))
    for members in families.values():
        if len(members) > 1:
            members.sort()
            ax.plot(
                [m[1] for m in members],
                [m[2] for m in members],
                "-",
                color="#777777",
                lw=0.8,
                zorder=0,
                label="_frontier",
            )
            xs, ys = np.array([m[1] for m in members]), np.array([m[2] for m in members])
            near_x, near_y = 0.03 * np.ptp(xs) + 1e-9, 0.03 * np.ptp(ys) + 1e-9
            for k, (beta, x, y) in enumerate(members):
                # policies often cluster (the optimum jumps between beta levels): stack the labels of a cluster
                stacked = int(np.sum((abs(xs[:k] - x) < near_x) & (abs(ys[:k] - y) < near_y)))
                ax.annotate(
                    f"β={beta:g}", (x, y), xytext=(6, -10 - 8 * stacked), textcoords="offset points", fontsize=7
                )
    ax.set_xlabel("mean total reward")
    ax.set_ylabel(f"CVaR$_{{{alpha:g}}}$ of total reward")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncols=1)  # never over the points
    return FigureSpec(
        "risk_frontier",
        "Risk frontier",
        f"Evaluated mean vs CVaR at the common level {alpha:g} of each final policy (95% intervals); "
        f"risk-averse runs that differ only in β are joined. Up and to the right is better on both.",
        fig,
    )


def fig_thetas(coll: Collection) -> FigureSpec | str:
    """Per-robot theta trajectories of team runs (one row per team condition, one column per component)."""
    teams = [g for g in coll.groups if g.team]
    if not teams:
        return "no team (distributed) runs"
    drawable = [g for g in teams if len(theta_columns(g.first.run.metrics)) <= MAX_THETA_PANELS]
    if not drawable:
        return f"the team runs' theta has more than {MAX_THETA_PANELS} components (a tabular policy): not drawn"
    cols = theta_columns(drawable[0].first.run.metrics)
    teams = [g for g in drawable if theta_columns(g.first.run.metrics) == cols][:4]
    fig, axes = _figure(3.0 * len(cols) + 0.6, 2.6 * len(teams) + 0.5, ncols=len(cols), nrows=len(teams), sharex=True)
    for row, g in enumerate(teams):
        robots = sorted(r for r in g.first.run.metrics.robot.unique() if r >= 0)
        faulty = faulty_robots(g.first)
        for c, col in enumerate(cols):
            ax = axes[row, c]
            for i, robot in enumerate(robots):
                name = f"robot {robot}" + (" (faulty)" if robot in faulty else "")
                plot_band(ax, curve_table(g.runs, col, robot), ROBOT_COLOURS[i % len(ROBOT_COLOURS)], name, "-")
            average = "network average" + (" (healthy robots)" if faulty else "")
            plot_band(ax, curve_table(g.runs, col, -1), "#000000", average, "--")
            ax.set_ylabel(rf"$\theta_{{{col[6:]}}}$")
            ax.set_title(f"{g.label}{_seeds(g.runs)}" if len(teams) > 1 else f"weight of source {int(col[6:]) + 1}")
            if row == len(teams) - 1:
                ax.set_xlabel("iteration")
                _iterations(ax)
    axes[0, 0].legend(loc="best")
    return FigureSpec(
        "team_thetas",
        "Per-robot parameters of the team runs",
        "Each robot's θ^i (solid) and the network average (dashed, black) per iteration; consensus "
        "pulls the robots together while each follows its own gradient estimate.",
        fig,
    )


def fig_soft_risk(coll: Collection) -> FigureSpec | str:
    """Soft risk: CVaR per iteration and the paths of theta, each risk.schedule group against its kind=none twin."""
    pairs = schedule_pairs(coll.groups)[:3]
    if not pairs:
        return "no runs with a soft-risk schedule (risk.schedule.kind=linear or exponential)"
    if len(theta_columns(pairs[0][0].first.run.metrics)) < 2:
        return "the soft-risk runs' world has fewer than two sources (no theta plane to draw)"
    if pairs[0][0].policy_kind == "tabular":
        return "the soft-risk runs' policy is tabular (its theta_0, theta_1 are two logits of one cell)"
    fig, axes = _figure(8.2, 3.6, ncols=2)
    curves, paths = axes[0]
    levels = curves.twinx()
    levels.grid(False)
    shown: list[Group] = []
    for scheduled, plain in pairs:
        for g in ([plain] if plain is not None else []) + [scheduled]:
            if g in shown:
                continue
            shown.append(g)
            name = f"{g.label}{_seeds(g.runs)}"
            plot_band(curves, curve_table(g.runs, "cvar"), g.color, name, "-" if g is scheduled else "--")
            for k, r in enumerate(g.runs):
                m = r.metrics_of()
                xs = np.append(m.theta_0.to_numpy(float), r.final_theta()[0])
                ys = np.append(m.theta_1.to_numpy(float), r.final_theta()[1])
                paths.plot(
                    xs,
                    ys,
                    "-" if g is scheduled else "--",
                    color=g.color,
                    lw=1.1,
                    alpha=0.85,
                    label=name if k == 0 else f"_{name} {r.seed}",
                )
                paths.plot(xs[-1:], ys[-1:], ls="none", marker="s", ms=5, color=g.color, mec="white", label="_end")
        if "beta_l" in scheduled.first.run.metrics:
            levels.plot(*_level_curve(scheduled), ":", color=scheduled.color, lw=1.2, label="_level")
    starts = {tuple(r.metrics_of()[["theta_0", "theta_1"]].iloc[0]) for g in shown for r in g.runs}
    for x, y in starts:
        paths.plot([x], [y], ls="none", marker="o", ms=6, mfc="white", mec="black", zorder=5, label="_start")
    beta = pairs[0][0].beta
    curves.set_xlabel("iteration")
    _iterations(curves)
    curves.set_ylabel(f"CVaR$_{{{beta:g}}}$ of total reward (training episodes)")
    levels.set_ylabel(r"$\beta_l$ (dotted)")
    levels.set_ylim(0, 1.05)
    curves.set_title("(a) CVaR at β and the gradient's level β_l")
    paths.set_xlabel(r"$\theta_0$ (weight of source 1)")
    paths.set_ylabel(r"$\theta_1$ (weight of source 2)")
    paths.set_title("(b) θ per iteration (circle θ0, square final)")
    fig.legend(*curves.get_legend_handles_labels(), loc="outside lower center", ncols=2)
    return FigureSpec(
        "soft_risk",
        "Soft risk (CeSoR schedule) against the paper's fixed β",
        "Left: CVaR at risk.beta of each iteration's training episodes (solid: a soft-risk schedule, "
        "dashed: the same runs with risk.schedule.kind=none), and the schedule's level β_l (dotted, "
        "right axis), the CVaR level its gradient ascends. Right: the paths of θ.",
        fig,
    )


def _level_curve(g: Group) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, beta_l) of a group (the schedule is the same for every seed)."""
    m = g.first.metrics_of()
    return m.iteration.to_numpy(float), m.beta_l.to_numpy(float)


def fig_landscape(coll: Collection, land, index: int) -> FigureSpec | str:
    """Mean and CVaR heatmaps over the theta grid, with the training paths of the runs on that world."""
    a, b = land.axes
    fig, axes = _figure(8.2, 3.9, ncols=2)
    runs = runs_on(land, coll)
    for ax, column, name in (
        (axes[0, 0], "mean", "mean total reward"),
        (axes[0, 1], "cvar", f"CVaR$_{{{land.beta:g}}}$ of total reward"),
    ):
        va, vb, values = land.grid(column)
        da = (va[1] - va[0]) / 2 if va.size > 1 else 0.5
        db = (vb[1] - vb[0]) / 2 if vb.size > 1 else 0.5
        vmin = float(np.nanpercentile(values, 5))
        image = ax.imshow(
            values,
            origin="lower",
            aspect="auto",
            cmap="viridis",
            interpolation="nearest",
            extent=(va[0] - da, va[-1] + da, vb[0] - db, vb[-1] + db),
            vmin=vmin,
            vmax=float(np.nanmax(values)),
        )
        fig.colorbar(image, ax=ax, label=name, extend="min", shrink=0.9)
        best = land.best(column)["theta"]
        outline = [patheffects.withStroke(linewidth=3, foreground="white")]
        drawn: set[str] = set()
        for r in runs:
            m = r.metrics_of()
            xs = np.append(m[f"theta_{a}"].to_numpy(float), r.final_theta()[a])
            ys = np.append(m[f"theta_{b}"].to_numpy(float), r.final_theta()[b])
            label = r.group.label if r.group.label not in drawn else f"_{r.group.label} {r.seed}"
            drawn.add(r.group.label)
            ax.plot(xs, ys, "-", color=r.group.color, lw=1.4, path_effects=outline, label=label)
            ax.plot(xs[:1], ys[:1], ls="none", marker="o", ms=5, mfc="white", mec="black", label="_start")
            ax.plot(xs[-1:], ys[-1:], ls="none", marker="s", ms=6, color=r.group.color, mec="white", label="_end")
        ax.plot(
            [best[a]],
            [best[b]],
            ls="none",
            marker="*",
            ms=15,
            color="white",
            mec="black",
            mew=0.9,
            label="grid maximum",
            zorder=6,
        )
        ax.set_xlim(va[0] - da, va[-1] + da)
        ax.set_ylim(vb[0] - db, vb[-1] + db)
        ax.set_xlabel(rf"$\theta_{{{a}}}$ (weight of source {a + 1})")
        ax.set_ylabel(rf"$\theta_{{{b}}}$ (weight of source {b + 1})")
        ax.grid(False)
        ax.set_title("(a) mean" if column == "mean" else "(b) CVaR")
    handles = [
        Line2D([], [], ls="none", marker="*", ms=11, color="white", mec="black", label="grid maximum"),
        Line2D([], [], ls="none", marker="o", ms=5, mfc="white", mec="black", label="θ0 (start)"),
        Line2D([], [], ls="none", marker="s", ms=5, color="#555555", label="final θ"),
    ]
    handles += [
        Line2D([], [], color=g.color, lw=1.6, label=g.label) for g in coll.groups if any(r.group is g for r in runs)
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=3)
    s = land.summary
    return FigureSpec(
        f"landscape{'' if index == 0 else f'_{index + 1}'}",
        "Objective landscape",
        f"Mean and CVaR of the total reward over a {s.get('points', '?')}×{s.get('points', '?')} grid of "
        f"(θ_{a}, θ_{b}), {s.get('episodes', '?')} episodes per point on common random numbers (seed "
        f"{s.get('seed', '?')}); colours below the 5th percentile are clipped. Lines: the training "
        f"paths of the runs on this world that optimise the mean or CVaR at this β (circle: θ0, "
        f"square: final θ); star: the grid maximum.",
        fig,
    )


# ------------------------------------------------------------------------------------------------ studies
# The figures of the studies beyond the paper (riskplan reproduce's measures, policies, heterogeneous team and
# faults); each picks its groups as its table does (riskplan.experiments.reporting.tables) and says why it is not
# drawn when a collection holds no such comparison.


def _errorbar(ax, x: tuple, y: tuple, colour: str, label: str, marker: str = "o") -> None:
    """A point (x, y) with its intervals: (value, low, high) each, missing bounds drawn without a bar."""
    xerr = np.nan_to_num(np.array([[x[0] - x[1]], [x[2] - x[0]]]))
    yerr = np.nan_to_num(np.array([[y[0] - y[1]], [y[2] - y[0]]]))
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


def fig_measures(coll: Collection) -> FigureSpec | str:
    """Risk measures: each measure's final policy by its mean and CVaR (seed intervals), and its reward distribution."""
    groups = measure_groups(coll)
    if not groups:
        return "no one-robot runs that differ only in their risk measure (wang, mean_cvar or entropic among them)"
    level = _common_beta(groups)
    fig, axes = _figure(8.6, 3.7, ncols=2)
    points, ecdf = axes[0]
    probs = np.linspace(0, 1, 801)
    for g in groups:
        row = group_row(g, beta=level)
        name = measure_name(g)
        _errorbar(
            points,
            (row["mean"], row["mean_low"], row["mean_high"]),
            (row["cvar"], row["cvar_low"], row["cvar_high"]),
            g.color,
            name + _seeds(g.runs),
            "D" if g.measure == "neutral" else "o",
        )
        k = groups.index(g)
        points.annotate(
            name,
            (row["mean"], row["cvar"]),
            xytext=(6, 4 if k % 2 == 0 else -10),
            textcoords="offset points",
            fontsize=7,
        )
        z = pooled_rewards(g)
        ecdf.plot(np.quantile(z, probs, method="inverted_cdf"), probs, color=g.color, label=name)
        ecdf.axvline(cvar(z, level), color=g.color, ls=":", lw=1.2, label=f"_CVaR {name}")
    points.set_xlabel("mean total reward")
    points.set_ylabel(f"CVaR$_{{{level:g}}}$ of total reward")
    points.set_title("(a) final policies (95% intervals over seeds)")
    ecdf.set_xlabel("total reward")
    ecdf.set_ylabel(r"empirical CDF  $P(Z \leq z)$")
    ecdf.set_title(f"(b) evaluation episodes, seeds pooled (dotted: CVaR$_{{{level:g}}}$)")
    ecdf.xaxis.set_major_locator(MaxNLocator(5))
    fig.legend(*points.get_legend_handles_labels(), loc="outside lower center", ncols=min(3, len(groups)))
    return FigureSpec(
        "risk_measures",
        "Risk measures in the paper world",
        f"Left: the evaluated mean and CVaR at {level:g} of each measure's final policy (the across-seed mean "
        "with a 95% Student-t interval). Right: the empirical CDF of the total reward on the evaluation episodes, "
        "all seeds pooled, with each policy's CVaR dotted. Every measure is trained from the paper's θ0 with its "
        "group defaults (conf/risk/).",
        fig,
    )


def fig_policies(coll: Collection) -> FigureSpec | str:
    """Policies that see more: CVaR per iteration of each policy against the landscape's best, and where they end."""
    groups = policy_groups(coll)
    if not groups:
        return "no one-robot runs that differ only in their policy (policy.kind, policy.features)"
    fig, axes = _figure(8.6, 3.6, ncols=2)
    curves, shares = axes[0]
    names = []
    for g in groups:
        name = policy_name(g) + f" ({len(g.first.final_theta())} parameters)"
        names.append(name)
        plot_band(curves, curve_table(g.runs, "cvar"), g.color, name + _seeds(g.runs))
    land = landscape_for(coll, groups[0])
    if land is not None:
        best = land.best("cvar")
        curves.axhline(best["value"], color="#777777", ls="--", lw=1.0, label="_best")
        curves.annotate(
            "best CVaR of the paper's policy (landscape grid)",
            (0.02, best["value"]),
            xycoords=("axes fraction", "data"),
            xytext=(0, -10),
            textcoords="offset points",
            fontsize=7,
            color="#555555",
        )
    beta = groups[0].beta
    curves.set_xlabel("iteration")
    _iterations(curves)
    curves.set_ylabel(f"CVaR$_{{{beta:g}}}$ of total reward (training episodes)")
    curves.set_title("(a) CVaR per iteration")
    sources = [k for k in run_values(groups[0].first) if k.startswith("reached_")]
    colours = dict(zip(sources, ("#009E73", "#D55E00", "#999999", "#56B4E9", "#CC79A7")))
    y = np.arange(len(groups))[::-1]
    left = np.zeros(len(groups))
    for k in sources:
        share = np.array([np.mean([run_values(r, beta)[k] for r in g.runs]) for g in groups])
        shares.barh(y, share, left=left, color=colours[k], edgecolor="white", label=k[len("reached_") :])
        left += share
    shares.set_yticks(y, [n.replace(" (", "\n(") for n in names])
    shares.set_xlim(0, 1)
    shares.set_xlabel("share of evaluation episodes (mean over seeds)")
    shares.set_title("(b) the source reached")
    shares.grid(False, axis="y")
    shares.legend(loc="lower right", title="reached", fontsize=7, title_fontsize=7)
    fig.legend(*curves.get_legend_handles_labels(), loc="outside lower center", ncols=1)
    theta0 = groups[0].first.flat.get("train.theta0")
    return FigureSpec(
        "richer_policies",
        "Policies that see more",
        f"Each policy trained from θ0 = {_short_list(theta0)} (a tabular policy starts from the logits it gives). "
        "Left: CVaR of each iteration's training episodes (across-seed mean, 95% band), and the largest CVaR over "
        "the landscape's grid of the paper's two-parameter policy (dashed). Right: the share of evaluation episodes "
        "that reach each source.",
        fig,
    )


def _short_list(text) -> str:
    try:
        values = json.loads(text) if isinstance(text, str) else list(text)
        return "(" + ", ".join(f"{float(v):g}" for v in values) + ")"
    except (TypeError, ValueError):
        return str(text)


def _paired_table(group: Group, reference: Group, value) -> pd.DataFrame:
    """(iteration x seed) table of value(run's headline rows, reference's headline rows of the same seed)."""
    by_seed = {r.seed: r for r in reference.runs}
    series = {}
    for r in group.runs:
        if r.seed in by_seed:
            mine = r.metrics_of().set_index("iteration")
            theirs = by_seed[r.seed].metrics_of().set_index("iteration")
            series[r.seed] = value(mine, theirs)
    return pd.DataFrame(series).sort_index()


def order_name(g: Group) -> str:
    """A team's order and graph: 'gradient_tracking (ring)', or 'centralized: complete graph, exact average'."""
    if _is_central(g):
        return "centralized (complete graph, exact average each iteration)"
    t = g.team_conf
    return f"{t.get('order', 'combine_then_adapt')} ({t.get('graph')})"


SMOOTH = 10  # iterations in the moving average of the objective gap of fig_hetero


def fig_hetero(coll: Collection) -> FigureSpec | str:
    """A heterogeneous team: the consensus error of each order, and its gap and distance to the centralized run."""
    distributed, central = hetero_groups(coll)
    if not distributed:
        return "no heterogeneous team runs (team.starts or team.risk) that differ in their order or graph"
    panels = 3 if central is not None else 1
    fig, axes = _figure(4.0 * panels, 3.5, ncols=panels)
    error = axes[0, 0]
    colours = dict(zip(("combine_then_adapt", "adapt_then_combine", "gradient_tracking"), ROBOT_COLOURS))
    for g in distributed:
        colour = colours.get(str(g.team_conf.get("order")), g.color)
        table = curve_table(g.runs, "consensus_error")
        if np.any(table.to_numpy(float) > 0):
            plot_band(error, table, colour, order_name(g) + _seeds(g.runs), log=True)
    error.set_yscale("log")
    error.set_xlabel("iteration")
    _iterations(error)
    error.set_ylabel(r"consensus error $\max_{i,j}\,\|\theta^i-\theta^j\|$")
    error.set_title("(a) consensus error")
    if central is not None:
        gap, distance = axes[0, 1], axes[0, 2]
        largest = 0.0
        for g in distributed:
            colour = colours.get(str(g.team_conf.get("order")), g.color)
            gaps = _paired_table(g, central, lambda m, c: c["objective"].astype(float) - m["objective"].astype(float))
            smooth = gaps.rolling(SMOOTH, min_periods=1).mean()  # each seed's gap, a moving average
            plot_band(gap, smooth, colour, order_name(g))
            largest = max(largest, float(np.nanmax(np.abs(smooth.to_numpy(float)))) if smooth.size else 0.0)
            final = _paired(g, central, lambda r, c: team_objective(c) - team_objective(r))
            if final:
                value, low, high = seed_interval(final)
                last = float(gaps.index.max())
                _errorbar(gap, (last, last, last), (value, low, high), colour, f"_final {g.label}", "D")
            thetas = theta_columns(g.first.run.metrics)
            dist = _paired_table(
                g,
                central,
                lambda m, c, cols=thetas: pd.Series(
                    np.linalg.norm(m[cols].to_numpy(float) - c.reindex(m.index)[cols].to_numpy(float), axis=1),
                    index=m.index,
                ),
            )
            dist = dist.where(dist > 1e-9)  # the first iterations, before the orders part (rounding): not drawn
            if np.any(dist.to_numpy(float) > 0):
                plot_band(distance, dist, colour, order_name(g), log=True)
        gap.axhline(0.0, color="#555555", lw=0.8)
        gap.set_yscale("symlog", linthresh=10 ** round(np.log10(max(0.005 * largest, 1e-9))))
        gap.set_xlabel("iteration")
        _iterations(gap)
        gap.set_ylabel("team objective: centralized − distributed")
        gap.set_title(f"(b) objective gap ({SMOOTH}-iteration mean; ◆ at θ̄)")
        distance.set_yscale("log")
        distance.set_xlabel("iteration")
        _iterations(distance)
        distance.set_ylabel(r"$\|\bar\theta - \bar\theta_{\mathrm{centralized}}\|$")
        distance.set_title("(c) distance to the centralized θ")
    fig.legend(*error.get_legend_handles_labels(), loc="outside lower center", ncols=2)
    t = distributed[0].team_conf
    step = float(distributed[0].first.metrics_of(0).step_size.iloc[-1])
    return FigureSpec(
        "hetero_team",
        "A heterogeneous team: the orders against the centralized run",
        f"{distributed[0].robots} robots from {len(t.get('starts') or [])} start cells, step size {step:g} at the "
        "end. (a) The largest distance between two robots' θ per iteration (log scale; geometric mean across seeds "
        "with a 95% band). "
        + (
            f"(b) The team objective of the centralized run minus that of each order, seed by seed: per iteration "
            f"from the training episodes (robot −1 rows: the sum of each robot's objective at its own θ^i, a "
            f"{SMOOTH}-iteration moving average; mean with a 95% band, symmetric log scale), and at the end (◆) "
            "summary.json's team objective at θ̄ on fresh episodes (95% interval over the seeds). The training "
            "objective flatters a team that disagrees (each robot's θ^i leans towards its own optimum); the final "
            "one is the team's objective at its common policy. (c) The distance between the network averages θ̄ "
            "of each order and of the centralized run of the same seed. The centralized run is the same team on a "
            "complete graph with uniform weights, adapt-then-combine: every robot holds the exact average after "
            "each iteration."
            if central is not None
            else "No centralized comparator (the same team on a complete graph) is among these runs."
        ),
        fig,
    )


def fig_faults(coll: Collection) -> FigureSpec | str:
    """Faults: the healthy robots' CVaR per iteration under each aggregation, against the fault-free team."""
    faulty, free = fault_groups(coll)
    if not faulty:
        return "no team runs with team.faults that differ only in their faults or aggregation"
    groups = ([free] if free is not None else []) + faulty
    two = len(theta_columns(groups[0].first.run.metrics)) == 2
    fig, axes = _figure(8.6 if two else 4.8, 3.6, ncols=2 if two else 1)
    curves = axes[0, 0]
    for g in groups:
        plot_band(
            curves, curve_table(g.runs, "cvar"), g.color, fault_name(g) + _seeds(g.runs), "--" if g is free else "-"
        )
    beta = groups[0].beta
    curves.set_xlabel("iteration")
    _iterations(curves)
    curves.set_ylabel(f"CVaR$_{{{beta:g}}}$ (healthy robots' training episodes)")
    curves.set_title("(a) the healthy robots' CVaR")
    if two:
        plane = axes[0, 1]
        for g in groups:
            for r in g.runs:
                m = r.metrics_of()
                plane.plot(
                    m.theta_0.to_numpy(float),
                    m.theta_1.to_numpy(float),
                    "--" if g is free else "-",
                    color=g.color,
                    lw=1.1,
                    alpha=0.85,
                    label=f"_{g.label} {r.seed}",
                )
                plane.plot(
                    m.theta_0.iloc[-1:], m.theta_1.iloc[-1:], ls="none", marker="s", ms=5, color=g.color, label="_end"
                )
        sent = {
            tuple(f["value"]) if isinstance(f.get("value"), list) else (f["value"],) * 2
            for g in faulty
            for f in g.faults
            if isinstance(f, dict) and f.get("value") is not None
        }
        for value in sent:
            plane.plot([value[0]], [value[1]], ls="none", marker="X", ms=9, color="#D55E00", mec="black", label="_sent")
        if sent:
            plane.annotate(
                "what the faulty robot sends", next(iter(sent)), xytext=(6, 6), textcoords="offset points", fontsize=7
            )
        plane.set_xlabel(r"$\theta_0$ (weight of source 1)")
        plane.set_ylabel(r"$\theta_1$ (weight of source 2)")
        plane.set_title("(b) the healthy robots' θ̄ (square: final)")
    fig.legend(*curves.get_legend_handles_labels(), loc="outside lower center", ncols=1)
    return FigureSpec(
        "faults",
        "A faulty robot: the plain mean against a resilient aggregation",
        f"{groups[0].robots} robots. (a) CVaR at {beta:g} of the healthy robots' training episodes per iteration "
        "(robot −1 rows; across-seed mean with a 95% band), for each aggregation with the faulty robot and for the "
        "fault-free team (dashed)."
        + (" (b) The healthy robots' network average θ̄ per iteration, every seed." if two else ""),
        fig,
    )


STUDY_BUILDERS = {  # study (riskplan.experiments.reporting.collect.STUDIES) -> its figure
    "measures": ("risk_measures", fig_measures),
    "policies": ("richer_policies", fig_policies),
    "hetero_team": ("hetero_team", fig_hetero),
    "faults": ("faults", fig_faults),
}


BUILDERS = (
    ("fig1_paths", fig_paths),
    ("fig2_cvar", fig_cvar),
    ("fig3_team", fig_team),
    ("fig4_consensus", fig_consensus),
    ("consensus_orders", fig_orders),
    ("reward_distribution", fig_distribution),
    ("risk_frontier", fig_frontier),
    ("team_thetas", fig_thetas),
    ("soft_risk", fig_soft_risk),
    *STUDY_BUILDERS.values(),
)


def make_figures(coll: Collection) -> tuple[list[FigureSpec], dict[str, str]]:
    """Every figure the runs support, and for the others why not (name -> reason). Never raises."""
    specs: list[FigureSpec] = []
    skipped: dict[str, str] = {}
    with matplotlib.rc_context(STYLE):
        jobs = list(BUILDERS) + [
            (f"landscape{'' if i == 0 else f'_{i + 1}'}", (lambda c, land=land, i=i: fig_landscape(c, land, i)))
            for i, land in enumerate(coll.landscapes)
        ]
        for name, build in jobs:
            if not coll.runs and not name.startswith("landscape"):
                skipped[name] = "no usable runs"
                continue
            try:
                result = build(coll)
            except Exception as err:
                skipped[name] = f"failed: {type(err).__name__}: {err}"
                continue
            if isinstance(result, FigureSpec):
                specs.append(result)
            else:
                skipped[name] = result
        for study in coll.studies:  # reproduce's studies, each from its own runs
            name, build = STUDY_BUILDERS[study.name]
            try:
                result = build(study.collection)
            except Exception as err:
                result = f"failed: {type(err).__name__}: {err}"
            if isinstance(result, FigureSpec):
                taken = {s.name for s in specs}
                if result.name in taken:  # the main runs drew one too
                    result.name = next(f"{name}_{k}" for k in range(2, len(taken) + 3) if f"{name}_{k}" not in taken)
                result.study = study.name
                specs.append(result)
                skipped.pop(name, None)
            else:
                skipped.setdefault(name, f"{study.name}/: {result}")
    return specs, skipped


PAGE_DPI = 130  # report.html's inline images: lighter than the 200-dpi files, sharp on screen


def figure_files(spec: FigureSpec, formats: list[str]) -> dict[str, bytes] | str:
    """The figure's files as bytes, {format: bytes}, and its image for the page ("page": PNG at PAGE_DPI); or,
    when matplotlib fails to draw it, the reason (one figure failing never aborts the report)."""
    try:
        with matplotlib.rc_context(STYLE):
            # in the order given: each draw re-runs the constrained layout from where the last one left it, so
            # the bytes of a format depend on what was drawn before
            files = {fmt: _savefig(spec.figure, fmt) for fmt in formats}
            png = files["png"] if "png" in files else _savefig(spec.figure, "png")
        files["page"] = _downscale(png, PAGE_DPI / STYLE["savefig.dpi"])
    except Exception as err:
        return f"failed: {type(err).__name__}: {err}"
    return files


def _savefig(figure: Figure, fmt: str) -> bytes:
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
