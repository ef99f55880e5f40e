"""Final figures of a run: the point values of mean, VaR and CVaRs on the evaluation episodes, with 95% percentile-bootstrap intervals."""

from __future__ import annotations

import numpy as np
from numba import njit

from riskplan.engine.estimators import cvar, tail_count, value_at_risk
from riskplan.engine.measures.registry import risk_spec
from riskplan.engine.rng import BOOTSTRAP, resample_counts, stream_key
from riskplan.engine.threads import over_threads

REPORT_BETAS = (0.05, 0.1, 0.2)


def bootstrap_intervals(z: np.ndarray, beta: float, resamples: int, seed: int) -> dict[str, dict[str, float]]:
    """Point value and 95% percentile-bootstrap interval of mean, VaR_beta, CVaR_beta and CVaR at REPORT_BETAS."""
    z = np.sort(np.asarray(z, dtype=float))
    if not 0 < z.size < 2**31:  # int32 counts, 32-bit index draws
        raise ValueError(f"bootstrap needs 1 to 2^31 - 1 values, got {z.size}")
    betas = np.array([beta, *REPORT_BETAS])
    tails = np.array([tail_count(b, z.size) for b in betas], dtype=np.int64)
    stats = np.empty((resamples, 2 + len(betas)))
    _bootstrap(z, betas, tails, np.uint64(stream_key(seed, BOOTSTRAP)), stats)
    point = [float(z.mean()), value_at_risk(z, beta)] + [cvar(z, b) for b in betas]
    low, high = np.percentile(stats, [2.5, 97.5], axis=0)
    names = ["mean", "value_at_risk", "cvar"] + [f"cvar_{b:g}" for b in REPORT_BETAS]
    return {name: {"value": point[i], "low": float(low[i]), "high": float(high[i])} for i, name in enumerate(names)}


LANES = 4  # resamples summed side by side: four independent chains of additions instead of one


def _bootstrap(z_sorted: np.ndarray, betas: np.ndarray, tails: np.ndarray, key: np.uint64, out: np.ndarray) -> None:
    """out[b] = mean, VaR_beta and the CVaRs of resample b: the groups of LANES resamples split among numba's
    thread count of threads (engine.threads), each running `_bootstrap_groups` without the GIL."""
    over_threads(_bootstrap_groups, (out.shape[0] + LANES - 1) // LANES, z_sorted, betas, tails, key, out)


@njit(cache=True, nogil=True)
def _bootstrap_groups(z_sorted, betas, tails, key, out, begin, end):
    """Resample groups begin..end-1: each resample draws n indices (`resample_counts`), then reads mean, VaR and
    CVaRs off the sorted counts.

    The means of LANES resamples are summed in one pass, each in its own order: a sum's additions wait on each
    other, and four chains keep the core busy (the same numbers, a quarter less time).
    """
    n, resamples = z_sorted.size, out.shape[0]
    for group in range(begin, end):
        first = group * LANES
        c0 = resample_counts(key, first, n)
        c1 = resample_counts(key, first + 1, n) if first + 1 < resamples else c0  # past the end: a stand-in
        c2 = resample_counts(key, first + 2, n) if first + 2 < resamples else c0
        c3 = resample_counts(key, first + 3, n) if first + 3 < resamples else c0
        t0 = t1 = t2 = t3 = 0.0
        for i in range(n):
            t0 += c0[i] * z_sorted[i]
            t1 += c1[i] * z_sorted[i]
            t2 += c2[i] * z_sorted[i]
            t3 += c3[i] * z_sorted[i]
        lanes, totals = (c0, c1, c2, c3), (t0, t1, t2, t3)
        for lane in range(min(LANES, resamples - first)):
            _tails(z_sorted, lanes[lane], totals[lane], betas, tails, out[first + lane])


@njit(cache=True)
def _tails(z_sorted, counts, total, betas, tails, row):
    """row = mean, VaR_beta and the CVaRs of one resample, from its counts and the sum of its values."""
    n = z_sorted.size
    row[0] = total / n
    for t in range(betas.size):
        if t > 0 and betas[t] == betas[0]:  # the run's beta is also a reported one: the same numbers
            row[2 + t] = row[2]
            continue
        m = tails[t]
        seen = 0
        i = 0
        while seen + counts[i] < m:
            seen += counts[i]
            i += 1
        v = z_sorted[i]
        if t == 0:
            row[1] = v
        tail = 0.0
        for k in range(i):
            tail += counts[k] * (z_sorted[k] - v)
        row[2 + t] = v + tail / (betas[t] * n)


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
