"""The radix argsort behind the spectral measures: np.argsort(kind="stable") exactly, on either side of the size
where it hands over to a comparison sort, with ties, signed zeros, infinities and digits that all keys share."""

from __future__ import annotations

import numpy as np
import pytest

from riskplan.engine.sorting import SMALL, argsort_into, workspace


def _rows(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(n)
    normal = rng.normal(1000.0, 300.0, n)
    return {
        "normal": normal,
        "ties, signed zeros": rng.normal(0.0, 2.0, n).round(),  # round gives -0.0 as well as 0.0
        "constant": np.full(n, 7.25),  # every digit shared: no pass runs
        "one exponent": 1.0 + rng.random(n),  # the top digits are shared and skipped
        "all negative": -np.abs(normal),
        "extremes": np.where(rng.random(n) < 0.1, rng.choice([np.inf, -np.inf, 1e-300, -1e300, 5e-324], n), normal),
    }


@pytest.mark.parametrize("n", [1, 2, SMALL - 1, SMALL, SMALL + 1, 6000])
def test_argsort_into_is_numpys_stable_argsort(n):
    order = np.empty(n, np.int64)
    keys, spare, counts = workspace(n)
    for name, row in _rows(n).items():
        argsort_into(row, order, keys, spare, counts)
        np.testing.assert_array_equal(order, np.argsort(row, kind="stable"), err_msg=name)


def test_argsort_into_reuses_its_workspace_between_rows():
    rows = np.random.default_rng(3).normal(size=(4, 3000)).round(2)
    order = np.empty(3000, np.int64)
    keys, spare, counts = workspace(3000)
    for row in rows:  # stale counters or keys from the row before would misplace this row's samples
        argsort_into(row, order, keys, spare, counts)
        np.testing.assert_array_equal(order, np.argsort(row, kind="stable"))
