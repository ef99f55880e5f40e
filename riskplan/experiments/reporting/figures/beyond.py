"""The figures beyond the paper drawn from the main runs: consensus by order, the reward distribution, the risk
frontier, the team's parameters, soft risk and the objective landscape."""

from __future__ import annotations

import numpy as np
from matplotlib import patheffects
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from riskplan.config.keys import KEYS
from riskplan.engine.risk_measures import cvar, value_at_risk
from riskplan.experiments.reporting.collect import Collection, Group, schedule_pairs, theta_columns
from riskplan.experiments.reporting.figures.drawing import (
    ROBOT_COLOURS,
    FigureSpec,
    curve_table,
    errorbar,
    faulty_robots,
    integer_iterations,
    legend,
    legend_below,
    legend_right,
    literal,
    new_figure,
    outer,
    panel_grid,
    panel_title,
    plot_band,
    pooled_rewards,
    seeds_text,
)
from riskplan.experiments.reporting.figures.naming import layout, names
from riskplan.experiments.reporting.tables import group_row, runs_on

MAX_THETA_PANELS = 6  # theta components drawn one panel each (a tabular policy's C*5 logits are not)
MAX_TEAM_ROWS = 4  # team groups whose per-robot parameters are drawn, a row each
ORDER_COLOURS = dict(zip(("combine_then_adapt", "adapt_then_combine", "gradient_tracking"), ROBOT_COLOURS))


def fig_orders(collected: Collection) -> FigureSpec | str:
    """Consensus error vs iteration for each team.order, one panel per set-up (the groups' other settings)."""
    order_key = KEYS.team.order
    teams = [g for g in collected.groups if g.team]
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
    fig, axes = new_figure(3.1 * len(panels) + 0.3, 3.3, ncols=len(panels), sharey=True)
    shown: dict[str, str] = {}
    for ax, (rest, gs) in zip(axes[0], panels):
        for g in sorted(gs, key=lambda g: str(g.config["team"].get("order"))):
            order = str(g.config["team"].get("order", "combine_then_adapt"))
            table = curve_table(g.runs, "consensus_error")
            if np.any(table.to_numpy(float) > 0):
                colour = ORDER_COLOURS.get(order, g.color)
                plot_band(ax, table, colour, order, log=True)
                shown.setdefault(order, colour)
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        integer_iterations(ax)
        ax.set_title(
            f"N={gs[0].robots}, {gs[0].config['team'].get('graph')}"
            + "".join(
                f", {k.split('.', 1)[-1]}={v}"
                for k, v in rest
                if k in (KEYS.team.delay.max, KEYS.team.drop, KEYS.team.consensus_rounds)
            )
        )
    axes[0, 0].set_ylabel(r"consensus error $\max_{i,j}\,\|\theta^i-\theta^j\|$")
    legend_below(fig, [Line2D([], [], color=c, lw=1.6, label=o) for o, c in shown.items()])
    return FigureSpec(
        "consensus_orders",
        "Consensus error by team.order",
        "The largest distance between two robots' parameters per iteration for each order of "
        "consensus and gradient steps (combine-then-adapt is the paper's eq. 14; gradient tracking "
        "steps along a tracker of the network-average gradient). Geometric mean across seeds with a "
        "95% band; one panel per set-up.",
        fig,
    )


def _ecdf(ax, g: Group, name: str, colour: str, probs: np.ndarray) -> float:
    """A group's ECDF with its VaR (dashed) and CVaR (dotted) at its β; returns the CVaR."""
    z = pooled_rewards(g)
    if z.size == 0:
        return np.nan
    x = np.quantile(z, probs, method="inverted_cdf")
    var, cv = value_at_risk(z, g.beta), cvar(z, g.beta)
    ax.plot(x, probs, color=colour, label=name)
    ax.axvline(var, color=colour, ls="--", lw=1.0, label=f"_VaR {g.label}")
    ax.axvline(cv, color=colour, ls=":", lw=1.3, label=f"_CVaR {g.label}")
    return cv


