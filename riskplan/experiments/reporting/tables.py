"""The report's tables, recomputed from the runs' evaluation episodes (never from summaries).

- `comparison_table`: one row per group (condition), the headline policy's final mean, CVaR, VaR at the group's
  risk.beta, P(risky) and P(source j reached), each with a 95% interval. With one seed the interval is a
  percentile bootstrap over the evaluation episodes (the run's seed and train.bootstrap, as in summary.json) and
  a Wilson interval for proportions; with several seeds the point is the across-seed mean and the interval a
  Student-t interval over the seeds. Its `degenerate` column marks a group that learned something degenerate
  (`degenerate_notes`). This is report.csv.
- `runs_table`: every run found, used, duplicate (its config and seed repeat a used run's) or skipped (with
  the reason).
- `landscape_table`: per landscape, its optima and how far each group's trained theta ended from them.
- `soft_risk_table`: per seed, each soft-risk group (risk.schedule) against its twin with the paper's fixed beta.
- The studies beyond the paper: `riskplan.experiments.reporting.study_tables`.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from riskplan.config.keys import KEYS
from riskplan.engine.risk_measures import cvar, objective, value_at_risk
from riskplan.experiments.reporting.collect import (
    Collection,
    Group,
    RunInfo,
    _distance,
    flatten,
    schedule_pairs,
)
from riskplan.experiments.reporting.labels import measure_name
from riskplan.experiments.reporting.stats import seed_interval, wilson
from riskplan.run.evaluation import degenerate_findings
from riskplan.run.intervals import bootstrap_intervals, objective_interval
from riskplan.run.run_files import RUN_LOG

FIGURES = ("mean", "cvar", "value_at_risk")
MAX_BOOTSTRAP = 1000


def source_names(config: dict) -> list[str]:
    """Names of the world's sources, as riskplan.engine.world names them."""
    sources = config.get("world", {}).get("sources", []) or []
    return [(s.get("name") or f"source_{j}") if isinstance(s, dict) else f"source_{j}" for j, s in enumerate(sources)]


def run_values(run: RunInfo, beta: float | None = None) -> dict[str, float]:
    """Point figures of a run's headline policy from its eval table (at the group's beta unless given)."""
    beta = run.group.beta if beta is None and run.group is not None else (beta or 0.1)
    e = run.eval_of()
    z = e.total_reward.to_numpy(dtype=float)
    values = {
        "mean": float(z.mean()),
        "cvar": cvar(z, beta),
        "value_at_risk": value_at_risk(z, beta),
        "risky_fraction": float((e.risky_steps.to_numpy() > 0).mean()),
    }
    reached = e.source_reached.to_numpy()
    for j, name in enumerate(source_names(run.config)):
        values[f"reached_{name}"] = float((reached == j).mean())
    values["reached_none"] = float((reached < 0).mean())
    values["episodes"] = int(z.size)
    return values


def run_intervals(run: RunInfo, beta: float, values: dict[str, float]) -> dict[str, tuple[float, float]]:
    """95% intervals of one run's figures: bootstrap over episodes (figures), Wilson (proportions)."""
    e = run.eval_of()
    z = e.total_reward.to_numpy(dtype=float)
    resamples = int(run.config.get("train", {}).get("bootstrap", MAX_BOOTSTRAP))
    boot = bootstrap_intervals(z, beta, max(1, min(resamples, MAX_BOOTSTRAP)), run.seed)
    out = {name: (boot[name]["low"], boot[name]["high"]) for name in FIGURES}
    for name, p in values.items():
        if name == "risky_fraction" or name.startswith("reached_"):
            out[name] = wilson(p * z.size, z.size)
    return out


def group_row(group: Group, beta: float | None = None) -> dict:
    """One comparison row for a group (optionally at another beta than the group's own)."""
    beta = group.beta if beta is None else beta
    per_run = [run_values(r, beta) for r in group.runs]
    names = [k for k in per_run[0] if k != "episodes"]
    row: dict = {
        "group": group.label,
        "measure": group.measure,
        "beta": beta,
        "robots": group.robots,
        "policy": ("network average" + (", from robot 0's start" if group.heterogeneous else ""))
        if group.team
        else "robot 0",
        "seeds": len(set(group.seeds)),  # distinct seeds (collect keeps one run per config and seed)
        "seed_list": " ".join(str(s) for s in group.seeds),
        "eval_episodes": per_run[0]["episodes"],
    }
    if len(per_run) == 1:
        intervals = run_intervals(group.runs[0], beta, per_run[0])
        row["interval"] = "95% bootstrap over episodes (Wilson for proportions)"
        for k in names:
            row[k] = per_run[0][k]
            row[f"{k}_low"], row[f"{k}_high"] = intervals.get(k, (math.nan, math.nan))
    else:
        row["interval"] = f"95% Student-t over {row['seeds']} seeds"
        for k in names:
            row[k], row[f"{k}_low"], row[f"{k}_high"] = seed_interval([v.get(k, math.nan) for v in per_run])
    for key, value in group.settings.items():
        row[f"config.{key}"] = value if isinstance(value, (int, float, str, bool)) else str(value)
    return row


