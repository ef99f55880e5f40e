"""r-robustness of a communication graph (LeBlanc, Zhang, Koutsoukos and Sundaram, "Resilient asymptotic consensus
in robust networks", IEEE JSAC 31(4), 2013), the condition the resilient aggregates (team.aggregate=trimmed_mean,
median, wmsr with team.trim=F) are checked against: (2F+1)-robust, and at most F faulty in-neighbours per robot.

Definitions (``adjacency[i, j]``: robot i hears robot j, so row i lists i's in-neighbours):
- a node set S is r-reachable when some node of S has at least r in-neighbours outside S;
- a digraph is r-robust when of every pair of nonempty, disjoint node sets S1, S2 at least one is r-reachable.

`robustness` decides it exactly by enumeration up to LIMIT robots: level(S), the largest number of in-neighbours
outside S of a node of S, for all 2^N sets, then g(T) = min level over the nonempty subsets of T (a sum over
subsets, N passes), and the largest r is min over S of max(level(S), g(complement of S)). O(N 2^N) time and
about 14 bytes per set: N = LIMIT takes well under a second. Beyond LIMIT the answer is None (unknown), except
that a robot hearing fewer than r others rules r >= 2 out (see `is_robust`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from riskplan.config.faults import Fault
from riskplan.config.schema import Aggregate
from riskplan.engine.team.graphs import strongly_connected

LIMIT = 20  # robots: decided exactly up to here (2^20 sets)

REFERENCE = 'LeBlanc et al., "Resilient asymptotic consensus in robust networks", IEEE JSAC 31(4), 2013'


def _adjacency(adjacency: np.ndarray) -> np.ndarray:
    """A square bool array with an empty diagonal (a robot is not its own in-neighbour)."""
    a = np.array(adjacency, dtype=bool)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f"expected a square adjacency matrix, got shape {a.shape}")
    np.fill_diagonal(a, False)
    return a


def levels(adjacency: np.ndarray) -> np.ndarray:
    """(2^N,) uint8: for each node set S (bit j = robot j), the largest number of in-neighbours outside S of a node
    of S (0 for the empty set). S is r-reachable iff levels[S] >= r. N <= LIMIT."""
    a = _adjacency(adjacency)
    n = len(a)
    if n > LIMIT:
        raise ValueError(f"levels enumerates 2^N sets; N = {n} is above the limit {LIMIT}")
    sets = np.arange(1 << n, dtype=np.uint32)
    outside = ~sets
    level = np.zeros(1 << n, dtype=np.uint8)
    for v in range(n):
        heard = np.uint32(sum(1 << int(j) for j in np.flatnonzero(a[v])))
        count = np.bitwise_count(outside & heard)  # v's in-neighbours outside S
        member = ((sets >> np.uint32(v)) & np.uint32(1)).astype(bool)
        np.maximum(level, count, out=level, where=member)
    return level


def robustness(adjacency: np.ndarray) -> int | None:
    """The largest r for which the digraph is r-robust (0 when it is not even 1-robust), decided exactly for
    2 <= N <= LIMIT robots; None beyond LIMIT (unknown). A single robot has no pair of sets to test: ValueError."""
    n = len(adjacency)
    if n < 2:
        raise ValueError("r-robustness needs at least 2 robots (one robot is r-robust for every r, vacuously)")
    if n > LIMIT:
        return None
    a = _adjacency(adjacency)
    return _largest_r(n, np.packbits(a).tobytes())


@functools.lru_cache(maxsize=8)
def _largest_r(n: int, packed: bytes) -> int:
    """`robustness` of the N x N adjacency packed by np.packbits (cached: the build and `riskplan check` both ask)."""
    level = levels(np.unpackbits(np.frombuffer(packed, dtype=np.uint8), count=n * n).reshape(n, n).astype(bool))
    full = (1 << n) - 1
    smallest = level.copy()  # smallest[T] = min level over the nonempty subsets of T, after the passes below
    smallest[0] = np.iinfo(np.uint8).max  # the empty set is not a candidate
    for bit in range(n):
        view = smallest.reshape(1 << (n - bit - 1), 2, 1 << bit)  # [.., 1, ..]: the sets holding `bit`
        np.minimum(view[:, 1, :], view[:, 0, :], out=view[:, 1, :])
    sets = np.arange(1, full, dtype=np.uint32)  # S nonempty and not everything, so its complement is nonempty
    return int(np.maximum(level[1:full], smallest[full ^ sets]).min())


def is_robust(adjacency: np.ndarray, r: int) -> bool | None:
    """Whether the digraph is r-robust: exact for N <= LIMIT, None (unknown) beyond it unless decided cheaply.

    Always true for r <= 0, and vacuously for N <= 1. Beyond LIMIT: a strongly connected digraph is 1-robust
    (every set other than the whole hears from outside it), and for r >= 2 a robot with fewer than r
    in-neighbours makes it not r-robust (S1 = {that robot}, S2 = everyone else: each node of S2 hears at most one
    robot outside S2)."""
    a = _adjacency(adjacency)
    n = len(a)
    if r <= 0 or n <= 1:
        return True
    if n <= LIMIT:
        return r <= robustness(a)
    if r >= 2 and int(a.sum(axis=1).min()) < r:
        return False
    if r == 1 and strongly_connected(a):
        return True
    return None


def _fault_text(fault: Fault) -> str:
    """'robot 6 byzantine from iteration 0 (value 1e+06)'."""
    text = f"robot {fault.robot} {fault.kind} from iteration {fault.start}"
    if fault.value is not None:
        text += f" (value {', '.join(f'{v:g}' for v in fault.value)})"
    if fault.scale is not None:
        text += f" (theta + noise of scale {fault.scale:g})"
    return text


@dataclass(frozen=True)
class Condition:
    """The resilience condition of a team: (2F+1)-robustness and F-local faults, as `riskplan check` prints it."""

    met: bool | None  # None: not decided (robustness unknown beyond LIMIT and nothing else broken)
    lines: tuple[str, ...]  # the text, one entry per line
    warning: str | None  # one line when the condition is not met, else None


def faulty_neighbours(adjacency: np.ndarray, faults: Sequence[Fault]) -> np.ndarray:
    """(N,) int: how many of each robot's in-neighbours are listed in `faults`."""
    faulty = np.zeros(len(adjacency), dtype=bool)
    faulty[[f.robot for f in faults]] = True
    return (_adjacency(adjacency) & faulty[None, :]).sum(axis=1)


