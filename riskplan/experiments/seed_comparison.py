"""What `riskplan reproduce` prints after its sweeps: each condition's mean, CVaR and VaR across seeds (mean ± sd of
the per-seed figures on the evaluation episodes), the paper's claims in a few lines."""

from __future__ import annotations

import sys

import pandas as pd
from rich.console import Console
from rich.table import Table

from riskplan.config.keys import KEYS

CONDITION_KEYS = (KEYS.policy.features, KEYS.policy.kind, KEYS.team.order, KEYS.team.aggregate)  # swept by the studies


def print_comparison(outcomes) -> None:
    """Across seeds: the mean and CVaR of each condition (the paper's claims in four lines)."""
    frames = []
    for outcome in outcomes:
        frame = outcome.summary.copy()
        frame["sweep"] = outcome.sweep_dir.name
        # the conditions of a study's sweep beyond risk and beta (the paper's sweeps have none)
        swept = [c for c in CONDITION_KEYS if c in frame and frame[c].astype(str).nunique() > 1]
        frame["condition"] = frame[swept].astype(str).agg(", ".join, axis=1) if swept else ""
        frames.append(frame)
    if not frames:
        return
    data = pd.concat(frames, ignore_index=True)
    data = data[data.status == "done"]
    if data.empty:
        return
    if "risk" not in data:
        data["risk"] = "cvar"
    data["risk"] = data["risk"].fillna("cvar")
    table = Table(
        title="Section V across seeds (mean ± sd of the per-seed figures on the evaluation episodes)",
        title_justify="left",
        show_edge=False,
        pad_edge=False,
    )
    for column in ("set-up", "objective", "seeds", "mean", "CVaR", "VaR"):
        table.add_column(column, justify="left" if column in ("set-up", "objective") else "right")
    for (sweep, risk, beta, condition), group in data.groupby(["sweep", "risk", "beta", "condition"], sort=False):
        setup = {
            "team": "3 robots, line graph",
            "wander": "1 robot, θ0 = (0, 0)",
            "soft_risk": "1 robot, θ0 = (0, 0), soft risk (linear)",
            "policies": "1 robot, θ0 = (0, 0)",
            "tabular": "1 robot, θ0 = (0, 0), tabular policy",
            "hetero_team": "8 robots from 8 starts, ring",
            "hetero_central": "8 robots from 8 starts, complete graph (centralized)",
            "faults": "7 robots, complete graph, robot 6 Byzantine",
            "faults_free": "7 robots, complete graph, fault-free",
            "floor_plan": "1 robot on the floor plan",
        }.get(sweep, "1 robot (centralized)")
        table.add_row(
            setup + (f", {condition}" if condition else ""),
            {"cvar": f"CVaR_{beta:g}", "neutral": "mean (risk-neutral)"}.get(risk, str(risk)),
            str(len(group)),
            *(
                f"{group[c].mean():.1f} ± {group[c].std(ddof=1) if len(group) > 1 else 0:.1f}"
                for c in ("mean", "cvar", "value_at_risk")
            ),
        )
    (Console() if sys.stdout.isatty() else Console(width=250)).print(table)