def comparison_table(collected: Collection) -> pd.DataFrame:
    """report.csv: one row per group."""
    notes = degenerate_notes(collected.groups)
    rows = [group_row(g) | {"degenerate": "; ".join(notes.get(g.label, [])) or None} for g in collected.groups]
    if not rows:
        return pd.DataFrame(
            columns=[
                "group",
                "measure",
                "beta",
                "robots",
                "policy",
                "seeds",
                "mean",
                "cvar",
                "value_at_risk",
                "risky_fraction",
            ]
        )
    table = pd.DataFrame(rows)
    front = ["group", "measure", "beta", "robots", "policy", "seeds", "seed_list", "eval_episodes", "interval"]
    front += ["degenerate"]
    figures = [c for c in table.columns if c not in front and not c.startswith("config.")]
    config = [c for c in table.columns if c.startswith("config.")]
    return table[front + figures + config]


def degenerate_notes(groups: list[Group]) -> dict[str, list[str]]:
    """Each group that learned something degenerate, by label: its runs' findings (summary.json's diagnosis: no
    source reached, below the initial policy), and for a risk-averse group, whether it ended below the risk-neutral
    group of its world on its own objective (`below_neutral`)."""
    notes: dict[str, list[str]] = {}
    for group in groups:
        found: dict[str, list] = {}  # check -> [(seed, message)]
        for run in group.runs:
            for finding in degenerate_findings(run.run.summary or {}):
                found.setdefault(finding["check"], []).append((run.seed, finding["message"]))
        for check, seen in found.items():
            seeds = ", ".join(str(seed) for seed, _ in seen)
            notes.setdefault(group.label, []).append(f"{check} (seed {seeds}): {seen[0][1]}")
        below = below_neutral(group, groups)
        if below:
            notes.setdefault(group.label, []).append(f"below_neutral: {below}")
    return notes


def below_neutral(group: Group, groups: list[Group]) -> str | None:
    """Why a risk-averse group ended below the risk-neutral group of its world (the same world.* keys and team
    size, the nearest such group) on its own objective, with 95% intervals apart; None when it did not, or when
    there is no such group."""
    neutral = [
        g
        for g in groups
        if g.measure == "neutral" and g.robots == group.robots and flat_world(g.config) == flat_world(group.config)
    ]
    if group.measure == "neutral" or not neutral:
        return None
    other = min(neutral, key=lambda g: _distance(g.first.flat, group.first.flat))
    risk = {"measure": group.measure, **group.config.get("risk", {})}
    own, theirs = objective_figure(group, risk), objective_figure(other, risk)
    if not own[2] < theirs[1]:
        return None
    return (
        f"on its own objective ({measure_name(group)}) it ended below the risk-neutral group '{other.label}': "
        f"{own[0]:.1f} [{own[1]:.1f}, {own[2]:.1f}] against {theirs[0]:.1f} [{theirs[1]:.1f}, {theirs[2]:.1f}] "
        f"(95% intervals apart): its training likely stalled in a poor local optimum (one that goes nowhere when "
        f"few episodes reach a source); try another train.theta0, a smaller train.step_size or a soft-risk "
        f"risk.schedule"
    )


def objective_figure(group: Group, risk: dict) -> tuple[float, float, float]:
    """(value, low, high): the measure `risk` of the group's headline policies, with a 95% interval as
    group_row's: over the evaluation episodes for one seed (the bootstrap of summary.json's objective), else
    Student-t over the seeds."""
    returns = [r.eval_of().total_reward.to_numpy(dtype=float) for r in group.runs]
    if len(returns) > 1:
        return seed_interval([objective(z, risk) for z in returns])
    run = group.runs[0]
    resamples = int(run.config.get("train", {}).get("bootstrap", MAX_BOOTSTRAP))
    figure, _ = objective_interval(returns[0], risk, max(1, min(resamples, MAX_BOOTSTRAP)), run.seed)
    return figure["value"], figure["low"], figure["high"]


