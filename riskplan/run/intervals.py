"""Final figures of a run: the point values of mean, VaR and CVaRs on the evaluation episodes, with 95% percentile-bootstrap intervals."""

from __future__ import annotations

import numpy as np
from numba import njit

from riskplan.engine import threads
from riskplan.engine.estimators import cvar, tail_count, value_at_risk
from riskplan.engine.measures.registry import risk_spec
from riskplan.engine.rng import BOOTSTRAP, LANES, count_lanes, lane_sums, stream_key

REPORT_BETAS = (0.05, 0.1, 0.2)


def bootstrap_intervals(z: np.ndarray, beta: float, resamples: int, seed: int) -> dict[str, dict[str, float]]:
    """Point value and 95% percentile-bootstrap interval of mean, VaR_beta, CVaR_beta and CVaR at REPORT_BETAS. The
    point values are of z in its order, bit for bit those riskplan.risk and numpy give of the episodes (eval.parquet,
    the report): summed sorted, they differed in the last digit."""
    given = np.asarray(z, dtype=float)
    z = np.sort(given)
    if not 0 < z.size < 2**31:  # int32 counts, 32-bit index draws
        raise ValueError(f"bootstrap needs 1 to 2^31 - 1 values, got {z.size}")
    betas = np.array([beta, *REPORT_BETAS])
    tails = np.array([tail_count(b, z.size) for b in betas], dtype=np.int64)
    stats = np.empty((resamples, 2 + len(betas)))
    _bootstrap(z, betas, tails, np.uint64(stream_key(seed, BOOTSTRAP)), stats)
    point = [float(given.mean()), value_at_risk(given, beta)] + [cvar(given, b) for b in betas]
    low, high = np.percentile(stats, [2.5, 97.5], axis=0)
    names = ["mean", "value_at_risk", "cvar"] + [f"cvar_{b:g}" for b in REPORT_BETAS]
    return {name: {"value": point[i], "low": float(low[i]), "high": float(high[i])} for i, name in enumerate(names)}


