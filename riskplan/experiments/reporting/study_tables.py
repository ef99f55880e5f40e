"""The report's tables of the studies beyond the paper (riskplan reproduce's measures/, policies/ and tabular/,
hetero_team/ and hetero_central/, faults/ and faults_free/, floor_plan/): `measures_table` (risk measures),
`policies_table` (policies that see more, against the landscape's best CVaR), `hetero_table` (a heterogeneous team's
orders against the centralized run), `faults_table` (aggregations under a faulty robot against the fault-free team)
and `floor_plan_table`, all as `study_tables`. Each picks its groups from any collection (so `riskplan report` on a
sweep of its own draws them too) and is empty when the collection holds none.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd

from riskplan.config.keys import KEYS
from riskplan.engine.risk_measures import objective
from riskplan.experiments.reporting.collect import (
    MEASURE_ORDER,
    Collection,
    Group,
    RunInfo,
    theta_columns,
)
from riskplan.experiments.reporting.labels import fault_name, measure_name, policy_name
from riskplan.experiments.reporting.stats import seed_interval
from riskplan.experiments.reporting.tables import (
    LONG_THETA,
    flat_world,
    group_row,
    pair_text,
    ratio,
    run_values,
    source_names,
    theta_text,
)
from riskplan.run.metrics_rows import AVERAGE

FLOOR_PLAN = "floor_plan"  # the floor-plan study's experiment (conf/experiment/floor_plan.yaml)
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


def measure_groups(collected: Collection) -> list[Group]:
    """One robot's groups that differ only in their risk measure (risk.*), when one of them is not CVaR or the mean,
    in MEASURE_ORDER."""
    alone = [g for g in collected.groups if not g.team]
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


def measures_table(collected: Collection) -> pd.DataFrame:
    """measures.csv: per risk measure, its final policy's trained objective, mean, CVaR at the common level,
    P(risky) and the shares of episodes reaching each source (report.csv's figures and intervals); and under_<m>:
    the policy scored by each measure m of the comparison (the mean over the seeds), so that each measure's own
    policy can be set against the others' under that measure."""
    groups = measure_groups(collected)
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


def policy_groups(collected: Collection) -> list[Group]:
    """One robot's groups that differ only in their policy (policy.kind, policy.features): the paper's first."""
    alone = [g for g in collected.groups if not g.team]
    family = _family(
        alone,
        ("policy.",),
        lambda g: (g.policy_kind, tuple(g.features)),
        lambda gs: len({(g.policy_kind, tuple(g.features)) for g in gs}) > 1,
    )
    return sorted(family, key=lambda g: (g.policy_kind == "tabular", len(g.features), g.features))


def landscape_for(collected: Collection, group: Group):
    """The landscape of the group's world at its CVaR level (the paper's 2-parameter policy over a grid of theta),
    or None."""
    world = flat_world(group.config)
    for scan in collected.landscapes:
        policy = scan.config.get("policy") or {}
        features = list(policy.get("features") or ["signals"])
        paper = policy.get("kind", "features") == "features" and features == ["signals"]  # not other features' weights
        if paper and flat_world(scan.config) == world and math.isclose(scan.beta, group.beta):
            return scan
    return None


def policies_table(collected: Collection) -> pd.DataFrame:
    """policies.csv: per policy, its length of theta, its final policy's figures (report.csv's), the seeds that reach
    each source, and the best CVaR over the landscape's grid of the paper's 2-parameter policy, with the gap to it."""
    groups = policy_groups(collected)
    if not groups:
        return pd.DataFrame()
    rows = []
    for g in groups:
        row = group_row(g)
        names = (g.first.run.summary or {}).get("theta_names") or []
        scan = landscape_for(collected, g)
        best = scan.best("cvar") if scan is not None else {"theta": None, "value": math.nan}
        smooth = scan.smoothed_best("cvar") if scan is not None else {"theta": None, "value": math.nan}
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
                "landscape_best_theta": pair_text(best["theta"]) if best["theta"] is not None else "n/a",
                "landscape_smoothed_best_cvar": smooth["value"],
                "gap_to_landscape_best": gap,
                "gap_percent": 100 * ratio(gap, abs(best["value"])),
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


def hetero_groups(collected: Collection) -> tuple[list[Group], Group | None]:
    """Heterogeneous teams (team.starts or team.risk) that differ in their order or graph: (the distributed groups,
    the centralized comparator or None)."""
    teams = [g for g in collected.groups if g.heterogeneous]
    varying = (
        KEYS.team.order,
        KEYS.team.graph,
        KEYS.team.weights,
        KEYS.team.edges,
        KEYS.team.radius,
        KEYS.team.directed,
    )
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
    return float(late_rows(run, AVERAGE).consensus_error.astype(float).mean())


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


def hetero_table(collected: Collection) -> pd.DataFrame:
    """hetero_team.csv: per order (and the centralized comparator), the consensus error's floor, the disagreement that
    persists, the team objective at theta-bar, and its gap and distance to the centralized run of the same seed."""
    distributed, central = hetero_groups(collected)
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
                    "consensus_final", [float(r.metrics_of(AVERAGE).consensus_error.iloc[-1]) for r in g.runs]
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


def fault_groups(collected: Collection) -> tuple[list[Group], Group | None]:
    """Teams that differ only in their faults and aggregation, one of them with faults: (the faulty groups, the
    fault-free comparator with the plain mean, or None)."""
    teams = [g for g in collected.groups if g.team]
    family = _family(
        teams,
        (KEYS.team.faults, KEYS.team.aggregate, KEYS.team.trim),
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
    return ratio(mine - theirs, abs(theirs))


def faults_table(collected: Collection) -> pd.DataFrame:
    """faults.csv: per aggregation under the faults, and the fault-free team, the healthy robots' theta-bar on its
    evaluation episodes (report.csv's figures), and its CVaR against the fault-free run of the same seed."""
    faulty, free = fault_groups(collected)
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


def study_tables(collected: Collection) -> dict[str, pd.DataFrame]:
    """The studies' tables of a collection (name -> table; empty tables for the studies it does not hold)."""
    return {
        "measures": measures_table(collected),
        "policies": policies_table(collected),
        "hetero_team": hetero_table(collected),
        "faults": faults_table(collected),
        "floor_plan": floor_plan_table(collected),
    }


def floor_plan_table(collected: Collection) -> pd.DataFrame:
    """floor_plan.csv: per policy of the floor-plan study (experiment=floor_plan, the shipped map), its mean, CVaR,
    P(risky) and the shares of episodes reaching each source (report.csv's figures and intervals). Runs on a map of
    another experiment are no part of it: report.csv has them."""
    groups = [g for g in collected.groups if g.config.get("experiment") == FLOOR_PLAN]
    rows = [{**group_row(g), "name": measure_name(g), **seeds_reaching(g)} for g in groups]
    return pd.DataFrame(rows)