MARKS = [
    Line2D([], [], color="#555555", ls="--", lw=1.0, label="VaR$_\\beta$"),
    Line2D([], [], color="#555555", ls=":", lw=1.3, label="CVaR$_\\beta$"),
]


def fig_distribution(collected: Collection) -> FigureSpec | str:
    """The distribution of the total reward per policy: ECDF with VaR and CVaR marked (full and lower tail); past
    MAX_CURVES groups, small multiples of the full ECDF."""
    groups = list(collected.groups)
    if not groups:
        return "no runs"
    lay = layout(groups)
    probs = np.unique(np.concatenate([np.linspace(0, 1, 801), np.geomspace(1e-4, 0.5, 600)]))
    zs = np.concatenate([pooled_rewards(g) for g in groups])
    if lay.single:
        fig, axes = new_figure(8.4, 3.3, ncols=2)
        full, tail = axes[0]
        top = min(0.5, max(0.3, 2 * max(g.beta for g in groups)))  # a tail, also when a beta sweep reaches 1
        panel = lay.panels[0]
        lows = []
        for g, name, colour in zip(panel.groups, panel.names, panel.colours):
            lows.append(_ecdf(full, g, name, colour, probs))
            _ecdf(tail, g, f"_tail {name}", colour, probs)
            tail.plot(
                [value_at_risk(pooled_rewards(g), g.beta)],
                [g.beta],
                ls="none",
                marker="o",
                ms=4,
                color=colour,
                label=f"_beta {g.label}",
            )
        for ax in (full, tail):
            ax.set_xlabel("total reward")
            ax.xaxis.set_major_locator(MaxNLocator(5))
        full.set_ylabel(r"empirical CDF  $P(Z \leq z)$")
        tail.set_ylim(0, top)
        low = min([c for c in lows if np.isfinite(c)] + [float(np.quantile(zs, 0.001))])
        high = float(np.quantile(zs, top))
        if not high > low:  # every episode of the tail paid the same: the point with a margin (matplotlib warned)
            low, high = low - max(1.0, abs(low)) * 0.05, high + max(1.0, abs(high)) * 0.05
        tail.set_xlim(low, high)
        full.set_title("all episodes")
        tail.set_title(f"lower tail (P ≤ {top:g})")
        what = "; the right panel zooms into the lower tail that CVaR averages (dots mark (VaR, β))."
    else:
        fig, axes = panel_grid(len(lay.panels), (3.0, 2.4), sharex=True, sharey=True)
        for ax, p in zip(axes, lay.panels):
            for g, name, colour in zip(p.groups, p.names, p.colours):
                _ecdf(ax, g, name, colour, probs)
            panel_title(ax, p.title)
            ax.xaxis.set_major_locator(MaxNLocator(4))
        outer(axes, "total reward", r"$P(Z \leq z)$")
        what = "." + lay.note()
    handles = [Line2D([], [], color=c, lw=1.6, label=n) for n, c in lay.legend().items()] if lay.shared else []
    legend_right(fig, handles + MARKS)
    return FigureSpec(
        "reward_distribution",
        "Distribution of the total reward",
        "Empirical CDF of the total reward of each final policy on its evaluation episodes (all seeds "
        f"pooled, {seeds_text(groups)}), with VaR (dashed) and CVaR (dotted) at each group's β{what}",
        fig,
    )


def frontier_beta(collected: Collection) -> float:
    """The common CVaR level of the frontier: the most frequent risk.beta (ties: closest to 0.1)."""
    betas = [g.beta for g in collected.groups]
    return max(set(betas), key=lambda b: (betas.count(b), -abs(b - 0.1))) if betas else 0.1


