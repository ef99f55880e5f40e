"""The report's tables, recomputed from the runs' evaluation episodes (never from summaries).

- `comparison_table`: one row per group (condition), the headline policy's final mean, CVaR, VaR at the group's
  risk.beta, P(risky) and P(source j reached), each with a 95% interval. With one seed the interval is a
  percentile bootstrap over the evaluation episodes (the run's seed and train.bootstrap, as in summary.json) and
  a Wilson interval for proportions; with several seeds the point is the across-seed mean and the interval a
  Student-t interval over the seeds. This is report.csv.
- `runs_table`: every run found, used, duplicate (its config and seed repeat a used run's) or skipped (with
  the reason).
- `landscape_table`: per landscape, its optima and how far each group's trained theta ended from them.
- `soft_risk_table`: per seed, each soft-risk group (risk.schedule) against its twin with the paper's fixed beta.
- The studies beyond the paper (`study_tables`): `measures_table` (risk measures), `policies_table` (policies that
  see more, against the landscape's best CVaR), `hetero_table` (a heterogeneous team's orders against the
  centralized run), `faults_table` (aggregations under a faulty robot against the fault-free team).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd

from riskplan.engine.risk_measures import cvar, objective, value_at_risk
from riskplan.experiments.reporting.collect import AVERAGE as AVERAGE_ROBOT
from riskplan.experiments.reporting.collect import (
    MEASURE_ORDER,
    Collection,
    Group,
    RunInfo,
    fault_name,
    flatten,
    measure_name,
    policy_name,
    schedule_pairs,
    theta_columns,
)
from riskplan.experiments.reporting.stats import seed_interval, wilson
from riskplan.run.intervals import bootstrap_intervals

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


def comparison_table(coll: Collection) -> pd.DataFrame:
    """report.csv: one row per group."""
    rows = [group_row(g) for g in coll.groups]
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
    figures = [c for c in table.columns if c not in front and not c.startswith("config.")]
    config = [c for c in table.columns if c.startswith("config.")]
    return table[front + figures + config]


def used_row(r, group: str) -> dict:
    """The runs table's row of a run the report used, under `group`."""
    v = run_values(r)
    return {
        "path": str(r.path),
        "status": "used",
        "group": group,
        "seed": r.seed,
        "note": "tables rebuilt from run.mcap" if r.rebuilt else "",
        "iterations": int(r.run.metrics.iteration.max()) + 1,
        "mean": v["mean"],
        "cvar": v["cvar"],
        "value_at_risk": v["value_at_risk"],
        "theta_final": theta_text(r.final_theta()),
    }


def runs_table(coll: Collection) -> pd.DataFrame:
    """Every run directory found: used (with its group and figures), duplicate (its config and seed repeat a used
    run's: the same sample, counted once) or skipped (with the reason)."""
    rows = [used_row(r, r.group.label if r.group else "") for r in coll.runs]
    for study in coll.studies:  # reproduce's studies: their runs, labelled by study and group
        rows += [
            used_row(r, f"{study.name}: {r.group.label}" if r.group else study.name) for r in study.collection.runs
        ]
    groups = {row["path"]: row["group"] for row in rows}
    for d in coll.duplicates:
        rows.append(
            {
                "path": str(d.path),
                "status": "duplicate",
                "group": groups.get(str(d.of.path), ""),
                "seed": d.seed,
                "note": f"the same config and seed as {d.of.path}: one sample, counted once",
            }
        )
    for land in coll.landscapes:
        rows.append(
            {
                "path": str(land.path),
                "status": "landscape",
                "group": "",
                "seed": land.summary.get("seed"),
                "note": f"{land.summary.get('points', '?')}^2 grid x {land.summary.get('episodes', '?')} episodes",
            }
        )
    for b in coll.broken:
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


def soft_risk_table(coll: Collection) -> pd.DataFrame:
    """soft_risk.csv: per seed, each soft-risk group (risk.schedule.kind other than none) and the group that differs
    from it only in risk.schedule (kind=none, the paper): the final policy's evaluated figures at risk.beta."""
    rows = []
    seen: set[int] = set()
    for scheduled, plain in schedule_pairs(coll.groups):
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
                        "schedule_start": r.flat.get("risk.schedule.start"),
                        "schedule_iterations": r.flat.get("risk.schedule.iterations"),
                        "beta": g.beta,
                        "seed": r.seed,
                        "mean": values["mean"],
                        "cvar": values["cvar"],
                        **{k: v for k, v in values.items() if k.startswith("reached_")},
                        "theta_final": " ".join(f"{t:.1f}" for t in r.final_theta()),
                    }
                )
    return pd.DataFrame(rows)


