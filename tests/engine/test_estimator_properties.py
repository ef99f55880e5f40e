"""Properties of the risk estimators (hypothesis): VaR and CVaR bounds, monotonicity and equivariances, batched rows,
and the gradients of eqs. (4) and (9) with a constant score. The examples are derandomized (tests/conftest.py)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from riskplan.risk import cvar, cvar_gradient, mean_gradient, summary_stats, tail_count, value_at_risk

LIMIT = 1e6
values = st.floats(-LIMIT, LIMIT, allow_nan=False, allow_infinity=False)
samples = hnp.arrays(np.float64, st.integers(1, 200), elements=values)
betas = st.floats(1e-3, 1.0, exclude_min=False)


def tol(*arrays) -> float:
    """Round-off allowance for sums of numbers as large as those given."""
    scale = max(float(np.max(np.abs(a))) if np.size(a) else 0.0 for a in arrays)
    return 1e-9 * (1.0 + scale)


@given(samples, betas)
def test_cvar_below_var_below_max_and_above_min(z, beta):
    c, v = cvar(z, beta), value_at_risk(z, beta)
    assert z.min() - tol(z) <= c <= v <= z.max()


@given(samples, betas)
def test_var_is_the_ceil_beta_w_th_smallest_sample(z, beta):
    m = tail_count(beta, z.size)
    assert m == min(max(math.ceil(beta * z.size - 1e-9 * max(1.0, beta * z.size)), 1), z.size)
    assert value_at_risk(z, beta) == np.sort(z)[m - 1]


@given(samples, betas, betas)
def test_cvar_is_monotone_in_beta(z, b1, b2):
    low, high = sorted((b1, b2))
    assert cvar(z, low) <= cvar(z, high) + tol(z)


@given(samples)
def test_cvar_at_beta_one_is_the_mean(z):
    assert math.isclose(cvar(z, 1.0), z.mean(), rel_tol=0, abs_tol=tol(z))


@given(st.integers(1, 60), st.integers(1, 60), st.data())
def test_cvar_is_the_mean_of_the_m_lowest_when_beta_w_is_whole(m, extra, data):
    w = m + extra - 1 if m + extra - 1 >= m else m
    z = data.draw(hnp.arrays(np.float64, w, elements=values, unique=True))
    assert math.isclose(cvar(z, m / w), np.sort(z)[:m].mean(), rel_tol=0, abs_tol=tol(z))


@given(samples, betas, values)
def test_translation_equivariance(z, beta, c):
    shifted = z + c
    assert value_at_risk(shifted, beta) == value_at_risk(z, beta) + c  # float addition keeps the order
    assert math.isclose(cvar(shifted, beta), cvar(z, beta) + c, rel_tol=0, abs_tol=tol(z, shifted))


@given(samples, betas, st.floats(1e-3, 1e3))
def test_positive_scaling_equivariance(z, beta, a):
    scaled = a * z
    assert value_at_risk(scaled, beta) == a * value_at_risk(z, beta)  # float product keeps the order
    assert math.isclose(cvar(scaled, beta), a * cvar(z, beta), rel_tol=1e-9, abs_tol=tol(scaled))


@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 4), st.integers(1, 50)), elements=values), betas)
def test_batched_estimators_equal_row_by_row(z, beta):
    stats = summary_stats(z, beta)
    for i, row in enumerate(z):
        assert cvar(z, beta)[i] == cvar(row, beta) == stats["cvar"][i]
        assert value_at_risk(z, beta)[i] == value_at_risk(row, beta) == stats["value_at_risk"][i]
        assert stats["mean"][i] == row.mean()


@given(samples, betas, st.floats(-10, 10))
def test_gradients_with_a_constant_score(z, beta, s):
    """With the same score s for every trajectory, eq. (9) is s * (CVaR - VaR) and the baselined mean gradient is 0."""
    scores = np.full((z.size, 1), s)
    assert math.isclose(
        cvar_gradient(z, scores, beta)[0],
        s * (cvar(z, beta) - value_at_risk(z, beta)),
        rel_tol=1e-9,
        abs_tol=10 * tol(z),
    )
    assert math.isclose(mean_gradient(z, scores)[0], 0.0, abs_tol=10 * tol(z))
    assert math.isclose(mean_gradient(z, scores, baseline=False)[0], s * z.mean(), rel_tol=1e-9, abs_tol=10 * tol(z))