def _frontier_panel(ax, groups: list[Group], called: list[str], colours: list[str], rows: dict):
    for g, name, colour in zip(groups, called, colours):
        row = rows[id(g)]
        errorbar(
            ax,
            (row["mean"], row["mean_low"], row["mean_high"]),
            (row["cvar"], row["cvar_low"], row["cvar_high"]),
            colour,
            name,
            "D" if g.measure == "neutral" else "o",
        )
    families: dict[tuple, list] = {}
    for g in groups:
        if g.measure == "neutral":
            continue
        key = tuple(sorted((k, str(v)) for k, v in g.settings.items() if k != KEYS.risk.beta))
        families.setdefault(key, []).append((g.beta, rows[id(g)]["mean"], rows[id(g)]["cvar"]))
    for members in families.values():
        if len(members) > 1:
            members.sort()
            ax.plot([m[1] for m in members], [m[2] for m in members], "-", color="#777777", lw=0.8, zorder=0)
            xs, ys = np.array([m[1] for m in members]), np.array([m[2] for m in members])
            near_x, near_y = 0.03 * np.ptp(xs) + 1e-9, 0.03 * np.ptp(ys) + 1e-9
            if all(name.startswith("β=") for name in called):  # the legend names each point's β already
                continue
            for k, (beta, x, y) in enumerate(members):
                # policies often cluster (the optimum jumps between beta levels): stack the labels of a cluster
                stacked = int(np.sum((abs(xs[:k] - x) < near_x) & (abs(ys[:k] - y) < near_y)))
                ax.annotate(
                    f"β={beta:g}", (x, y), xytext=(6, -10 - 8 * stacked), textcoords="offset points", fontsize=7
                )


def fig_frontier(collected: Collection) -> FigureSpec | str:
    """Risk frontier: evaluated mean vs CVaR at one common level, one point per group, beta sweeps joined."""
    if len(collected.groups) < 2:
        return "needs at least two conditions (e.g. a risk.beta sweep)"
    alpha = frontier_beta(collected)
    rows = {id(g): group_row(g, beta=alpha) for g in collected.groups}
    lay = layout(list(collected.groups))
    if lay.single:
        fig, grid = new_figure(6.4, 3.6)
        axes = [grid[0, 0]]
    else:
        fig, axes = panel_grid(len(lay.panels), (3.0, 2.6), sharex=True, sharey=True)
    for ax, p in zip(axes, lay.panels):
        _frontier_panel(ax, p.groups, p.names, p.colours, rows)
        if not lay.single:
            panel_title(ax, p.title)
    outer(axes, "mean total reward", f"CVaR$_{{{alpha:g}}}$ of total reward")
    if lay.shared:
        handles = [
            Line2D([], [], ls="none", marker="o", ms=6, color=c, mec="white", label=n) for n, c in lay.legend().items()
        ]
        legend(fig, handles)
    return FigureSpec(
        "risk_frontier",
        "Risk frontier",
        f"Evaluated mean vs CVaR at the common level {alpha:g} of each final policy (95% intervals); "
        f"risk-averse runs that differ only in β are joined. Up and to the right is better on both.{lay.note()}",
        fig,
    )


def fig_thetas(collected: Collection) -> FigureSpec | str:
    """Per-robot theta trajectories of team runs (one row per team condition, one column per component)."""
    teams = [g for g in collected.groups if g.team]
    if not teams:
        return "no team (distributed) runs"
    drawable = [g for g in teams if len(theta_columns(g.first.run.metrics)) <= MAX_THETA_PANELS]
    if not drawable:
        return f"the team runs' theta has more than {MAX_THETA_PANELS} components (a tabular policy): not drawn"
    cols = theta_columns(drawable[0].first.run.metrics)
    same = [g for g in drawable if theta_columns(g.first.run.metrics) == cols]
    shown = same[:MAX_TEAM_ROWS]
    called = names(same)
    panel = min(3.0, 8.6 / len(cols))
    fig, axes = new_figure(
        panel * len(cols) + 1.6, 0.85 * panel * len(shown) + 0.5, ncols=len(cols), nrows=len(shown), sharex=True
    )
    for row, (g, name) in enumerate(zip(shown, called)):
        robots = sorted(r for r in g.first.run.metrics.robot.unique() if r >= 0)
        faulty = faulty_robots(g.first)
        for c, col in enumerate(cols):
            ax = axes[row, c]
            for i, robot in enumerate(robots):
                label = f"robot {robot}" + (" (faulty)" if robot in faulty else "")
                plot_band(ax, curve_table(g.runs, col, robot), ROBOT_COLOURS[i % len(ROBOT_COLOURS)], label, "-")
            average = "network average" + (" (healthy robots)" if faulty else "")
            plot_band(ax, curve_table(g.runs, col, -1), "#000000", average, "--")
            ax.set_ylabel(rf"$\theta_{{{col[6:]}}}$")
            ax.set_title(f"{name}: θ_{col[6:]}" if len(shown) > 1 else f"weight of source {int(col[6:]) + 1}")
            if row == len(shown) - 1:
                ax.set_xlabel("iteration")
                integer_iterations(ax)
    handles, seen = [], set()
    for ax in axes.flat:
        for line in ax.get_lines():
            if not line.get_label().startswith("_") and line.get_label() not in seen:
                seen.add(line.get_label())
                handles.append(line)
    legend_right(fig, handles)
    left = f" The first {len(shown)} of {len(same)} team groups." if len(same) > len(shown) else ""
    return FigureSpec(
        "team_thetas",
        "Per-robot parameters of the team runs",
        "Each robot's θ^i (solid) and the network average (dashed, black) per iteration; consensus "
        f"pulls the robots together while each follows its own gradient estimate.{left}",
        fig,
    )