def runs_on(land, coll: Collection) -> list[RunInfo]:
    """The runs trained on the landscape's world (same world config and theta length) for one of its objectives:
    the mean, or CVaR at the landscape's beta (a beta sweep's other levels climb surfaces it does not show)."""
    world = {k: v for k, v in _flat_world(land.config).items()}
    out = []
    for r in coll.runs:
        risk = r.config.get("risk", {})
        shown = risk.get("measure") == "neutral" or (
            risk.get("measure", "cvar") == "cvar" and math.isclose(float(risk.get("beta", -1.0)), land.beta)
        )
        team = r.config.get("team") or {}
        if team.get("starts") or team.get("risk") or team.get("faults"):
            shown = False  # a heterogeneous or faulty team climbs another objective than this world's from its start
        if (
            shown
            and _flat_world(r.config) == world
            and len(r.final_theta()) == len(land.summary.get("theta_fixed", [0, 0]))
        ):
            out.append(r)
    return out


def _flat_world(config: dict) -> dict:
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


def _ratio(numerator: float, denominator: float) -> float:
    """numerator / denominator, NaN (shown as missing) when it is undefined."""
    if not (math.isfinite(numerator) and math.isfinite(denominator)) or denominator == 0:
        return math.nan
    return numerator / denominator


def landscape_table(coll: Collection) -> pd.DataFrame:
    """Per landscape and group on its world: the grid optima and the group's final theta, distance and gap."""
    rows = []
    for land in coll.landscapes:
        a, b = land.axes
        best = {k: land.best(k) for k in ("mean", "cvar")}
        thetas = land.table[[f"theta_{a}", f"theta_{b}"]].to_numpy(float)
        base = {
            "landscape": str(land.path),
            "beta": land.beta,
            "episodes": land.summary.get("episodes"),
            "points": land.summary.get("points"),
            "best_mean_theta": _fmt_theta(best["mean"]["theta"], a, b),
            "best_mean": best["mean"]["value"],
            "best_cvar_theta": _fmt_theta(best["cvar"]["theta"], a, b),
            "best_cvar": best["cvar"]["value"],
        }
        groups: dict[str, list[RunInfo]] = {}
        for r in runs_on(land, coll):
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
            value_there = float(land.table[target].iloc[nearest])
            se_column = f"{target}_se"
            best_index = land.best_index(target)
            se = (
                float(land.table[se_column].iloc[best_index])
                if se_column in land.table and best_index is not None
                else math.nan
            )
            smooth = land.smoothed_best(target)
            smooth_theta = np.array(smooth["theta"] if smooth["theta"] is not None else [np.nan, np.nan], float)
            gap = best[target]["value"] - value_there
            rows.append(
                {
                    **base,
                    "group": label,
                    "seeds": len(runs),
                    "objective": target,
                    "final_theta": f"({final[0]:.1f}, {final[1]:.1f})",
                    "distance_to_optimum": float(np.linalg.norm(final - opt)),
                    "smoothed_optimum_theta": _fmt_pair(smooth_theta),
                    "distance_to_smoothed_optimum": float(np.linalg.norm(final - smooth_theta)),
                    "landscape_at_final": value_there,
                    "gap_to_optimum": gap,
                    "gap_percent": 100 * _ratio(gap, abs(best[target]["value"])),
                    "standard_error_at_optimum": se,
                    "grid_step": float(np.diff(np.unique(thetas[:, 0]))[0])
                    if len(np.unique(thetas[:, 0])) > 1
                    else math.nan,
                }
            )
    return pd.DataFrame(rows)


def _fmt_theta(theta: list[float] | None, a: int, b: int) -> str:
    return "n/a" if theta is None else _fmt_pair((theta[a], theta[b]))


def _fmt_pair(pair) -> str:
    if not all(math.isfinite(v) for v in pair):
        return "n/a"
    return f"({pair[0]:.1f}, {pair[1]:.1f})"