def _bootstrap(z_sorted: np.ndarray, betas: np.ndarray, tails: np.ndarray, key: np.uint64, out: np.ndarray) -> None:
    """out[b] = mean, VaR_beta and the CVaRs of resample b: the groups of LANES resamples split among numba's
    thread count of threads (engine.threads), each running `_bootstrap_groups` without the GIL."""
    threads.over_threads(_bootstrap_groups, (out.shape[0] + LANES - 1) // LANES, z_sorted, betas, tails, key, out)


@njit(cache=True, nogil=True)
def _bootstrap_groups(z_sorted, betas, tails, key, out, begin, end):
    """Resample groups begin..end-1 of LANES resamples each: their counts drawn (`count_lanes`, into arrays reused
    from one group to the next), their means summed side by side (`lane_sums`), then VaR and the CVaRs read off
    the sorted counts (`_tails`)."""
    n, resamples = z_sorted.size, out.shape[0]
    lanes = np.zeros((LANES, n), dtype=np.int32)  # past the last resample, a lane's sum is computed and dropped
    drawn = np.empty(n, dtype=np.uint32)
    for group in range(begin, end):
        first = group * LANES
        used = min(LANES, resamples - first)
        count_lanes(key, first, used, lanes, drawn)
        totals = lane_sums(lanes, z_sorted)
        for lane in range(used):
            out[first + lane, 0] = totals[lane] / n
        _tails(z_sorted, lanes, used, betas, tails, out[first : first + used])


@njit(cache=True)
def _tails(z_sorted, lanes, used, betas, tails, rows):
    """rows[lane, 1:] = VaR_beta and the CVaRs of the group's resamples from their counts lanes (LANES, n), `used`
    of them.

    Each CVaR's tail sum of the LANES resamples runs side by side, as the means do: to the longest of their tails,
    a resample's terms past its own tail each a 0.0, which leaves its sum as it was (the sum starts at +0.0 and its
    terms are at most 0, so it is never -0.0). Plain loops and scalars throughout: a tuple indexed at run time, or
    an array's max, took numba a second more to compile in a first run."""
    n = z_sorted.size
    c0, c1, c2, c3 = lanes[0], lanes[1], lanes[2], lanes[3]
    for t in range(betas.size):
        if t > 0 and betas[t] == betas[0]:  # the run's beta is also a reported one: the same numbers
            for lane in range(used):
                rows[lane, 2 + t] = rows[lane, 2]
            continue
        m = tails[t]
        i0 = i1 = i2 = i3 = 0  # each lane's VaR position (an unused lane's stays 0: no terms)
        for lane in range(used):
            seen = 0
            i = 0
            while seen + lanes[lane, i] < m:
                seen += lanes[lane, i]
                i += 1
            if lane == 0:
                i0 = i
            elif lane == 1:
                i1 = i
            elif lane == 2:
                i2 = i
            else:
                i3 = i
            if t == 0:
                rows[lane, 1] = z_sorted[i]
        v0, v1, v2, v3 = z_sorted[i0], z_sorted[i1], z_sorted[i2], z_sorted[i3]
        a0 = a1 = a2 = a3 = 0.0
        for k in range(max(max(i0, i1), max(i2, i3))):
            z = z_sorted[k]
            a0 += c0[k] * (z - v0) if k < i0 else 0.0
            a1 += c1[k] * (z - v1) if k < i1 else 0.0
            a2 += c2[k] * (z - v2) if k < i2 else 0.0
            a3 += c3[k] * (z - v3) if k < i3 else 0.0
        for lane in range(used):
            var, total = (v0, a0) if lane == 0 else (v1, a1) if lane == 1 else (v2, a2) if lane == 2 else (v3, a3)
            rows[lane, 2 + t] = var + total / (betas[t] * n)


def objective_interval(z: np.ndarray, risk, resamples: int, seed: int) -> tuple[dict, np.ndarray]:
    """Point value and 95% percentile-bootstrap interval of the measure of z that `risk` names (a risk node), from
    the very resamples of `bootstrap_intervals` (the same stream): ({"measure", "value", "low", "high"}, each
    resample's value), the latter for intervals of sums over robots."""
    return objective_intervals([z], [risk], resamples, seed)[0]


def objective_intervals(zs: list[np.ndarray], risks: list, resamples: int, seed: int) -> list[tuple[dict, np.ndarray]]:
    """objective_interval of each (z, risk node) pair, the same numbers. The samples of one measure and one size
    bootstrap together (Measure.bootstrap_rows): their resamples' counts are the same, drawn once for all (a team
    whose robots start apart has a term per start, eight bootstraps in one)."""
    key = np.uint64(stream_key(seed, BOOTSTRAP))
    specs = [risk_spec(risk) for risk in risks]
    groups: dict[tuple[int, int], list[int]] = {}
    for i, ((measure, _), z) in enumerate(zip(specs, zs)):
        groups.setdefault((id(measure), np.size(z)), []).append(i)
    sorted_zs: list[np.ndarray] = [np.empty(0)] * len(zs)
    values: list[np.ndarray] = [np.empty(0)] * len(zs)
    for members in groups.values():
        rows = np.empty((len(members), np.size(zs[members[0]])))
        for row, i in zip(rows, members):
            row[:] = np.asarray(zs[i], dtype=float).ravel()
            row.sort()
        out = np.empty((len(members), resamples))
        specs[members[0]][0].bootstrap_rows(rows, [specs[i][1] for i in members], key, out)
        for k, i in enumerate(members):
            sorted_zs[i], values[i] = rows[k], out[k]
    results = []
    for (measure, params), z, resampled in zip(specs, sorted_zs, values):
        low, high = np.percentile(resampled, [2.5, 97.5])
        figure = {"measure": measure.name, "value": float(measure.objective(z, params))}
        results.append((figure | {"low": float(low), "high": float(high)}, resampled))
    return results
