"""Resilient aggregation (team.aggregate=trimmed_mean, median, wmsr with team.trim=F): what a robot makes of its own
value and the values it received in one consensus round, per coordinate m.

The received values are those the links would mix under the existing rules (delays, drops, stale=arrival|latest:
the `use` mask of `Mixer._received`); a link that delivered nothing hands its weight a^{ij} to robot i itself, as
under team.aggregate=mean. Then, per coordinate:

- trimmed_mean: drop the F largest and the F smallest received values (all of them when there are 2F or fewer);
- wmsr (W-MSR, LeBlanc et al., IEEE JSAC 2013): drop the F largest of the received values strictly above the robot's
  own value (all of them when there are fewer than F), and the F smallest of those strictly below it; values equal
  to its own are kept;
- and for both, the weight a^{ij}_m of every dropped link goes to robot i itself, so the row stays stochastic:
  out = (a^{ii} + idle + dropped) own + sum over kept links of a^{ij} value^{ij};
- median: the median of the robot's own value and the received ones, unweighted (the mean of the two middle values,
  as 0.5 a + 0.5 b, when their count is even); but a robot that received fewer than 2F values keeps its own value.
  F is the bound on faulty in-neighbours (`rule_f`: for median, the most faulty in-neighbours of a healthy robot,
  not team.trim). Why 2F: with K >= 2F received values, at most F of them faulty, the healthy ones (its own among
  them) are a majority of the K + 1 pooled, so the middle values lie within the healthy ones; with K < 2F
  (drops, delays, switching) F faulty values could be a middle one, e.g. its own and one byzantine value would
  average halfway to the byzantine value.

Ties are broken by sender index: among equal values the link from the lower-indexed robot counts as the smaller
(a stable sort of the received values in order of j). Sums run own term first, then the kept links in order of j,
so with F = 0 trimmed_mean and wmsr equal mean up to rounding, not bit for bit. Values must be finite.

`aggregate_row` is the rule for ONE robot (what a robot that owns only its row, e.g. a Ray actor, calls);
`aggregate_team` runs it for every robot in numba and agrees with it exactly. `row_inputs` cuts a team's arrays
down to one robot's row. `rule_f` is the F a rule runs with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit, prange

from riskplan.config.faults import Fault
from riskplan.config.schema import Aggregate
from riskplan.engine.team import kernels, robustness

CODES = {Aggregate.trimmed_mean: 1, Aggregate.median: 2, Aggregate.wmsr: 3}
_TRIMMED, _MEDIAN, _WMSR = 1, 2, 3


def _code(rule: Aggregate | str) -> int:
    """The kernel's code of a resilient rule; ValueError for mean (eq. 14 is `kernels.mix_used`)."""
    rule = Aggregate(rule)
    if rule not in CODES:
        raise ValueError(
            f"{rule} is not a resilient aggregate ({', '.join(map(str, CODES))}); mean is kernels.mix_used"
        )
    return CODES[rule]


def rule_f(rule: Aggregate | str, trim: int, adjacency: np.ndarray, faults: Sequence[Fault]) -> int:
    """The F that `aggregate_row` and `aggregate_team` take for `rule`: team.trim for trimmed_mean and wmsr; for
    median (which takes no team.trim) the most faulty in-neighbours of a healthy robot on the full graph, the F
    `riskplan check` judges it with (0 without faults: the plain median); 0 for mean (unused)."""
    rule = Aggregate(rule)
    if rule == Aggregate.median:
        return robustness.most_faulty_neighbours(adjacency, faults)
    return int(trim) if rule in CODES else 0


def aggregate_row(
    rule: Aggregate | str,
    own: np.ndarray,
    received: np.ndarray,
    weights: np.ndarray,
    own_weight: np.ndarray,
    trim: int,
) -> np.ndarray:
    """One robot's aggregate: (M,) out.

    own: (M,) its own value; received: (K, M) the values of the K links it mixes this round, in order of the sender
    j; weights: (K, M) their a^{ij}_m; own_weight: (M,) a^{ii}_m plus the weights of its links that delivered
    nothing (summed in order of j; `row_inputs`); trim: F >= 0 (`rule_f`). median uses neither weight."""
    code = _code(rule)
    own = np.asarray(own, dtype=float)
    received = np.asarray(received, dtype=float).reshape(-1, own.shape[0])
    weights = np.asarray(weights, dtype=float).reshape(received.shape)
    own_weight = np.asarray(own_weight, dtype=float).reshape(own.shape)
    count = len(received)
    out = np.empty(own.shape[0])
    for k in range(own.shape[0]):
        x, values = float(own[k]), received[:, k]
        if code == _MEDIAN:
            if count < 2 * trim:  # too few to outvote F faulty values (module docstring)
                out[k] = x
                continue
            pool = np.concatenate([[x], values])
            ranked = pool[np.argsort(pool, kind="stable")]
            half = len(ranked) // 2
            out[k] = ranked[half] if len(ranked) % 2 else 0.5 * ranked[half - 1] + 0.5 * ranked[half]
            continue
        order = np.argsort(values, kind="stable")  # ascending; ties in order of j
        dropped = np.zeros(count, dtype=bool)
        if code == _TRIMMED:
            if count <= 2 * trim:
                dropped[:] = True
            elif trim:
                dropped[order[:trim]] = True
                dropped[order[count - trim :]] = True
        else:  # W-MSR: the values below x are a prefix of `order`, those above it a suffix
            below, above = int((values < x).sum()), int((values > x).sum())
            dropped[order[: min(trim, below)]] = True
            dropped[order[count - min(trim, above) :]] = True
        diagonal = float(own_weight[k])
        for c in range(count):
            if dropped[c]:
                diagonal += float(weights[c, k])
        total = diagonal * x
        for c in range(count):
            if not dropped[c]:
                total += float(weights[c, k]) * float(values[c])
        out[k] = total
    return out