# ------------------------------------------------------------------------------------------------ studies
# The tables of the studies beyond the paper (riskplan reproduce's measures/, policies/ and tabular/, hetero_team/
# and hetero_central/, faults/ and faults_free/). Each picks its groups from any collection (so `riskplan report`
# on a sweep of its own draws them too) and is empty when the collection holds none.

LATE = 0.25  # the last quarter of the iterations: where a constant step's floor is measured


def _rest(group: Group, varying: tuple[str, ...]) -> tuple:
    """The group's config without the keys that start with one of `varying` (and without the seed)."""
    return tuple(sorted((k, str(v)) for k, v in group.first.flat.items() if not k.startswith(varying)))


def _family(groups: list[Group], varying: tuple[str, ...], kind, wanted) -> list[Group]:
    """The largest set of groups that agree on every key but those starting with `varying`, among which `kind(g)`
    takes the most distinct values; [] when `wanted(family)` says it is not a comparison of that kind."""
    families: dict[tuple, list[Group]] = {}
    for g in groups:
        families.setdefault(_rest(g, varying), []).append(g)
    best = max(families.values(), key=lambda gs: (len({kind(g) for g in gs}), len(gs)), default=[])
    return best if best and wanted(best) else []


def measure_groups(coll: Collection) -> list[Group]:
    """One robot's groups that differ only in their risk measure (risk.*), when one of them is not CVaR or the mean,
    in MEASURE_ORDER."""
    alone = [g for g in coll.groups if not g.team]
    family = _family(
        alone,
        ("risk.",),
        lambda g: g.measure,
        lambda gs: len({g.measure for g in gs}) > 1 and any(g.measure not in ("cvar", "neutral") for g in gs),
    )
    order = {m: i for i, m in enumerate(MEASURE_ORDER)}
    return sorted(family, key=lambda g: (order.get(g.measure, len(order)), g.beta, g.eta, g.weight))


def run_objective(run: RunInfo, risk: dict | None = None) -> float:
    """The measure the run trained (its risk node), or the node `risk`, on its headline policy's evaluation
    episodes."""
    # a writable copy: the numba kernels behind objective() then run on the arrays training gives them (a read-only
    # parquet column would compile and cache a second signature of each kernel)
    z = np.array(run.eval_of().total_reward.to_numpy(dtype=float), dtype=float, copy=True)
    return float(objective(z, run.config.get("risk", {}) if risk is None else risk))


def measures_table(coll: Collection) -> pd.DataFrame:
    """measures.csv: per risk measure, its final policy's trained objective, mean, CVaR at the common level,
    P(risky) and the shares of episodes reaching each source (report.csv's figures and intervals); and under_<m>:
    the policy scored by each measure m of the comparison (the mean over the seeds), so that each measure's own
    policy can be set against the others' under that measure."""
    groups = measure_groups(coll)
    if not groups:
        return pd.DataFrame()
    level = _common_beta(groups)
    measures = {g.measure: g.config.get("risk", {}) for g in groups}  # each measure's node, to score every policy
    rows = []
    for g in groups:
        row = group_row(g, beta=level)
        values = [run_objective(r) for r in g.runs]
        under = {f"under_{m}": float(np.mean([run_objective(r, node) for r in g.runs])) for m, node in measures.items()}
        if len(values) > 1:
            row["objective"], row["objective_low"], row["objective_high"] = seed_interval(values)
        else:
            own = (g.first.run.summary or {}).get("objective") or {}
            row["objective"] = values[0]
            row["objective_low"], row["objective_high"] = own.get("low", math.nan), own.get("high", math.nan)
        rows.append(
            {
                "group": g.label,
                "measure": g.measure,
                "name": measure_name(g),
                "risk_beta": g.beta,
                "risk_eta": g.eta if g.measure in ("wang", "entropic") else math.nan,
                "risk_weight": g.weight if g.measure == "mean_cvar" else math.nan,
                **{k: v for k, v in row.items() if k not in ("group", "measure", "robots", "policy")},
                **seeds_reaching(g),
                **under,
            }
        )
    return pd.DataFrame(rows)


def _common_beta(groups: list[Group]) -> float:
    betas = [g.beta for g in groups]
    return max(set(betas), key=lambda b: (betas.count(b), -abs(b - 0.1)))


