"""What the report calls a group of runs: its label, made of the fewest config keys (in priority order) that tell
the groups apart, and the names of its measure, its policy and its team's faults (`riskplan.experiments.reporting.
collect` groups the runs and labels them here)."""

from __future__ import annotations

import itertools
import json
import math
from typing import Any, Protocol

from riskplan.config.keys import KEYS
from riskplan.engine.measures.registry import label, parameter_keys


class Group(Protocol):
    """What labelling reads of a group of runs (reporting.collect.Group, which imports this module, has it)."""

    label: str
    settings: dict[str, Any]  # its differing keys -> value
    config: dict
    measure: str
    beta: float
    robots: int
    team: bool
    team_conf: dict
    policy_kind: str
    features: list[str]
    faults: list


# Keys tried first when labelling groups (in this order); the rest follow alphabetically.
LABEL_PRIORITY = (
    KEYS.risk.measure,
    KEYS.risk.beta,
    KEYS.risk.schedule.kind,
    KEYS.team.robots,
    KEYS.team.graph,
    KEYS.team.weights,
    KEYS.team.delay.max,
    KEYS.team.drop,
    KEYS.team.consensus_rounds,
    KEYS.train.samples,
    "train.theta0",
    KEYS.experiment,
)


class Missing:
    def __repr__(self) -> str:
        return "(absent)"


MISSING = Missing()


def hashable(v: Any) -> Any:
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return v


def label_groups(groups: list[Group], differing: list[str]) -> None:
    """Label each group by the fewest differing keys (in priority order) that tell the groups apart."""
    if len(groups) == 1:
        groups[0].label = _describe(groups[0], [KEYS.risk.measure, KEYS.team.robots], single=True)
        return
    order = [k for k in LABEL_PRIORITY if k in differing] + [k for k in differing if k not in LABEL_PRIORITY]
    chosen: list[str] = []
    distinct = 1
    for k in order:
        trial = chosen + [k]
        count = len({tuple(hashable(g.settings.get(c, MISSING)) for c in trial) for g in groups})
        if count > distinct:
            chosen, distinct = trial, count
        if distinct == len(groups):
            break
    for g in groups:
        g.label = _describe(g, chosen)
    _tell_apart(groups, chosen)
    seen: dict[str, int] = {}  # labels still shared (values that differ only past what is shown) get a suffix
    for g in groups:
        if g.label in seen:
            seen[g.label] += 1
            g.label = f"{g.label} #{seen[g.label]}"
        else:
            seen[g.label] = 1


def _tell_apart(groups: list[Group], chosen: list[str]) -> None:
    """Groups that share a label (a long value such as world.sources, cut at 40 characters, or team.starts, shown
    as its count) get each such key's value where the groups' values first differ: 'world.sources=…"name": "b"…'."""
    sharing: dict[str, list[Group]] = {}
    for g in groups:
        sharing.setdefault(g.label, []).append(g)
    for same in (same for same in sharing.values() if len(same) > 1):
        for k in chosen:
            texts = [str(g.settings.get(k, MISSING)) for g in same]
            if len(set(texts)) == 1:
                continue
            first = next((i for i, chars in enumerate(zip(*texts)) if len(set(chars)) > 1), min(map(len, texts)))
            start = max(0, first - CONTEXT)
            for g, text in zip(same, texts, strict=True):
                piece = text[start : start + 3 * CONTEXT]
                piece = f"{'…' if start else ''}{piece}{'…' if start + 3 * CONTEXT < len(text) else ''}"
                cut = f"={_short(g.settings.get(k, MISSING))}"  # as _describe showed it, if it did
                g.label = g.label.replace(cut, f"={piece}", 1) if cut in g.label else f"{g.label}, {k}={piece}"


CONTEXT = 12  # characters shown before the first difference of a value that tells groups apart (and twice after)