def fig_soft_risk(collected: Collection) -> FigureSpec | str:
    """Soft risk: CVaR per iteration and the paths of theta, each risk.schedule group against its kind=none twin."""
    pairs = schedule_pairs(collected.groups)[:3]
    if not pairs:
        return "no runs with a soft-risk schedule (risk.schedule.kind=linear or exponential)"
    if len(theta_columns(pairs[0][0].first.run.metrics)) < 2:
        return "the soft-risk runs' world has fewer than two sources (no theta plane to draw)"
    if pairs[0][0].policy_kind == "tabular":
        return "the soft-risk runs' policy is tabular (its theta_0, theta_1 are two logits of one cell)"
    fig, axes = new_figure(8.6, 3.6, ncols=2)
    curves, paths = axes[0]
    levels = curves.twinx()
    levels.grid(False)
    shown: list[Group] = []
    scheduled_groups = [s for s, _ in pairs]
    for scheduled, plain in pairs:
        for g in ([plain] if plain is not None else []) + [scheduled]:
            if g not in shown:
                shown.append(g)
    called = dict(zip(map(id, shown), names(shown)))
    for g in shown:
        scheduled = any(g is s for s in scheduled_groups)
        style = "-" if scheduled else "--"
        plot_band(curves, curve_table(g.runs, "cvar"), g.color, called[id(g)], style)
        _theta_paths(paths, g, called[id(g)], style)
    for scheduled in scheduled_groups:
        if "beta_l" in scheduled.first.run.metrics:
            levels.plot(*_level_curve(scheduled), ":", color=scheduled.color, lw=1.2, label="_level")
    starts = {tuple(r.metrics_of()[["theta_0", "theta_1"]].iloc[0]) for g in shown for r in g.runs}
    for x, y in starts:
        paths.plot([x], [y], ls="none", marker="o", ms=6, mfc="white", mec="black", zorder=5, label="_start")
    _label_soft_risk(curves, levels, paths, pairs[0][0].beta)
    legend_below(fig, curves.get_legend_handles_labels()[0], ncols=2)
    return FigureSpec(
        "soft_risk",
        "Soft risk (CeSoR schedule) against the paper's fixed β",
        "Left: CVaR at risk.beta of each iteration's training episodes (solid: a soft-risk schedule, "
        "dashed: the same runs with risk.schedule.kind=none), and the schedule's level β_l (dotted, "
        "right axis), the CVaR level its gradient ascends. Right: the paths of θ.",
        fig,
    )


def _theta_paths(ax, g: Group, name: str, style: str) -> None:
    """Each run's path of (theta_0, theta_1) over its iterations, ending at its final theta (a square)."""
    for k, r in enumerate(g.runs):
        m = r.metrics_of()
        xs = np.append(m.theta_0.to_numpy(float), r.final_theta()[0])
        ys = np.append(m.theta_1.to_numpy(float), r.final_theta()[1])
        ax.plot(xs, ys, style, color=g.color, lw=1.1, alpha=0.85, label=name if k == 0 else f"_{name} {r.seed}")
        ax.plot(xs[-1:], ys[-1:], ls="none", marker="s", ms=5, color=g.color, mec="white", label="_end")


