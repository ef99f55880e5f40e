"""The measures by name: the built-in ones, and those installed packages register in the entry-point group
`riskplan.risk_measures` (looked up only for a name that is not built in, so a run of a built-in measure never
scans the installed packages). A risk node resolves here to its measure and checked parameters (`risk_spec`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from enum import Enum
from typing import Any, NamedTuple

from riskplan.config.schema import RiskConf, RiskplanConf
from riskplan.engine.measures.base import Measure, Params, field
from riskplan.engine.measures.cvar import CVaR
from riskplan.engine.measures.entropic import Entropic
from riskplan.engine.measures.mean_cvar import MeanCVaR
from riskplan.engine.measures.neutral import Neutral
from riskplan.engine.measures.wang import Wang
from riskplan.util.errors import BadInput, did_you_mean

GROUP = "riskplan.risk_measures"  # the entry-point group of users' measures
BUILT_IN: dict[str, Measure] = {m.name: m for m in (CVaR(), Neutral(), Wang(), MeanCVaR(), Entropic())}
MEASURES = tuple(BUILT_IN)  # the built-in measures' names: cvar, neutral, wang, mean_cvar, entropic
_FROM_PACKAGES: dict[str, Measure] = {}  # the entry points loaded so far, by name


class RiskSpec(NamedTuple):
    """A risk node resolved: its measure and that measure's checked parameter values."""

    measure: Measure
    params: Params


def lookup(name: Any, where: str = "risk.measure") -> Measure:
    """The measure of a name (a Measure passes as it is): a built-in one, else an installed package's entry point;
    BadInput naming `where` for a name no package provides."""
    if isinstance(name, Measure):
        return name
    if isinstance(name, Enum):  # the member's value names the measure
        name = name.value
    if not isinstance(name, str) or not name:
        raise BadInput(where, f"got {name!r}; expected a measure's name: {', '.join(MEASURES)} or one from a package")
    if name in BUILT_IN:
        return BUILT_IN[name]
    if name not in _FROM_PACKAGES:
        _FROM_PACKAGES[name] = _load(name, where)
    return _FROM_PACKAGES[name]


def _load(name: str, where: str) -> Measure:
    """The measure an installed package's entry point `name` gives, checked."""
    from importlib.metadata import entry_points  # lazy: only for a name that is not built in (riskplan's start-up)

    found = {point.value: point for point in entry_points(group=GROUP, name=name)}
    if not found:
        installed = sorted({point.name for point in entry_points(group=GROUP)} - set(MEASURES))
        others = f"installed: {', '.join(installed)}" if installed else "none is installed"
        raise BadInput(
            where,
            f"got {name!r}; expected a built-in measure ({', '.join(MEASURES)}) or one an installed package "
            f"registers in the entry-point group {GROUP} ({others}){did_you_mean(name, [*MEASURES, *installed])}",
        )
    if len(found) > 1:
        raise BadInput(where, f"got {name!r}, which several entry points give ({', '.join(sorted(found))}); keep one")
    (point,) = found.values()
    try:
        measure = point.load()
    except Exception as err:  # a package's import: whatever it raises is said in one line
        raise BadInput(
            where, f"got {name!r}, whose entry point {point.value} fails to load: {type(err).__name__}: {err}"
        ) from None
    if not isinstance(measure, Measure):
        raise BadInput(
            where,
            f"got {name!r}, whose entry point {point.value} is a {type(measure).__name__}, not a measure; make it "
            f"riskplan.risk.distortion(...) or a riskplan.risk.Measure",
        )
    if measure.name != name:
        raise BadInput(
            where,
            f"got {name!r}, whose entry point {point.value} is the measure {measure.name!r}; name the entry point as the measure",
        )
    return measure


def names() -> list[str]:
    """Every measure's name: the built-in ones, then those of installed packages (which this looks up)."""
    from importlib.metadata import entry_points  # lazy: rarely asked

    return [*MEASURES, *sorted({p.name for p in entry_points(group=GROUP)} - set(MEASURES))]


def risk_spec(risk: Any, where: str = "risk") -> RiskSpec:
    """The measure and checked parameters of a risk node: a mapping ({"measure": "wang", "eta": 0.75},
    {"measure": "power", "params": {"gamma": 0.5}}) or an object with attributes (a RiskConf). BadInput names the
    first bad key below `where`."""
    if not isinstance(risk, Mapping) and not hasattr(risk, "measure"):  # "cvar" alone read as a node of no measure
        raise BadInput(where, f"got {risk!r}; give a risk node, a mapping such as {{'measure': 'cvar', 'beta': 0.1}}")
    if isinstance(risk, Mapping):  # a mistyped key ('betta') was ignored: the measure ran at its default
        for key in risk:
            if key not in NODE_KEYS:
                raise BadInput(
                    f"{where}.{key}",
                    f"not a key of a risk node; expected one of {', '.join(NODE_KEYS)} (a package's measure takes "
                    f"its parameters under params){did_you_mean(key, NODE_KEYS)}",
                )
    measure = lookup(field(risk, "measure"), f"{where}.measure")
    return RiskSpec(measure, measure.params_of(risk, where))


NODE_KEYS = tuple(f.name for f in dataclasses.fields(RiskConf))  # measure, beta, eta, weight, schedule, params


def check_risk_nodes(params: RiskplanConf) -> None:
    """Each risk node of a config resolves (risk, and team.risk's): BadInput for a name no package provides or
    bad parameters, before anything runs."""
    risk_spec(params.risk)
    for i, node in enumerate(params.team.risk or []):
        risk_spec(node, f"team.risk.{i}")


def label(risk: Any, *, short: bool = False, beta: float | None = None) -> str:
    """`Measure.label` of a risk node; a node that does not resolve (a package's measure not installed here) is
    named by its measure and params as written."""
    try:
        measure, params = risk_spec(risk)
    except BadInput:
        values = field(risk, "params") or {}
        shown = ", ".join(f"{k}={v}" for k, v in dict(values).items())
        name = str(field(risk, "measure"))
        return f"{name} ({shown})" if shown else name
    return measure.label(params, short=short, beta=beta)


def parameter_keys(risk: Any) -> set[str]:
    """The config keys of a risk node's measure's parameters (risk.eta, risk.params.gamma); none when it does not
    resolve."""
    try:
        measure = lookup(field(risk, "measure"))
    except BadInput:
        return set()
    return {measure.key(p.name) for p in measure.parameters}