def used_row(r, group: str) -> dict:
    """The runs table's row of a run the report used, under `group`."""
    v = run_values(r)
    return {
        "path": str(r.path),
        "status": "used",
        "group": group,
        "seed": r.seed,
        "note": "tables rebuilt from run.mcap" if r.rebuilt else f"{RUN_LOG} cut short" if r.log_cut else "",
        "iterations": int(r.run.metrics.iteration.max()) + 1,
        "mean": v["mean"],
        "cvar": v["cvar"],
        "value_at_risk": v["value_at_risk"],
        "theta_final": theta_text(r.final_theta()),
    }


def runs_table(collected: Collection) -> pd.DataFrame:
    """Every run directory found: used (with its group and figures), duplicate (its config and seed repeat a used
    run's: the same sample, counted once) or skipped (with the reason)."""
    rows = [used_row(r, r.group.label if r.group else "") for r in collected.runs]
    for study in collected.studies:  # reproduce's studies: their runs, labelled by study and group
        rows += [
            used_row(r, f"{study.name}: {r.group.label}" if r.group else study.name) for r in study.collection.runs
        ]
    groups = {row["path"]: row["group"] for row in rows}
    for d in collected.duplicates:
        rows.append(
            {
                "path": str(d.path),
                "status": "duplicate",
                "group": groups.get(str(d.of.path), ""),
                "seed": d.seed,
                "note": f"the same config and seed as {d.of.path}: one sample, counted once",
            }
        )
    for scan in collected.landscapes:
        rows.append(
            {
                "path": str(scan.path),
                "status": "landscape",
                "group": "",
                "seed": scan.summary.get("seed"),
                "note": f"{scan.summary.get('points', '?')}^2 grid x {scan.summary.get('episodes', '?')} episodes",
            }
        )
    for b in collected.broken:
        rows.append({"path": str(b.path), "status": "skipped", "note": b.reason})
    table = pd.DataFrame(
        rows,
        columns=[
            "path",
            "status",
            "group",
            "seed",
            "note",
            "iterations",
            "mean",
            "cvar",
            "value_at_risk",
            "theta_final",
        ],
    )
    return table.astype({"seed": "Int64", "iterations": "Int64"})


LONG_THETA = 8  # a theta longer than this (a tabular policy's C*5 logits) is summarised in the runs table


def theta_text(theta: list[float]) -> str:
    """A final theta as text: its values, or for a long one (a table of logits) its length and range."""
    if len(theta) > LONG_THETA:
        finite = [t for t in theta if math.isfinite(t)]
        span = f" in [{min(finite):.3f}, {max(finite):.3f}]" if finite else ""
        return f"{len(theta)} values{span}"
    return " ".join(f"{t:.3f}" if math.isfinite(t) else "n/a" for t in theta)


def soft_risk_table(collected: Collection) -> pd.DataFrame:
    """soft_risk.csv: per seed, each soft-risk group (risk.schedule.kind other than none) and the group that differs
    from it only in risk.schedule (kind=none, the paper): the final policy's evaluated figures at risk.beta."""
    rows = []
    seen: set[int] = set()
    for scheduled, plain in schedule_pairs(collected.groups):
        for g in ([plain] if plain is not None else []) + [scheduled]:
            if id(g) in seen:
                continue
            seen.add(id(g))
            for r in g.runs:
                values = run_values(r, g.beta)
                rows.append(
                    {
                        "group": g.label,
                        "schedule": g.schedule,
                        "schedule_start": r.flat.get(KEYS.risk.schedule.start),
                        "schedule_iterations": r.flat.get(KEYS.risk.schedule.iterations),
                        "beta": g.beta,
                        "seed": r.seed,
                        "mean": values["mean"],
                        "cvar": values["cvar"],
                        **{k: v for k, v in values.items() if k.startswith("reached_")},
                        "theta_final": " ".join(f"{t:.1f}" for t in r.final_theta()),
                    }
                )
    return pd.DataFrame(rows)


def runs_on(scan, collected: Collection) -> list[RunInfo]:
    """The runs trained on the landscape's world (same world config and theta length) for one of its objectives:
    the mean, or CVaR at the landscape's beta (a beta sweep's other levels climb surfaces it does not show)."""
    world = {k: v for k, v in flat_world(scan.config).items()}
    out = []
    for r in collected.runs:
        risk = r.config.get("risk", {})
        shown = risk.get("measure") == "neutral" or (
            risk.get("measure", "cvar") == "cvar" and math.isclose(float(risk.get("beta", -1.0)), scan.beta)
        )
        team = r.config.get("team") or {}
        if team.get("starts") or team.get("risk") or team.get("faults"):
            shown = False  # a heterogeneous or faulty team climbs another objective than this world's from its start
        if shown and flat_world(r.config) == world and _same_theta(r, scan):
            out.append(r)
    return out


