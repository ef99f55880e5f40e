"""What a figure calls its groups, and how it lays out many of them.

A figure names only what differs between the groups it draws, in a few words ("β=0.05", "graph=ring,
distributed N=5"): the fewest config keys that tell those groups apart (not the whole collection's), each written
short. The measure and the team are said as the report's tables say them (riskplan.experiments.reporting.labels:
"risk-averse (CVaR β=0.1)", "distributed N=3", "centralized"), so one policy has one name in every table, figure
and report, a reproduction's or a user's; a path's seed follows it as ", seed 0" (`seeded`). Past MAX_CURVES
groups a figure draws small multiples (`layout`): one panel per value of one of those keys, or one per group.

The paper's figures are titled so only where the runs are a reproduction's (`is_reproduction`); a user's sweep gets
plain titles.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path

from riskplan.config.keys import KEYS
from riskplan.experiments.reporting.collect import PALETTE, Collection, Group
from riskplan.experiments.reporting.figures.drawing import literal
from riskplan.experiments.reporting.labels import fault_name, measure_name, team_name

MAX_CURVES = 8  # groups drawn in one panel; more make small multiples
MAX_PANELS = 20  # panels of small multiples; past them the figure says how many it left out
MEASURE, POLICY, FAULTS = KEYS.risk.measure, "policy", "faults"  # keys that name several config keys at once
BUNDLED = {
    KEYS.risk.eta: MEASURE,
    KEYS.risk.weight: MEASURE,
    KEYS.policy.kind: POLICY,
    KEYS.policy.features: POLICY,
    KEYS.team.faults: FAULTS,
    KEYS.team.aggregate: FAULTS,
    KEYS.team.trim: FAULTS,
}
PRIORITY = (  # the keys a name is made of, tried in this order (the rest follow alphabetically, experiment last)
    MEASURE,
    KEYS.risk.beta,
    KEYS.risk.schedule.kind,
    KEYS.team.robots,
    KEYS.team.graph,
    KEYS.team.weights,
    KEYS.team.order,
    KEYS.team.delay.max,
    KEYS.team.drop,
    KEYS.team.consensus_rounds,
    POLICY,
    FAULTS,
    KEYS.team.starts,
    KEYS.train.samples,
    "train.theta0",
)
SHORTEST = 24  # characters of a value in a name
PAPER_FOLDERS = ("single", "team")  # riskplan reproduce's folders of Figs. 1-2 and 3-4


def _value(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    text = str(value)
    if text.startswith("["):
        try:
            items = json.loads(text)
            text = "[" + ", ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in items) + "]"
        except (TypeError, ValueError):
            pass
    return literal(text if len(text) <= SHORTEST else text[: SHORTEST - 1] + "…")


def _key(key: str) -> str:
    """A config key as a name shows it: team.graph -> graph, train.step_size.initial -> step_size.initial."""
    head, _, rest = key.partition(".")
    return rest if rest and head in (KEYS.team, KEYS.train, KEYS.world, KEYS.risk, KEYS.policy) else key


def text(g: Group, key: str) -> str:
    """One key of a group, written short."""
    if key == MEASURE:
        return measure_name(g)
    if key == KEYS.risk.beta:
        return f"β={g.beta:g}"
    if key == KEYS.team.robots:
        return team_name(g)
    if key == POLICY:
        return "tabular policy" if g.policy_kind == "tabular" else f"features=[{', '.join(g.features)}]"
    if key == FAULTS:
        return fault_name(g)
    if key == KEYS.team.starts:
        starts = g.team_conf.get("starts")
        return f"{len(starts)} start cells" if starts else "one start cell"
    return f"{_key(key)}={_value(g.first.flat.get(key, '(absent)'))}"


def key_name(key: str) -> str:
    """A key as a caption says it: 'β', 'N', 'graph', 'risk measure'."""
    return {
        MEASURE: "risk measure",
        KEYS.risk.beta: "β",
        KEYS.team.robots: "team size N",
        POLICY: "policy",
        FAULTS: "fault and aggregation",
        KEYS.team.starts: "set of start cells",
    }.get(key, _key(key))


def differing(groups: list[Group]) -> list[str]:
    """The keys (MEASURE, POLICY and FAULTS standing for theirs) whose values differ between the groups, in the
    order names are made of; the keys a bundle stands for follow at the end, for groups its words do not tell apart."""
    flat = [g.first.flat for g in groups]
    raw = sorted(k for k in {k for f in flat for k in f} if len({_hashable(f.get(k)) for f in flat}) > 1)
    keys = {_bundle(k) for k in raw}
    ordered = [k for k in PRIORITY if k in keys]
    ordered += sorted(k for k in keys if k not in PRIORITY and k != KEYS.experiment)
    ordered += [KEYS.experiment] if KEYS.experiment in keys else []
    return ordered + [k for k in raw if _bundle(k) != k]


def _bundle(key: str) -> str:
    """The key a name shows for a config key: MEASURE for the measure's parameters (risk.params.*), ..."""
    return MEASURE if key.startswith(f"{KEYS.risk.params}.") else BUNDLED.get(key, key)