def _label_soft_risk(curves, levels, paths, beta: float) -> None:
    """The axes' labels and titles of fig_soft_risk: (a) CVaR and the level β_l, (b) the plane of θ."""
    curves.set_xlabel("iteration")
    integer_iterations(curves)
    curves.set_ylabel(f"CVaR$_{{{beta:g}}}$ of total reward (training episodes)")
    levels.set_ylabel(r"$\beta_l$ (dotted)")
    levels.set_ylim(0, 1.05)
    curves.set_title("(a) CVaR at β and the gradient's level β_l")
    paths.set_xlabel(r"$\theta_0$ (weight of source 1)")
    paths.set_ylabel(r"$\theta_1$ (weight of source 2)")
    paths.set_title("(b) θ per iteration (circle θ0, square final)")


def _level_curve(g: Group) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, beta_l) of a group (the schedule is the same for every seed)."""
    m = g.first.metrics_of()
    return m.iteration.to_numpy(float), m.beta_l.to_numpy(float)


def fig_landscape(collected: Collection, scan, index: int) -> FigureSpec | str:
    """Mean and CVaR heatmaps over the theta grid, with the training paths of the runs on that world."""
    a, b = scan.axes
    fig, axes = new_figure(8.6, 3.9, ncols=2)
    runs = runs_on(scan, collected)
    drawn = [g for g in collected.groups if any(r.group is g for r in runs)]
    called = dict(zip(map(id, drawn), names(drawn)))
    _landscape_panel(fig, axes[0, 0], scan, "mean", "mean total reward", runs)
    _landscape_panel(fig, axes[0, 1], scan, "cvar", f"CVaR$_{{{scan.beta:g}}}$ of total reward", runs)
    handles = [
        Line2D([], [], ls="none", marker="*", ms=11, color="white", mec="black", label="grid maximum"),
        Line2D([], [], ls="none", marker="o", ms=5, mfc="white", mec="black", label="θ0 (start)"),
        Line2D([], [], ls="none", marker="s", ms=5, color="#555555", label="final θ"),
    ]
    handles += [Line2D([], [], color=g.color, lw=1.6, label=called[id(g)]) for g in drawn]
    legend_below(fig, handles, ncols=3 if len(handles) <= 9 else 4)
    s = scan.summary
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


def _landscape_panel(fig, ax, scan, column: str, name: str, runs: list) -> None:
    """One heatmap of the landscape (its colour bar named `name`), the runs' paths of theta over it and its maximum."""
    a, b = scan.axes
    va, vb, values = scan.grid(column)
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
    best = scan.best(column)["theta"]
    outline = [patheffects.withStroke(linewidth=3, foreground="white")]
    seen: set[str] = set()
    for r in runs:
        m = r.metrics_of()
        xs = np.append(m[f"theta_{a}"].to_numpy(float), r.final_theta()[a])
        ys = np.append(m[f"theta_{b}"].to_numpy(float), r.final_theta()[b])
        label = literal(r.group.label) if r.group.label not in seen else f"_{r.group.label} {r.seed}"
        seen.add(r.group.label)
        ax.plot(xs, ys, "-", color=r.group.color, lw=1.4, path_effects=outline, label=label)
        ax.plot(xs[:1], ys[:1], ls="none", marker="o", ms=5, mfc="white", mec="black", label="_start")
        ax.plot(xs[-1:], ys[-1:], ls="none", marker="s", ms=6, color=r.group.color, mec="white", label="_end")
    ax.plot(  # alike in shape only to paper.draw_world's start cells: another marker, nothing to share
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
    label_a, label_b = scan.axis_labels
    ax.set_xlabel(rf"$\theta_{{{a}}}$ ({literal(label_a)})")
    ax.set_ylabel(rf"$\theta_{{{b}}}$ ({literal(label_b)})")
    ax.grid(False)
    ax.set_title("(a) mean" if column == "mean" else "(b) CVaR")