def seeds_reaching(group: Group, share: float = 0.5) -> dict[str, int]:
    """seeds_reaching_<source> (and _none): the seeds whose final policy reaches that source (none: no source) in more
    than `share` of its evaluation episodes."""
    out = {}
    names = source_names(group.config)
    for j, name in [*enumerate(names), (-1, "none")]:
        out[f"seeds_reaching_{name}"] = sum(
            int(
                (
                    (r.eval_of().source_reached.to_numpy() == j)
                    if j >= 0
                    else (r.eval_of().source_reached.to_numpy() < 0)
                ).mean()
                > share
            )
            for r in group.runs
        )
    return out


def policy_groups(coll: Collection) -> list[Group]:
    """One robot's groups that differ only in their policy (policy.kind, policy.features): the paper's first."""
    alone = [g for g in coll.groups if not g.team]
    family = _family(
        alone,
        ("policy.",),
        lambda g: (g.policy_kind, tuple(g.features)),
        lambda gs: len({(g.policy_kind, tuple(g.features)) for g in gs}) > 1,
    )
    return sorted(family, key=lambda g: (g.policy_kind == "tabular", len(g.features), g.features))


def landscape_for(coll: Collection, group: Group):
    """The landscape of the group's world at its CVaR level (the paper's 2-parameter policy over a grid of theta),
    or None."""
    world = _flat_world(group.config)
    for land in coll.landscapes:
        if _flat_world(land.config) == world and math.isclose(land.beta, group.beta):
            return land
    return None


def policies_table(coll: Collection) -> pd.DataFrame:
    """policies.csv: per policy, its length of theta, its final policy's figures (report.csv's), the seeds that reach
    each source, and the best CVaR over the landscape's grid of the paper's 2-parameter policy, with the gap to it."""
    groups = policy_groups(coll)
    if not groups:
        return pd.DataFrame()
    rows = []
    for g in groups:
        row = group_row(g)
        names = (g.first.run.summary or {}).get("theta_names") or []
        land = landscape_for(coll, g)
        best = land.best("cvar") if land is not None else {"theta": None, "value": math.nan}
        smooth = land.smoothed_best("cvar") if land is not None else {"theta": None, "value": math.nan}
        gap = best["value"] - row["cvar"]
        rows.append(
            {
                "group": g.label,
                "policy": policy_name(g),
                "kind": g.policy_kind,
                "features": " ".join(g.features) if g.policy_kind == "features" else "",
                "theta_length": len(g.first.final_theta()),
                "theta_names": " ".join(names) if len(names) <= LONG_THETA else f"{len(names)} (cell, move) logits",
                "theta0": g.first.flat.get("train.theta0"),
                **{k: v for k, v in row.items() if k not in ("group", "measure", "robots", "policy")},
                **seeds_reaching(g),
                "landscape_best_cvar": best["value"],
                "landscape_best_theta": _fmt_pair(best["theta"]) if best["theta"] is not None else "n/a",
                "landscape_smoothed_best_cvar": smooth["value"],
                "gap_to_landscape_best": gap,
                "gap_percent": 100 * _ratio(gap, abs(best["value"])),
            }
        )
    return pd.DataFrame(rows)


def _is_central(group: Group) -> bool:
    """A team that averages exactly every round: the complete graph with uniform weights (max_degree, or Metropolis,
    which is uniform on a complete graph), adapt-then-combine, no delays, drops or faults: centralized gradient ascent
    on the team objective."""
    t = group.team_conf
    return (
        group.team
        and str(t.get("graph")) == "complete"
        and str(t.get("weights", "metropolis")) in ("max_degree", "metropolis")
        and str(t.get("order", "combine_then_adapt")) == "adapt_then_combine"
        and not (t.get("delay") or {}).get("max")
        and not t.get("drop")
        and not t.get("faults")
    )


def hetero_groups(coll: Collection) -> tuple[list[Group], Group | None]:
    """Heterogeneous teams (team.starts or team.risk) that differ in their order or graph: (the distributed groups,
    the centralized comparator or None)."""
    teams = [g for g in coll.groups if g.heterogeneous]
    varying = ("team.order", "team.graph", "team.weights", "team.edges", "team.radius", "team.directed")
    family = _family(teams, varying, lambda g: (str(g.team_conf.get("order")), str(g.team_conf.get("graph"))), bool)
    central = [g for g in family if _is_central(g)]
    distributed = [g for g in family if not _is_central(g)]
    order = ("combine_then_adapt", "adapt_then_combine", "gradient_tracking")
    distributed.sort(
        key=lambda g: (order.index(o) if (o := str(g.team_conf.get("order"))) in order else 3, str(g.label))
    )
    return distributed, (central[0] if central else None)