def _hashable(value):
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return value if not isinstance(value, (list, dict)) else json.dumps(value, sort_keys=True)


def _tells_apart(groups: list[Group], keys: tuple[str, ...]) -> bool:
    return len({tuple(text(g, k) for k in keys) for g in groups}) == len(groups)


def naming_keys(groups: list[Group]) -> list[str]:
    """The fewest differing keys (at most four, earliest in PRIORITY) whose values tell every group apart; else
    every key that adds to what the others tell apart."""
    keys = differing(groups)
    if len(groups) < 2:
        return []
    for size in range(1, min(4, len(keys)) + 1):
        for chosen in combinations(keys, size):
            if _tells_apart(groups, chosen):
                return list(chosen)
    chosen: list[str] = []
    for k in keys:
        trial = [*chosen, k]
        if len({tuple(text(g, c) for c in trial) for g in groups}) > len(
            {tuple(text(g, c) for c in chosen) for g in groups}
        ):
            chosen = trial
    return chosen


def alone(g: Group) -> str:
    """The name of a group drawn alone, as the report's label of a lone group: its measure, then its team."""
    return f"{measure_name(g)}, {team_name(g)}"


def seeded(name: str, seed: int) -> str:
    """A group's name for the paths of one of its seeds (Fig. 1's legend and panels)."""
    return f"{name}, seed {seed}"


def names(groups: list[Group], keys: list[str] | None = None, unique: bool = True) -> list[str]:
    """Each group's name: the values of `keys` (default: naming_keys) joined by commas, the measure by its label
    (which holds CVaR's β: 'risk-averse (CVaR β=0.1)'; no β apart beside a measure). Names that would still collide
    get '#2', '#3' when `unique`."""
    if len(groups) == 1 and keys is None:
        return [alone(groups[0])]
    keys = naming_keys(groups) if keys is None else keys
    out = []
    for g in groups:
        parts = [text(g, k) for k in keys]
        if MEASURE in keys and KEYS.risk.beta in keys:
            parts[keys.index(KEYS.risk.beta)] = ""
        out.append(", ".join(p for p in parts if p) or "runs")
    if not unique:
        return out
    if len(set(out)) < len(out) and MEASURE in keys and KEYS.risk.beta in keys:  # a β that differs between neutral runs
        out = [", ".join(text(g, k) for k in keys) for g in groups]
    seen: dict[str, int] = {}
    for i, name in enumerate(out):
        seen[name] = seen.get(name, 0) + 1
        if seen[name] > 1:
            out[i] = f"{name} #{seen[name]}"
    return out


def colours(groups: list[Group]) -> list[str]:
    """The groups' own colours (as the page's table shows them) when they differ, else the palette in order."""
    own = [g.color for g in groups]
    if len(set(own)) == len(own):
        return own
    return [PALETTE[i % len(PALETTE)] for i in range(len(groups))]


