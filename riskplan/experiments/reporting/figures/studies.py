"""The figures of the studies beyond the paper (riskplan reproduce's measures, policies, heterogeneous team and
faults); each picks its groups as its table does (riskplan.experiments.reporting.study_tables) and says why it is not
drawn when a collection holds no such comparison."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
from matplotlib.ticker import MaxNLocator

from riskplan.engine.risk_measures import cvar
from riskplan.experiments.reporting.collect import Collection, Group, theta_columns
from riskplan.experiments.reporting.figures.beyond import ORDER_COLOURS
from riskplan.experiments.reporting.figures.drawing import (
    FigureSpec,
    curve_table,
    errorbar,
    integer_iterations,
    new_figure,
    paired_table,
    plot_band,
    pooled_rewards,
    seeds_text,
)
from riskplan.experiments.reporting.labels import fault_name, measure_name, policy_name
from riskplan.experiments.reporting.stats import seed_interval
from riskplan.experiments.reporting.study_tables import (
    _common_beta,
    _is_central,
    _paired,
    fault_groups,
    hetero_groups,
    landscape_for,
    measure_groups,
    policy_groups,
    team_objective,
)
from riskplan.experiments.reporting.tables import group_row, run_values


def fig_measures(collected: Collection) -> FigureSpec | str:
    """Risk measures: each measure's final policy by its mean and CVaR (seed intervals), and its reward distribution."""
    groups = measure_groups(collected)
    if not groups:
        return "no one-robot runs that differ only in their risk measure (wang, mean_cvar or entropic among them)"
    level = _common_beta(groups)
    fig, axes = new_figure(8.6, 3.7, ncols=2)
    points, ecdf = axes[0]
    probs = np.linspace(0, 1, 801)
    for g in groups:
        row = group_row(g, beta=level)
        name = measure_name(g)
        errorbar(
            points,
            (row["mean"], row["mean_low"], row["mean_high"]),
            (row["cvar"], row["cvar_low"], row["cvar_high"]),
            g.color,
            name,
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
        f"over {seeds_text(groups)} with a 95% Student-t interval). Right: the empirical CDF of the total reward on the evaluation episodes, "
        "all seeds pooled, with each policy's CVaR dotted. Every measure is trained from the paper's θ0 with its "
        "group defaults (conf/risk/).",
        fig,
    )


def fig_policies(collected: Collection) -> FigureSpec | str:
    """Policies that see more: CVaR per iteration of each policy against the landscape's best, and where they end."""
    groups = policy_groups(collected)
    if not groups:
        return "no one-robot runs that differ only in their policy (policy.kind, policy.features)"
    fig, axes = new_figure(8.6, 3.6, ncols=2)
    curves, shares = axes[0]
    names = []
    for g in groups:
        name = policy_name(g) + f" ({len(g.first.final_theta())} parameters)"
        names.append(name)
        plot_band(curves, curve_table(g.runs, "cvar"), g.color, name)
    scan = landscape_for(collected, groups[0])
    if scan is not None:
        best = scan.best("cvar")
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
    integer_iterations(curves)
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
        f"Left: CVaR of each iteration's training episodes (across-seed mean over {seeds_text(groups)}, 95% band), and the largest CVaR over "
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


def order_name(g: Group) -> str:
    """A team's order and graph: 'gradient_tracking (ring)', or 'centralized: complete graph, exact average'."""
    if _is_central(g):
        return "centralized (complete graph, exact average each iteration)"
    t = g.team_conf
    return f"{t.get('order', 'combine_then_adapt')} ({t.get('graph')})"


SMOOTH = 10  # iterations in the moving average of the objective gap of fig_hetero


def fig_hetero(collected: Collection) -> FigureSpec | str:
    """A heterogeneous team: the consensus error of each order, and its gap and distance to the centralized run."""
    distributed, central = hetero_groups(collected)
    if not distributed:
        return "no heterogeneous team runs (team.starts or team.risk) that differ in their order or graph"
    panels = 3 if central is not None else 1
    fig, axes = new_figure(3.1 * panels, 3.5, ncols=panels)
    error = axes[0, 0]
    for g in distributed:
        table = curve_table(g.runs, "consensus_error")
        if np.any(table.to_numpy(float) > 0):
            plot_band(error, table, _order_colour(g), order_name(g), log=True)
    error.set_yscale("log")
    error.set_xlabel("iteration")
    integer_iterations(error)
    error.set_ylabel(r"consensus error $\max_{i,j}\,\|\theta^i-\theta^j\|$")
    error.set_title("(a) consensus error")
    if central is not None:
        _against_central(axes[0, 1], axes[0, 2], distributed, central)
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


def _order_colour(g: Group) -> str:
    """A team's colour by its order (ORDER_COLOURS, as fig_orders draws it), else its group's."""
    return ORDER_COLOURS.get(str(g.team_conf.get("order")), g.color)


def _against_central(gap, distance, distributed: list[Group], central: Group) -> None:
    """Panels (b) and (c) of fig_hetero: each order's objective gap to the centralized run, seed by seed (smoothed,
    with the final gap at θ̄ as a diamond), and the distance of its θ̄ to the centralized run's."""
    largest = 0.0
    for g in distributed:
        colour = _order_colour(g)
        gaps = paired_table(g, central, lambda m, c: c["objective"].astype(float) - m["objective"].astype(float))
        smooth = gaps.rolling(SMOOTH, min_periods=1).mean()  # each seed's gap, a moving average
        plot_band(gap, smooth, colour, order_name(g))
        largest = max(largest, float(np.nanmax(np.abs(smooth.to_numpy(float)))) if smooth.size else 0.0)
        final = _paired(g, central, lambda r, c: team_objective(c) - team_objective(r))
        if final:
            value, low, high = seed_interval(final)
            last = float(gaps.index.max())
            errorbar(gap, (last, last, last), (value, low, high), colour, f"_final {g.label}", "D")
        thetas = theta_columns(g.first.run.metrics)
        dist = paired_table(
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
    integer_iterations(gap)
    gap.set_ylabel("team objective: centralized − distributed")
    gap.set_title(f"(b) objective gap ({SMOOTH}-iteration mean; ◆ at θ̄)")
    distance.set_yscale("log")
    distance.set_xlabel("iteration")
    integer_iterations(distance)
    distance.set_ylabel(r"$\|\bar\theta - \bar\theta_{\mathrm{centralized}}\|$")
    distance.set_title("(c) distance to the centralized θ")


def fig_faults(collected: Collection) -> FigureSpec | str:
    """Faults: the healthy robots' CVaR per iteration under each aggregation, against the fault-free team."""
    faulty, free = fault_groups(collected)
    if not faulty:
        return "no team runs with team.faults that differ only in their faults or aggregation"
    groups = ([free] if free is not None else []) + faulty
    two = len(theta_columns(groups[0].first.run.metrics)) == 2
    fig, axes = new_figure(8.6 if two else 4.8, 3.6, ncols=2 if two else 1)
    curves = axes[0, 0]
    for g in groups:
        plot_band(curves, curve_table(g.runs, "cvar"), g.color, fault_name(g), "--" if g is free else "-")
    beta = groups[0].beta
    curves.set_xlabel("iteration")
    integer_iterations(curves)
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
