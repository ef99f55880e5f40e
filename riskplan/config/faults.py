"""team.faults as typed, checked Fault records: which robot fails, how, and from which iteration.

The YAML keys are `{robot, kind, from, value | scale}`; `from` is a Python keyword, so the schema keeps the entries
as mappings and this module turns them into frozen `Fault`s once, with one line naming the key of any problem.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from riskplan.config.schema import FaultKind, TeamConf
from riskplan.util.checks import is_whole, require
from riskplan.util.errors import BadInput

KEYS = ("robot", "kind", "from", "value", "scale")
START_LIMIT = 1 << 63  # iterations are int64 in the engine


@dataclass(frozen=True)
class Fault:
    """One faulty robot: from iteration `start` on it crashes, is stuck, or is Byzantine (sends `value`, or its own
    theta plus seeded noise of standard deviation `scale`)."""

    robot: int
    kind: FaultKind
    start: int
    value: tuple[float, ...] | None = None  # byzantine: one number for every parameter, or one per parameter
    scale: float | None = None  # byzantine: the noise's standard deviation


def faults_of(team: TeamConf) -> tuple[Fault, ...]:
    """The checked faults of a team (in the order given); BadInput naming `team.faults.<i>.<key>` otherwise."""
    faults, seen = [], {}
    for i, entry in enumerate(team.faults):
        where = f"team.faults.{i}"
        require(
            isinstance(entry, Mapping),
            where,
            f"got {entry!r}; expected a mapping such as {{robot: 2, kind: crash, from: 50}}",
        )
        unknown = [k for k in entry if k not in KEYS]
        require(not unknown, f"{where}.{unknown[0] if unknown else ''}", f"unknown key; valid keys: {', '.join(KEYS)}")
        robot = entry.get("robot")
        require(
            is_whole(robot) and 0 <= robot < team.robots,
            f"{where}.robot",
            f"got {robot!r}; expected a robot index 0..{team.robots - 1}",
        )
        require(
            robot not in seen,
            f"{where}.robot",
            f"robot {robot} is also team.faults.{seen.get(robot)}; list a robot once",
        )
        seen[robot] = i
        kind = entry.get("kind")
        require(
            kind in FaultKind.names(),
            f"{where}.kind",
            f"got {kind!r}; expected one of {', '.join(FaultKind.names())}",
        )
        start = entry.get("from", 0)
        require(
            is_whole(start) and 0 <= start < START_LIMIT,
            f"{where}.from",
            f"got {start!r}; expected the iteration it starts at, a whole number 0 <= from < 2^63, e.g. 50",
        )
        faults.append(_with_payload(entry, where, int(robot), FaultKind(kind), int(start)))
    if faults:
        require(
            team.robots > 1, "team.faults", "a centralized run (team.robots=1) has no team to fail; drop the faults"
        )
        require(
            len(faults) < team.robots,
            "team.faults",
            f"lists all {team.robots} robots; at least one must stay healthy",
        )
    return tuple(faults)


def _with_payload(entry: Mapping, where: str, robot: int, kind: FaultKind, start: int) -> Fault:
    """The Fault, with a byzantine robot's `value` or `scale` (exactly one), and neither for the others."""
    value, scale = entry.get("value"), entry.get("scale")
    if kind != FaultKind.byzantine:
        extra = "value" if value is not None else "scale" if scale is not None else None
        require(extra is None, f"{where}.{extra}", f"only a byzantine robot sends a {extra}; drop it for kind={kind}")
        return Fault(robot, kind, start)
    require(
        (value is None) != (scale is None),
        where,
        "a byzantine robot needs exactly one of value (the theta it sends) or scale (noise around its own theta)",
    )
    if scale is not None:
        require(_finite(scale) and scale > 0, f"{where}.scale", f"got {scale!r}; expected a finite number > 0")
        return Fault(robot, kind, start, scale=float(scale))
    values = list(value) if isinstance(value, list | tuple) else [value]
    require(
        bool(values) and all(_finite(v) for v in values),
        f"{where}.value",
        f"got {value!r}; expected a finite number, or a list of finite numbers (one per parameter)",
    )
    return Fault(robot, kind, start, value=tuple(float(v) for v in values))


def _finite(value: Any) -> bool:
    """A finite real number (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def check_value_size(faults: tuple[Fault, ...], params: int) -> None:
    """A byzantine `value` gives one number, or one per policy parameter (known once the policy is built)."""
    for i, fault in enumerate(faults):
        if fault.value is not None and len(fault.value) not in (1, params):
            raise BadInput(
                f"team.faults.{i}.value",
                f"gives {len(fault.value)} numbers; the policy has {params} parameters: give one number or {params}",
            )