def row_inputs(
    weights: np.ndarray, adjacency: np.ndarray, use: np.ndarray, neighbour: np.ndarray, own: np.ndarray, i: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robot i's arguments of `aggregate_row` from the team's arrays (those of `aggregate_team`): (own (M,),
    received (K, M), weights (K, M), own_weight (M,)), the links in `use` in order of j."""
    links = [j for j in range(len(adjacency)) if adjacency[i, j] and use[i, j]]
    own_weight = np.array(weights[i, i, :], dtype=float)
    for k in range(own_weight.shape[0]):
        idle = 0.0
        for j in range(len(adjacency)):
            if adjacency[i, j] and not use[i, j]:
                idle += float(weights[i, j, k])
        own_weight[k] += idle
    m = own.shape[1]
    received = np.array([neighbour[i, j, :] for j in links], dtype=float).reshape(-1, m)
    link_weights = np.array([weights[i, j, :] for j in links], dtype=float).reshape(-1, m)
    return np.array(own[i], dtype=float), received, link_weights, own_weight


def aggregate_team(
    rule: Aggregate | str,
    weights: np.ndarray,
    adjacency: np.ndarray,
    use: np.ndarray,
    neighbour: np.ndarray,
    own: np.ndarray,
    trim: int,
) -> np.ndarray:
    """`aggregate_row` for every robot i, bit for bit: (N, M) out. weights (N, N, M) a^{ij}_m; adjacency (N, N)
    the links; use (N, N) the links that mix a value this round; neighbour (N, N, M) the value on each link (only
    those in `use` are read); own (N, M). In parallel (ROWS rows a thread) from kernels.PARALLEL_ENTRIES entries
    on: a row is one thread's, so the numbers do not depend on the thread count."""
    n, m = own.shape
    out = np.empty((n, m))
    args = (
        _code(rule),
        np.ascontiguousarray(weights, dtype=float),
        np.ascontiguousarray(adjacency, dtype=bool),
        np.ascontiguousarray(use, dtype=bool),
        np.ascontiguousarray(neighbour, dtype=float),
        np.ascontiguousarray(own, dtype=float),
        int(trim),
        out,
    )
    if n * n >= kernels.PARALLEL_ENTRIES:
        _aggregate_parallel(*args, kernels.ROWS)
    else:
        _aggregate_rows(*args, 0, n)
    return out


@njit(parallel=True, cache=True)
def _aggregate_parallel(code, weights, adjacency, use, neighbour, own, trim, out, rows):
    """`_aggregate_rows` of every row, `rows` at a time in parallel."""
    n = own.shape[0]
    chunks = (n + rows - 1) // rows
    for chunk in prange(chunks):
        _aggregate_rows(
            code, weights, adjacency, use, neighbour, own, trim, out, chunk * rows, min(n, (chunk + 1) * rows)
        )


@njit(cache=True)
def _aggregate_rows(code, weights, adjacency, use, neighbour, own, trim, out, first, last):
    """`aggregate_row` of rows first..last-1 (see it for the rules), the same operations in the same order."""
    n, m = own.shape
    links = np.empty(n, dtype=np.int64)
    values = np.empty(n)
    pool = np.empty(n + 1)
    dropped = np.zeros(n, dtype=np.bool_)
    for i in range(first, last):
        count = 0
        for j in range(n):
            if adjacency[i, j] and use[i, j]:
                links[count] = j
                count += 1
        for k in range(m):
            x = own[i, k]
            if code == _MEDIAN:
                if count < 2 * trim:
                    out[i, k] = x
                    continue
                pool[0] = x
                for c in range(count):
                    pool[c + 1] = neighbour[i, links[c], k]
                ranked = pool[: count + 1][np.argsort(pool[: count + 1], kind="mergesort")]
                half = (count + 1) // 2
                out[i, k] = ranked[half] if (count + 1) % 2 else 0.5 * ranked[half - 1] + 0.5 * ranked[half]
                continue
            below, above = 0, 0
            for c in range(count):
                v = neighbour[i, links[c], k]
                values[c] = v
                dropped[c] = False
                below += v < x
                above += v > x
            order = np.argsort(values[:count], kind="mergesort")
            if code == _TRIMMED:
                if count <= 2 * trim:
                    for c in range(count):
                        dropped[c] = True
                else:
                    for c in range(trim):
                        dropped[order[c]] = True
                        dropped[order[count - 1 - c]] = True
            else:
                for c in range(min(trim, below)):
                    dropped[order[c]] = True
                for c in range(min(trim, above)):
                    dropped[order[count - 1 - c]] = True
            idle = 0.0
            for j in range(n):
                a = weights[i, j, k]
                idle += a if adjacency[i, j] and not use[i, j] else 0.0
            diagonal = weights[i, i, k] + idle
            for c in range(count):
                if dropped[c]:
                    diagonal += weights[i, links[c], k]
            total = diagonal * x
            for c in range(count):
                if not dropped[c]:
                    total += weights[i, links[c], k] * values[c]
            out[i, k] = total
