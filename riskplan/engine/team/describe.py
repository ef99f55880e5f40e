"""The team as `riskplan check` prints it: graph, weights, the parts of Assumption 5, the SLEM and its predicted
consensus rate, what team.order does each iteration, and with faults or a resilient aggregate, the resilience
condition ((2F+1)-robustness, F-local faults)."""

from __future__ import annotations

import math

import numpy as np

from riskplan.config.faults import faults_of
from riskplan.config.schema import Aggregate, Order, TeamConf
from riskplan.engine.team import graphs, robustness
from riskplan.engine.team.network import TOL, Network


def _matrix_text(matrix: np.ndarray, indent: str = "    ") -> str:
    """An N x N matrix as aligned rows."""
    rows = np.array2string(matrix, precision=4, suppress_small=True, max_line_width=160).splitlines()
    return "\n".join(indent + row for row in rows)


def describe(network: Network, team: TeamConf) -> str:
    """Multi-line text for `riskplan check`: graph, weights, Assumption 5 parts, SLEM and predicted rate."""
    n = network.robots
    kind = "directed" if network.directed else "undirected"
    lines = [f"team: {n} robot{'s' if n != 1 else ''}, {network.graph} graph ({kind}), weights={team.weights}"]
    if n == 1:
        lines.append("centralized run: no communication; Assumption 5 holds trivially")
        return "\n".join(lines)
    notation = "j->i: robot j sends to robot i" if network.directed else "i-j: a two-way link"
    lines.append(f"edges ({notation}): {graphs.format_edges(network.adjacency, network.directed)}")
    if network.positions is not None:
        spots = "; ".join(f"{k}:({x:.3f},{y:.3f})" for k, (x, y) in enumerate(network.positions))
        lines.append(f"positions (unit square): {spots}")
    w = network.weights
    same = all(np.array_equal(w[:, :, 0], w[:, :, k]) for k in range(network.n_params))
    lines.append("weights A (row i = what robot i mixes; rows sum to 1):")
    for k in range(1 if same else network.n_params):
        if not same:
            lines.append(f"  parameter {k}:")
        lines.append(_matrix_text(w[:, :, k]))
    doubly = np.allclose(w.sum(axis=0), 1.0, atol=TOL)
    lines.append("Assumption 5: holds")
    switching = team.switching.enabled
    window = f"; under switching every link is up within any {team.switching.window} iterations" if switching else ""
    lines.append("  (1) strongly connected: yes" + window)
    lines.append(f"  (2) gamma = {network.gamma:.6g} > 0 (smallest weight on the diagonal and on the links)")
    gap, delay = team.max_gap, team.delay.max
    lines.append(
        f"  (3) B = {gap}: a link delivers at least once every {gap} iterations "
        f"(drop probability {team.drop:g}; arrivals at most B + B0 = {gap + delay} apart)"
    )
    lines.append(f"  (4) B0 = {delay}: delays uniform on 0..{delay} iterations; stale={team.stale}")
    weighted = "" if doubly else ": the consensus value is a weighted, not plain, average"
    lines.append(f"  A is {'doubly' if doubly else 'row'} stochastic{weighted}")
    slem = network.slem
    slem = 0.0 if slem < 1e-12 else slem  # rounding noise of an exact-averaging matrix (e.g. complete graph)
    rounds = team.consensus_rounds
    per_iteration = slem**rounds
    rate = f"SLEM = {slem:.6g}: on the fixed graph the consensus error shrinks by about x{slem:.4g} per round"
    if rounds > 1:
        rate += f", x{per_iteration:.4g} per iteration ({rounds} rounds)"
    if slem == 0:
        rate += " (exact average after one round)"
    elif slem < 1:
        rate += f"; {1.0 / -math.log(slem):.3g} rounds per e-fold"
    lines.append(rate)
    if delay or team.drop or switching:
        lines.append("  (delays, drops and switching slow this down; the SLEM rate is a best case)")
    lines.append(describe_order(team))
    faults = faults_of(team)
    if team.aggregate != Aggregate.mean or faults:
        lines.extend(robustness.condition(network.adjacency, team.aggregate, team.trim, faults, unreliable(team)).lines)
    return "\n".join(lines)


def unreliable(team: TeamConf) -> tuple[str, ...]:
    """The settings under which a consensus round may hear fewer links than the graph has."""
    settings = [f"team.drop={team.drop:g}"] if team.drop else []
    settings += [f"team.delay.max={team.delay.max}"] if team.delay.max else []
    return (*settings, "team.switching") if team.switching.enabled else tuple(settings)


def describe_order(team: TeamConf) -> str:
    """One line for `riskplan check`: what team.order does each iteration, and for gradient tracking what is exact."""
    rounds = f"A^{team.consensus_rounds}" if team.consensus_rounds > 1 else "A"
    if team.order == Order.adapt_then_combine:
        return f"order: adapt_then_combine: theta <- {rounds} (theta + eps Delta) (the gradient steps are mixed too)"
    if team.order != Order.gradient_tracking:
        return (
            f"order: combine_then_adapt (eq. 14): theta <- {rounds} theta + eps Delta; the consensus error keeps "
            f"a floor of about eps |Delta^i - Delta^j|"
        )
    text = (
        f"order: gradient_tracking: theta <- {rounds} theta + eps y / v, y <- {rounds} y + Delta_new - Delta_old "
        f"(y_0 = Delta_0); y and the push-sum weight v (v_0 = 1) travel with theta in one message, as running "
        f"sums"
    )
    if team.delay.max or team.drop or team.switching.enabled:
        return text + (
            "; sum_i y^i + the mass in flight = sum_i Delta^i exactly; late mass arrives within "
            f"B + B0 = {team.max_gap + team.delay.max} iterations, so the trackers lag, never drift"
        )
    return text + "; no delays or drops: v = 1 and sum_i y^i = sum_i Delta^i exactly (DIGing)"