def most_faulty_neighbours(adjacency: np.ndarray, faults: Sequence[Fault]) -> int:
    """The most in-neighbours listed in `faults` that a healthy robot (one not listed) has: median's F."""
    faulty = {f.robot for f in faults}
    counts = faulty_neighbours(adjacency, faults)
    return max((int(counts[i]) for i in range(len(counts)) if i not in faulty), default=0)


# What still holds, per rule, in rounds that hear fewer links than the graph has (`condition`'s `unreliable`).
_SAFE = {
    Aggregate.trimmed_mean: "a robot that hears 2F or fewer values keeps its own, and otherwise the values it keeps lie "
    "within the healthy ones it heard",
    Aggregate.wmsr: "W-MSR drops up to F values above and F below its own, however few it hears, so the values it "
    "keeps lie within the healthy ones it heard",
    Aggregate.median: "a robot that hears fewer than 2F values keeps its own, and otherwise the median of its own and "
    "the heard values lies within the healthy ones",
}


def condition(
    adjacency: np.ndarray, aggregate: Aggregate, trim: int, faults: Sequence[Fault], unreliable: Sequence[str] = ()
) -> Condition:
    """Whether the graph and the faults meet the resilience condition of `aggregate` with F = `trim`, and the text.

    For trimmed_mean, median and wmsr: the graph is (2F+1)-robust, and each healthy robot has at most F faulty
    in-neighbours (the F-local model). The median drops nothing and takes no team.trim: its F is the most faulty
    in-neighbours a healthy robot has. For mean with faults: no condition (the mean has no resilience), said so.
    `unreliable`: the settings under which a round may hear fewer links than the graph has ("team.drop=0.5", ...);
    the verdict is still that of the full graph, and a line says what that does and does not cover."""
    a = _adjacency(adjacency)
    n = len(a)
    aggregate = Aggregate(aggregate)
    worst = most_faulty_neighbours(a, faults)
    named, given = f"team.trim={trim}", f"team.trim=F={trim}"
    if aggregate == Aggregate.median:
        trim, named = worst, f"F={worst}"
        given = f"{named} (the most faulty in-neighbours of a healthy robot; median takes no team.trim)"
    listed = ", ".join(_fault_text(f) for f in faults) or "none"
    lines = [f"resilience: team.aggregate={aggregate}, {given}; faults: {listed}"]
    if aggregate == Aggregate.mean:
        lines.append(
            "  team.aggregate=mean has no resilience: each faulty robot's value enters its neighbours' mix with its "
            "weight, so one byzantine robot can drag the team anywhere; use trimmed_mean, median or wmsr with "
            "team.trim=F"
        )
        return Condition(None, tuple(lines), None)
    r = 2 * trim + 1
    if n <= LIMIT:
        largest = robustness(a)
        robust = r <= largest
        found = f"the graph is {largest}-robust, not {largest + 1}-robust (exact: enumeration, N = {n} <= {LIMIT})"
    elif (robust := is_robust(a, r)) is False:
        low = int(a.sum(axis=1).argmin())
        found = f"robot {low} hears only {int(a[low].sum())} robots, so the graph is not {r}-robust (N = {n})"
    else:
        found = f"the largest r is not computed above the enumeration limit of {LIMIT} robots (N = {n})"
        found += "; strongly connected, so 1-robust" if robust else ""
    full = " on the full graph" if unreliable else ""
    verdict = {True: "holds", False: "FAILS", None: "unknown"}[robust]
    lines.append(f"  (2F+1)-robustness: needs {r}-robust; {found}: {verdict}{full}")
    local = worst <= trim
    lines.append(
        f"  F-local faults: at most {worst} faulty in-neighbour{'s' if worst != 1 else ''} per healthy robot "
        f"(F = {trim}): {'holds' if local else 'FAILS'}{full}"
    )
    if unreliable:
        # A round's heard links are a subset of the graph's: no more faulty ones (safety survives), but the
        # round's graph may be far from (2F+1)-robust (agreement does not).
        lines.append(
            f"  warning: with {', '.join(unreliable)} a round hears only the links that deliver in it, so a robot may "
            f"hear fewer than 2F+1 values and the graph of a round need not be {r}-robust: the verdicts above judge "
            f"the full graph, and consensus is not guaranteed (a robot may be left at its own value for many "
            f"rounds). With at most F faulty in-neighbours, safety still holds: {_SAFE[aggregate]}, so each healthy "
            f"robot's mix stays within the range of its own value and the healthy values it heard (under delays or "
            f"stale=latest, possibly sent in earlier iterations)"
        )
    lines.append(
        f"  (2F+1)-robustness with at most F faulty in-neighbours per robot is sufficient for W-MSR to reach "
        f"resilient asymptotic consensus ({REFERENCE}); the same counting argument covers trimmed_mean; for median "
        f"it is a check only (the median stays within the healthy values when a robot hears at least 2F, but "
        f"robustness does not guarantee that median consensus converges). A byzantine robot here sends one value "
        f"to all its neighbours (LeBlanc et al.'s malicious model)"
    )
    met = None if robust is None and local else bool(robust) and local
    warning = None
    if met is False:
        broken = []
        if robust is False:
            broken.append(f"the graph is not {r}-robust")
        if not local:
            broken.append(f"a healthy robot has {worst} faulty in-neighbours")
        warning = (
            f"team.aggregate={aggregate} with {named}: {' and '.join(broken)}, so resilient consensus is not "
            f"guaranteed (needs (2F+1)-robustness and at most F faulty in-neighbours per robot; riskplan check says "
            f"more)"
        )
    return Condition(met, tuple(lines), warning)