def late_rows(run: RunInfo, robot: int | None = None) -> pd.DataFrame:
    """The metrics rows of the last quarter (LATE) of a run's iterations, of one robot (default: the headline)."""
    m = run.metrics_of(robot) if robot is not None else run.metrics_of()
    last = int(m.iteration.max()) + 1
    first = last - max(1, round(LATE * last))
    return m[m.iteration >= first]


def consensus_floor(run: RunInfo) -> float:
    """The mean consensus error over the last quarter of the iterations (robot -1 rows)."""
    return float(late_rows(run, AVERAGE_ROBOT).consensus_error.astype(float).mean())


def theta_disagreement(run: RunInfo) -> float:
    """The largest distance between two healthy robots' theta averaged over the last quarter of the iterations: the
    disagreement that persists (sampling noise averages out; a heterogeneous floor does not)."""
    m = run.run.metrics
    cols = theta_columns(m)
    last = int(m.iteration.max()) + 1
    late = m[(m.robot >= 0) & (m.iteration >= last - max(1, round(LATE * last)))]
    if "healthy" in late:
        late = late[late.healthy.astype(bool)]
    means = late.groupby("robot")[cols].mean().to_numpy(float)
    if len(means) < 2:
        return math.nan
    return float(max(np.linalg.norm(means[i] - means[j]) for i in range(len(means)) for j in range(i + 1, len(means))))


def team_objective(run: RunInfo) -> float:
    """summary.json's team objective: the sum of the robots' objectives at theta-bar, each from its own start."""
    value = ((run.run.summary or {}).get("team_objective") or {}).get("value")
    return float(value) if isinstance(value, (int, float)) else math.nan


def _paired(group: Group, reference: Group | None, value) -> list[float]:
    """value(run, reference run of the same seed) for every seed both groups hold."""
    if reference is None:
        return []
    by_seed = {r.seed: r for r in reference.runs}
    return [value(r, by_seed[r.seed]) for r in group.runs if r.seed in by_seed]


def _interval_columns(name: str, values: list[float]) -> dict:
    mean, low, high = seed_interval(values)
    return {name: mean, f"{name}_low": low, f"{name}_high": high}


def hetero_table(coll: Collection) -> pd.DataFrame:
    """hetero_team.csv: per order (and the centralized comparator), the consensus error's floor, the disagreement that
    persists, the team objective at theta-bar, and its gap and distance to the centralized run of the same seed."""
    distributed, central = hetero_groups(coll)
    if not distributed:
        return pd.DataFrame()
    rows = []
    for g in distributed + ([central] if central is not None else []):
        t = g.team_conf
        steps = g.first.metrics_of(0).step_size.astype(float)
        rows.append(
            {
                "group": g.label,
                "order": str(t.get("order", "combine_then_adapt")),
                "graph": str(t.get("graph")),
                "weights": str(t.get("weights")),
                "centralized": g is central,
                "robots": g.robots,
                "starts": len(t.get("starts") or []),
                "step_size": float(steps.iloc[-1]),
                "constant_step": bool(np.allclose(steps.to_numpy(), steps.iloc[0])),
                "iterations": int(g.first.run.metrics.iteration.max()) + 1,
                "seeds": len(g.runs),
                "seed_list": " ".join(str(s) for s in g.seeds),
                **_interval_columns("consensus_floor", [consensus_floor(r) for r in g.runs]),
                **_interval_columns(
                    "consensus_final", [float(r.metrics_of(AVERAGE_ROBOT).consensus_error.iloc[-1]) for r in g.runs]
                ),
                **_interval_columns("theta_disagreement", [theta_disagreement(r) for r in g.runs]),
                **_interval_columns("team_objective", [team_objective(r) for r in g.runs]),
                **_interval_columns(
                    "gap_to_central", _paired(g, central, lambda r, c: team_objective(c) - team_objective(r))
                ),
                "seeds_below_central": sum(
                    int(x > 0) for x in _paired(g, central, lambda r, c: team_objective(c) - team_objective(r))
                ),
                **_interval_columns(
                    "distance_to_central",
                    _paired(
                        g,
                        central,
                        lambda r, c: float(np.linalg.norm(np.subtract(r.final_theta(), c.final_theta()))),
                    ),
                ),
                "theta_final": theta_text(list(np.mean([r.final_theta() for r in g.runs], axis=0))),
            }
        )
    table = pd.DataFrame(rows)
    table["gap_percent"] = 100 * table["gap_to_central"] / table["team_objective"].abs()
    return table


