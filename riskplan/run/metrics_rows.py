"""The rows of metrics.parquet (and of run.mcap's /metrics) that every driver logs: one per robot and iteration,
and a team's network-average row (robot `AVERAGE`), from the engine's statistics or a Ray robot's own step."""

from __future__ import annotations

import math

import numpy as np

from riskplan.engine.step import Statistics

AVERAGE = -1  # the `robot` id of the network average in team tables


def statistics_rows(statistics: Statistics, seconds: float) -> list[dict]:
    """An iteration's metrics rows from riskplan.engine.step's Statistics: one per robot, then a team's network
    average (robot AVERAGE: its statistics on the healthy robots' pooled episodes, their mean theta and gradient).
    `seconds`: the iteration's time, on every row."""
    l, thetas, e = statistics.iteration, statistics.thetas, statistics.estimates
    eps, error, healthy = statistics.step_size, statistics.consensus_error, statistics.healthy
    rows = _robot_rows(l, e.stats, thetas, e.grads, eps, error, e.episodes, seconds, e.levels, healthy)
    if statistics.team is not None:
        rows.append(
            average_row(l, statistics.team, thetas, e.grads, e.levels, healthy, eps, error, e.episodes, seconds)
        )
    return rows


def average_row(l, team, thetas, grads, levels, healthy, eps, error, samples, seconds, **extra) -> dict:
    """A team's network-average row (robot AVERAGE): `team`, its statistics on the healthy robots' pooled episodes
    (riskplan.engine.step.team_statistics), their mean theta and gradient, their episodes (`samples` per robot), and
    beta_l where every robot shares it; then `extra` columns."""
    ok = slice(None) if np.all(healthy) else np.asarray(healthy, dtype=bool)
    level = levels[0] if np.all(levels == levels[0]) else math.nan
    count = samples * int(np.sum(healthy))
    return metrics_row(
        l,
        AVERAGE,
        team,
        thetas[ok].mean(axis=0),
        grads[ok].mean(axis=0),
        eps,
        error,
        count,
        seconds,
        level,
        True,
        **extra,
    )


def _robot_rows(l, stats, thetas, grads, eps, error, samples, seconds, levels, healthy) -> list[dict]:
    """`metrics_row` of every robot i (stats[k][i], thetas[i], grads[i], levels[i], healthy[i]): the same dicts,
    copies of one template with the values every robot shares, filled in column by column."""
    n, m = thetas.shape
    if n <= 4:  # a centralized run or a small team: one metrics_row each is quicker
        return [
            metrics_row(
                l,
                i,
                {k: v[i] for k, v in stats.items()},
                thetas[i],
                grads[i],
                eps,
                error,
                samples,
                seconds,
                levels[i],
                healthy[i],
            )
            for i in range(n)
        ]
    template = metrics_row(
        l, 0, {k: 0.0 for k in stats}, np.zeros(m), np.zeros(1), eps, error, samples, seconds, levels[0], True
    )
    columns = {
        "robot": range(n),
        "healthy": np.asarray(healthy, dtype=bool).tolist(),
        **{k: np.asarray(v, dtype=float).tolist() for k, v in stats.items()},
        **{f"theta_{j}": column for j, column in enumerate(np.asarray(thetas, dtype=float).T.tolist())},
        "grad_norm": _norms(grads),
        "beta_l": np.asarray(levels, dtype=float).tolist(),
    }
    rows = [template.copy() for _ in range(n)]
    for key, column in columns.items():  # existing keys: the template's order stays
        for row, value in zip(rows, column):
            row[key] = value
    return rows


def _norms(vectors: np.ndarray) -> list[float]:
    """np.linalg.norm of each row, bit for bit: that is sqrt(x.dot(x)), and numpy's vecdot (numpy >= 2) takes each
    row's dot product by the very function x.dot(x) calls (the dtype's dot, a BLAS ddot)."""
    if hasattr(np, "vecdot"):
        return np.sqrt(np.vecdot(vectors, vectors)).tolist()
    return [math.sqrt(x.dot(x)) for x in vectors]


def metrics_row(l, robot, stats, theta, grad, eps, error, samples, seconds, level, healthy, **extra) -> dict:
    """One metrics.parquet row, its columns in their order (`level`: beta_l, the CVaR level of the iteration's
    gradient; stats are at beta; `healthy`: false once the robot's fault of team.faults has started), then `extra`
    columns (the ray backend's `staleness`)."""
    return {
        "iteration": int(l),
        "robot": int(robot),
        "healthy": bool(healthy),
        **{k: float(v) for k, v in stats.items()},
        **{f"theta_{j}": float(t) for j, t in enumerate(theta)},
        "grad_norm": float(np.linalg.norm(grad)),
        "step_size": eps,
        "beta_l": float(level),
        "consensus_error": error,
        "samples": int(samples),
        "seconds": seconds,
        **extra,
    }