def _describe(group: Group, keys: list[str], single: bool = False) -> str:
    """Human label from the chosen keys, e.g. 'risk-averse (CVaR β=0.1), distributed N=3', 'Wang (η=0.5)'."""
    parts = []
    keys = list(keys)
    handled = {KEYS.risk.measure, KEYS.risk.beta, KEYS.team.robots}
    risk = _risk(group)
    measure_named = False
    if (
        {KEYS.risk.measure, KEYS.risk.beta} & set(keys)
        or single
        or (parameter_keys(risk) - {KEYS.risk.beta}) & set(keys)
    ):
        # the measure's own label (riskplan.engine.measures), with a reporting β where it tells groups apart
        beta = group.beta if KEYS.risk.beta in keys and KEYS.risk.measure not in keys else None
        parts.append(label(risk, beta=beta))  # CVaR's β always: one name in every report
        measure_named = True
        handled |= {KEYS.risk.eta, KEYS.risk.weight} | {k for k in keys if k.startswith(f"{KEYS.risk.params}.")}
    if KEYS.team.robots in keys or single:
        parts.append(team_name(group))
    if {KEYS.policy.kind, KEYS.policy.features} & set(keys):
        parts.append(policy_name(group))
        handled |= {KEYS.policy.kind, KEYS.policy.features}
    if KEYS.team.risk in keys or (single and group.team_conf.get("risk")):
        parts.append(team_risk_name(group, named=measure_named))
        handled.add(KEYS.team.risk)
    if {KEYS.team.faults, KEYS.team.aggregate, KEYS.team.trim} & set(keys):
        parts.append(fault_name(group))
        handled |= {KEYS.team.faults, KEYS.team.aggregate, KEYS.team.trim}
    for k in keys:
        if k in handled:
            continue
        if k == KEYS.team.starts:
            starts = group.team_conf.get("starts")
            parts.append(f"{len(starts)} start cells" if starts else "one start cell")
            continue
        name = (
            "schedule"
            if k == KEYS.risk.schedule.kind
            else k.split(".", 1)[1]
            if k.startswith(("team.", "train.", f"{KEYS.risk.schedule}."))
            else k
        )
        parts.append(f"{name}={_short(group.settings.get(k))}")
    return ", ".join(parts) or "runs"


def measure_name(group: Group, beta: bool = True) -> str:
    """The measure a group trains, by name and parameters (the measure's label): 'risk-neutral', 'risk-averse
    (CVaR β=0.1)', 'Wang (η=0.5)', 'mean-CVaR (λ=0.5, β=0.1)', 'entropic (η=0.001)', 'power (gamma=0.5)'. The
    one name of a measure in every label, table and figure legend (riskplan.experiments.reporting.figures.naming)."""
    return label(_risk(group), short=not beta)


def team_name(group: Group) -> str:
    """'centralized', or 'distributed N=3': a group's team as labels and the figures' names say it."""
    return f"distributed N={group.robots}" if group.team else "centralized"


def team_risk_name(group: Group, named: bool = False) -> str:
    """The robots' own measures (team.risk), in the robots' order, a run of equal ones counted: 'own measures:
    risk-averse (CVaR β=0.2) ×2 | Wang (η=0.5)'; without team.risk, 'one measure for all: Wang (η=0.5)' (its name
    left out when the label `named` it already)."""
    nodes = group.team_conf.get("risk")
    if not nodes:
        return "one measure for all" if named else f"one measure for all: {measure_name(group)}"
    names = [label(node) for node in nodes]
    return "own measures: " + " | ".join(
        f"{name} ×{count}" if count > 1 else name
        for name, count in ((name, len(list(run))) for name, run in itertools.groupby(names))
    )


def _risk(group: Group) -> dict:
    """The group's risk node (its measure cvar when the config names none)."""
    return {"measure": group.measure, **group.config.get("risk", {})}


def policy_name(group: Group) -> str:
    """'tabular policy', or the features a features policy sees: 'features=[signals, risky]'."""
    if group.policy_kind == "tabular":
        return "tabular policy"
    return f"features=[{', '.join(group.features)}]"


def fault_name(group: Group) -> str:
    """The team's faults and how its robots aggregate: 'fault-free, mean', 'robot 6 byzantine, trimmed_mean F=1'."""
    faults = group.faults
    what = (
        ", ".join(
            f"robot {f.get('robot')} {f.get('kind')}" + (f" from {f.get('from')}" if f.get("from") else "")
            for f in faults
            if isinstance(f, dict)
        )
        if faults
        else "fault-free"
    )
    aggregate = str(group.team_conf.get("aggregate", "mean"))
    if aggregate in ("trimmed_mean", "wmsr"):
        aggregate += f" F={group.team_conf.get('trim', 0)}"
    return f"{what}, {aggregate}"


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, Missing):
        return "(absent)"
    text = str(v)
    if text.startswith("["):
        try:
            values = json.loads(text)
            if all(isinstance(x, (int, float)) for x in values):
                text = "[" + ", ".join(f"{x:g}" for x in values) + "]"
        except (ValueError, TypeError):
            pass
    return text if len(text) <= 40 else text[:37] + "..."
