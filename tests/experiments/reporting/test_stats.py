"""Intervals across seeds (riskplan.experiments.reporting.stats), on known answers: Student's t quantiles, the t
interval of a seed mean, the Wilson interval of a proportion, and the per-iteration band (arithmetic or geometric)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from riskplan.experiments.reporting.stats import band, seed_interval, t975, wilson

Z = 1.959963984540054  # the 97.5% quantile of N(0, 1)


def test_t_quantiles_from_the_table_and_beyond_it():
    assert (t975(1), t975(2), t975(10), t975(30)) == (12.706, 4.303, 2.228, 2.042)
    assert t975(100) == pytest.approx(1.984, abs=0.002) and math.isnan(t975(0))


def test_seed_interval_is_the_t_interval_of_the_finite_values():
    assert seed_interval([1.0, 2.0, 3.0]) == pytest.approx(
        (2.0, 2.0 - 4.303 / math.sqrt(3), 2.0 + 4.303 / math.sqrt(3))
    )
    assert seed_interval([np.nan, 4.0, 6.0, np.inf]) == pytest.approx((5.0, 5.0 - 12.706, 5.0 + 12.706))  # sd sqrt(2)
    mean, low, high = seed_interval([5.0])
    assert mean == 5.0 and math.isnan(low) and math.isnan(high)  # one seed: no interval
    assert all(math.isnan(v) for v in seed_interval([np.nan]))


def test_wilson_interval_known_values():
    assert wilson(0, 10) == pytest.approx((0.0, Z**2 / (10 + Z**2)))  # 0.2775: the upper end with no success
    assert wilson(10, 10) == pytest.approx((10 / (10 + Z**2), 1.0))
    low, high = wilson(5, 10)
    assert (low, high) == pytest.approx((0.2366, 0.7634), abs=5e-5) and low + high == pytest.approx(1.0)
    assert all(math.isnan(v) for v in wilson(3, 0))


def test_band_is_the_mean_and_t_interval_per_iteration_arithmetic_or_geometric():
    table = pd.DataFrame([[1.0, 3.0], [2.0, np.nan]])
    rows = band(table)
    assert rows["mean"].tolist() == [2.0, 2.0] and rows["n"].tolist() == [2, 1]
    assert (rows.low[0], rows.high[0]) == pytest.approx((2.0 - 12.706, 2.0 + 12.706))  # sd sqrt(2) over sqrt(2)
    assert np.isnan(rows.low[1]) and np.isnan(rows.high[1])  # one finite seed: no band
    geometric = band(pd.DataFrame([[1.0, 3.0], [10.0, 1000.0]]), log=True)
    assert geometric["mean"].tolist() == pytest.approx([math.sqrt(3.0), 100.0])
    assert geometric.low[1] * geometric.high[1] == pytest.approx(100.0**2)  # symmetric on the log axis