@dataclass
class Panel:
    """The groups one panel draws: their names within it and their colours, and the panel's title."""

    groups: list[Group]
    names: list[str]
    colours: list[str]
    title: str = ""


@dataclass
class Layout:
    """The panels of a figure; `shared`: whether one name has one colour in every panel (one legend for all);
    `left_out`: groups not drawn (past MAX_PANELS)."""

    panels: list[Panel]
    shared: bool = True
    left_out: int = 0
    keys: list[str] = field(default_factory=list)
    facet: tuple[str, ...] = ()  # the keys whose values make the panels (none: one panel, or one per group)

    @property
    def single(self) -> bool:
        return len(self.panels) == 1

    def legend(self) -> dict[str, str]:
        """name -> colour over all panels, in the order first drawn."""
        out: dict[str, str] = {}
        for p in self.panels:
            for name, colour in zip(p.names, p.colours):
                out.setdefault(name, colour)
        return out

    def note(self) -> str:
        """What the caption says of the layout: the panels, and any groups left out."""
        text = ""
        if len(self.panels) > 1:
            text = (
                " One panel per group (shared axes)."
                if all(len(p.groups) == 1 for p in self.panels)
                else f" One panel per {' and '.join(key_name(k) for k in self.facet)} (shared axes)."
            )
        if self.left_out:
            text += f" {self.left_out} more groups are not drawn (at most {MAX_PANELS} panels)."
        return text


def layout(groups: list[Group], most: int = MAX_CURVES, palette: tuple[str, ...] = PALETTE) -> Layout:
    """One panel of all the groups when they are at most `most`; else small multiples: one panel per value of the
    naming key (or pair of keys) that leaves the fewest panels of at most `most` groups each (the other keys name
    the curves, one colour per name in every panel), or, when none does, one panel per group."""
    keys = naming_keys(groups)
    if len(groups) <= most:
        return Layout([Panel(list(groups), names(groups), colours(groups))], keys=keys)
    best = None
    facets = [(k,) for k in keys] + (list(combinations(keys, 2)) if len(keys) > 2 else [])
    for facet in facets if len(keys) > 1 else []:
        values: dict[str, list[Group]] = {}
        for g in groups:
            values.setdefault(", ".join(text(g, k) for k in facet), []).append(g)
        if max(len(v) for v in values.values()) <= most and len(values) <= MAX_PANELS:
            if best is None or len(values) < len(best[1]):
                best = (facet, values)
    if best is not None:
        facet, values = best
        rest = [k for k in keys if k not in facet]
        everyone = names(groups, rest, unique=False)  # unique within each panel: the facet's value differs
        chosen: dict[str, str] = {}
        for name in everyone:
            chosen.setdefault(name, palette[len(chosen) % len(palette)])
        panels = []
        for title, members in values.items():
            own = [everyone[groups.index(g)] for g in members]
            panels.append(Panel(members, own, [chosen[n] for n in own], title))
        return Layout(panels, keys=keys, facet=facet)
    shown = groups[:MAX_PANELS]
    every = names(groups, keys)
    panels = [Panel([g], [every[i]], [g.color], every[i]) for i, g in enumerate(shown)]
    return Layout(panels, shared=False, left_out=len(groups) - len(shown), keys=keys)


def is_reproduction(collected: Collection) -> bool:
    """Whether the runs are a reproduction's (riskplan reproduce's single/ or team/ folders among the inputs):
    only then are Figs. 1-4 the paper's figures."""
    roots = []
    for path in collected.inputs:
        path = Path(path).resolve()
        if any((path / f).is_dir() for f in PAPER_FOLDERS):
            roots.append(path)
        elif path.name in PAPER_FOLDERS and all((path.parent / f).is_dir() for f in PAPER_FOLDERS):
            roots.append(path.parent)
    folders = [root / f for root in roots for f in PAPER_FOLDERS]
    return any(folder in Path(r.path).resolve().parents for r in collected.runs for folder in folders)