def _same_theta(run: RunInfo, scan) -> bool:
    """Whether the run's theta means what the landscape's does: the same names (its policy.features, in order),
    or, where either predates theta_names, the same length."""
    names, own = (run.run.summary or {}).get("theta_names"), scan.summary.get("theta_names")
    if isinstance(names, list) and isinstance(own, list):
        return names == own
    return len(run.final_theta()) == len(scan.summary.get("theta_fixed", [0, 0]))


def flat_world(config: dict) -> dict:
    return {k: v for k, v in flatten(config).items() if k.startswith("world.")}


def csv_text(table: pd.DataFrame) -> str:
    """A table as CSV text: a missing or non-finite value (NaN, +-inf) is an empty cell, never 'nan' or 'inf'."""
    clean = table.copy()
    for column in clean.columns:
        if pd.api.types.is_float_dtype(clean[column]):
            clean[column] = clean[column].where(np.isfinite(clean[column]))
        elif clean[column].dtype == object:
            clean[column] = clean[column].map(_finite_or_none)
    return clean.to_csv(index=False)


def _finite_or_none(value):
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return None
    return value


def ratio(numerator: float, denominator: float) -> float:
    """numerator / denominator, NaN (shown as missing) when it is undefined."""
    if not (math.isfinite(numerator) and math.isfinite(denominator)) or denominator == 0:
        return math.nan
    return numerator / denominator


def landscape_table(collected: Collection) -> pd.DataFrame:
    """Per landscape and group on its world: the grid optima and the group's final theta, distance and gap."""
    rows = []
    for scan in collected.landscapes:
        a, b = scan.axes
        best = {k: scan.best(k) for k in ("mean", "cvar")}
        thetas = scan.table[[f"theta_{a}", f"theta_{b}"]].to_numpy(float)
        base = {
            "landscape": str(scan.path),
            "beta": scan.beta,
            "episodes": scan.summary.get("episodes"),
            "points": scan.summary.get("points"),
            "best_mean_theta": _fmt_theta(best["mean"]["theta"], a, b),
            "best_mean": best["mean"]["value"],
            "best_cvar_theta": _fmt_theta(best["cvar"]["theta"], a, b),
            "best_cvar": best["cvar"]["value"],
        }
        groups: dict[str, list[RunInfo]] = {}
        for r in runs_on(scan, collected):
            groups.setdefault(r.group.label, []).append(r)
        if not groups:
            rows.append(base)
        for label, runs in groups.items():
            finals = np.array([[r.final_theta()[a], r.final_theta()[b]] for r in runs])
            final = finals.mean(axis=0)
            target = "mean" if runs[0].group.measure == "neutral" else "cvar"
            found = best[target]["theta"] is not None
            opt = np.array([best[target]["theta"][a], best[target]["theta"][b]]) if found else np.full(2, np.nan)
            nearest = int(np.argmin(((thetas - final) ** 2).sum(axis=1)))
            value_there = float(scan.table[target].iloc[nearest])
            se_column = f"{target}_se"
            best_index = scan.best_index(target)
            se = (
                float(scan.table[se_column].iloc[best_index])
                if se_column in scan.table and best_index is not None
                else math.nan
            )
            smooth = scan.smoothed_best(target)
            smooth_theta = np.array(smooth["theta"] if smooth["theta"] is not None else [np.nan, np.nan], float)
            gap = best[target]["value"] - value_there
            rows.append(
                {
                    **base,
                    "group": label,
                    "seeds": len(runs),
                    "objective": target,
                    "final_theta": pair_text(final),
                    "distance_to_optimum": float(np.linalg.norm(final - opt)),
                    "smoothed_optimum_theta": pair_text(smooth_theta),
                    "distance_to_smoothed_optimum": float(np.linalg.norm(final - smooth_theta)),
                    "landscape_at_final": value_there,
                    "gap_to_optimum": gap,
                    "gap_percent": 100 * ratio(gap, abs(best[target]["value"])),
                    "standard_error_at_optimum": se,
                    "grid_step": float(np.diff(np.unique(thetas[:, 0]))[0])
                    if len(np.unique(thetas[:, 0])) > 1
                    else math.nan,
                }
            )
    return pd.DataFrame(rows)


def _fmt_theta(theta: list[float] | None, a: int, b: int) -> str:
    return "n/a" if theta is None else pair_text((theta[a], theta[b]))


def pair_text(pair) -> str:
    if not all(math.isfinite(v) for v in pair):
        return "n/a"
    return f"({_coordinate(pair[0])}, {_coordinate(pair[1])})"


def _coordinate(value: float) -> str:
    """One decimal, as a reader compares thetas; a huge one (a --range=0,1e200 grid) in exponent form, not as the
    hundreds of digits of its float."""
    return f"{value:.1f}" if abs(value) < 1e6 else f"{value:.4g}"
