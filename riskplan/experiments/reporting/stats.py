"""Small statistics for the report: across-seed means with t intervals, Wilson intervals, empirical CDFs."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd

# Two-sided 95% Student-t quantiles t_{0.975, df} for df = 1..30 (beyond: normal 1.96 as the limit).
_T975 = (
    12.706,
    4.303,
    3.182,
    2.776,
    2.571,
    2.447,
    2.365,
    2.306,
    2.262,
    2.228,
    2.201,
    2.179,
    2.160,
    2.145,
    2.131,
    2.120,
    2.110,
    2.101,
    2.093,
    2.086,
    2.080,
    2.074,
    2.069,
    2.064,
    2.060,
    2.056,
    2.052,
    2.048,
    2.045,
    2.042,
)


def t975(df: int) -> float:
    """The 97.5% quantile of Student's t with df degrees of freedom."""
    if df < 1:
        return math.nan
    if df <= len(_T975):
        return _T975[df - 1]
    return 1.96 + 2.4 / df  # within 0.002 of the exact value for df > 30


def seed_interval(values) -> tuple[float, float, float]:
    """(mean, low, high): the across-seed mean and its 95% t interval; the interval is NaN for one seed."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return math.nan, math.nan, math.nan
    mean = float(v.mean())
    if v.size < 2:
        return mean, math.nan, math.nan
    half = t975(v.size - 1) * float(v.std(ddof=1)) / math.sqrt(v.size)
    return mean, mean - half, mean + half


def band(table: pd.DataFrame, log: bool = False) -> pd.DataFrame:
    """Per row (iteration) of a (iterations x seeds) table: mean, low, high and n across the seeds.

    With log=True the statistics are taken on log10 of the positive values (geometric mean and a multiplicative
    band), which is what a log-scale axis shows.
    """
    values = table.to_numpy(dtype=float)
    if log:
        values = np.where(values > 0, values, np.nan)
        values = np.log10(values)
    n = np.sum(np.isfinite(values), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(np.where(np.isfinite(values), values, np.nan), axis=1) if values.size else np.array([])
        sd = np.nanstd(values, axis=1, ddof=1) if values.shape[1] > 1 else np.full(len(values), np.nan)
    half = np.array([t975(int(k) - 1) if k > 1 else math.nan for k in n]) * sd / np.sqrt(np.maximum(n, 1))
    low, high = mean - half, mean + half
    if log:
        mean, low, high = 10.0**mean, 10.0**low, 10.0**high
    return pd.DataFrame({"mean": mean, "low": low, "high": high, "n": n}, index=table.index)


def wilson(successes: float, n: int) -> tuple[float, float]:
    """95% Wilson score interval of a proportion."""
    if n <= 0:
        return math.nan, math.nan
    z = 1.959963984540054
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    low = 0.0 if successes <= 0 else max(0.0, centre - half)
    high = 1.0 if successes >= n else min(1.0, centre + half)
    return low, high