def fault_groups(coll: Collection) -> tuple[list[Group], Group | None]:
    """Teams that differ only in their faults and aggregation, one of them with faults: (the faulty groups, the
    fault-free comparator with the plain mean, or None)."""
    teams = [g for g in coll.groups if g.team]
    family = _family(
        teams,
        ("team.faults", "team.aggregate", "team.trim"),
        lambda g: (json.dumps(g.faults, sort_keys=True), str(g.team_conf.get("aggregate"))),
        lambda gs: any(g.faults for g in gs),
    )
    free = [g for g in family if not g.faults]
    free.sort(key=lambda g: str(g.team_conf.get("aggregate", "mean")) != "mean")
    faulty = [g for g in family if g.faults]
    order = ("mean", "median", "trimmed_mean", "wmsr")
    faulty.sort(key=lambda g: (order.index(a) if (a := str(g.team_conf.get("aggregate"))) in order else 4, g.label))
    return faulty, (free[0] if free else None)


FAULT_TOLERANCE = 0.05  # "within 5%" of the fault-free team's CVaR


def _relative_cvar(run: RunInfo, reference: RunInfo, beta: float) -> float:
    """(CVaR of the run - CVaR of the reference) / |CVaR of the reference|, on their evaluation episodes."""
    mine, theirs = run_values(run, beta)["cvar"], run_values(reference, beta)["cvar"]
    return _ratio(mine - theirs, abs(theirs))


def faults_table(coll: Collection) -> pd.DataFrame:
    """faults.csv: per aggregation under the faults, and the fault-free team, the healthy robots' theta-bar on its
    evaluation episodes (report.csv's figures), and its CVaR against the fault-free run of the same seed."""
    faulty, free = fault_groups(coll)
    if not faulty:
        return pd.DataFrame()
    rows = []
    for g in faulty + ([free] if free is not None else []):
        row = group_row(g)
        relative = _paired(g, free, lambda r, c, beta=g.beta: _relative_cvar(r, c, beta))
        worst = max((abs(x) for x in relative), default=math.nan)
        t = g.team_conf
        rows.append(
            {
                "group": g.label,
                "name": fault_name(g),
                "faults": json.dumps(g.faults, sort_keys=True),
                "faulty_robots": len({f.get("robot") for f in g.faults if isinstance(f, dict)}),
                "aggregate": str(t.get("aggregate", "mean")),
                "trim": int(t.get("trim", 0) or 0),
                "fault_free": g is free,
                **{k: v for k, v in row.items() if k not in ("group", "measure", "policy")},
                **_interval_columns("cvar_vs_fault_free", relative),
                "worst_cvar_vs_fault_free": worst,
                "within_tolerance": bool(worst <= FAULT_TOLERANCE) if math.isfinite(worst) else None,
            }
        )
    return pd.DataFrame(rows)


def study_tables(coll: Collection) -> dict[str, pd.DataFrame]:
    """The studies' tables of a collection (name -> table; empty tables for the studies it does not hold)."""
    return {
        "measures": measures_table(coll),
        "policies": policies_table(coll),
        "hetero_team": hetero_table(coll),
        "faults": faults_table(coll),
        "floor_plan": floor_plan_table(coll),
    }


def floor_plan_table(coll: Collection) -> pd.DataFrame:
    """floor_plan.csv: per policy trained on a map (world.map), its mean, CVaR, P(risky) and the shares of episodes
    reaching each source (report.csv's figures and intervals)."""
    groups = [g for g in coll.groups if (g.config.get("world") or {}).get("map")]
    rows = [{**group_row(g), "name": measure_name(g), **seeds_reaching(g)} for g in groups]
    return pd.DataFrame(rows)
