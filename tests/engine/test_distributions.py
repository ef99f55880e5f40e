"""Reward distributions (riskplan.engine.distributions): parsing, errors, the kernel's programs against numpy, mixture
weights whose sum overflows, bounds by interval arithmetic, and programs that could overflow or nest too deep."""

from __future__ import annotations

import numpy as np
import pytest

from riskplan.engine import distributions as D
from riskplan.engine.dynamics import _draw
from riskplan.engine.world import MAX_STACK
from riskplan.util.errors import BadInput

PAPER_RISKY = {"clip": [-1e4, 1e4], "of": {"sum": [{"scale": 200, "of": {"uniform": [0, 1]}}, {"normal": [0, 100]}]}}


def kernel_sample(data, n: int, seed: int = 0) -> np.ndarray:
    """n draws of a distribution through the numba postfix interpreter."""
    ops, params = D.compile_program(D.parse(data))
    stack = np.empty(MAX_STACK)
    state = np.uint64(seed)
    out = np.empty(n)
    for i in range(n):
        out[i], state = _draw(ops, params, 0, len(ops), stack, np.uint64(state))
    return out


@pytest.mark.parametrize(
    "data",
    [
        3.5,
        {"constant": -2},
        {"uniform": [0, 1]},
        {"normal": [2000, 2000]},
        {"bernoulli": 0.01},
        {"mixture": [{"weight": 0.99, "of": 0}, {"weight": 0.01, "of": {"normal": [-1e4, 10]}}]},
        {"sum": [1, {"uniform": [-1, 1]}]},
        PAPER_RISKY,
    ],
)
def test_round_trip(data):
    dist = D.parse(data)
    assert D.parse(D.to_data(dist)) == dist


@pytest.mark.parametrize(
    "data, where",
    [
        ("normal(0,1)", "reward"),
        ({"gauss": [0, 1]}, "reward"),
        ({"normal": [0, -1]}, "reward.normal"),
        ({"uniform": [2, 1]}, "reward.uniform"),
        ({"bernoulli": 1.5}, "reward.bernoulli"),
        ({"scale": 2}, "reward"),
        ({"clip": [0, 1], "of": {"normal": [0]}}, "reward.of.normal"),
        ({"mixture": [{"weight": 1}]}, "reward.mixture.0"),
        ({"sum": []}, "reward.sum"),
        (True, "reward"),
        ({"normal": [0, float("inf")]}, "reward.normal"),
        ({"normal": [0, 1], "uniform": [0, 1]}, "reward"),
    ],
)
def test_garbage_is_rejected_with_the_key(data, where):
    with pytest.raises(BadInput) as err:
        D.parse(data)
    assert err.value.where == where


def test_paper_risky_reward_moments_in_kernel_and_numpy():
    """200 a + d, a ~ U[0,1], d ~ N(0, 100^2): mean 100, variance 200^2/12 + 100^2 (clipping is negligible)."""
    expected_std = np.sqrt(200**2 / 12 + 100**2)
    for draws in (
        kernel_sample(PAPER_RISKY, 200_000),
        D.sample(D.parse(PAPER_RISKY), np.random.default_rng(0), 200_000),
    ):
        assert draws.mean() == pytest.approx(100.0, abs=1.5)
        assert draws.std() == pytest.approx(expected_std, rel=0.01)


def test_kernel_clip_mixture_bernoulli():
    clipped = kernel_sample({"clip": [-1, 1], "of": {"normal": [0, 10]}}, 20_000)
    assert clipped.min() == -1.0 and clipped.max() == 1.0
    assert np.mean(np.abs(clipped) == 1.0) == pytest.approx(1 - 0.0797, abs=0.01)  # P(|N(0,100)| > 1)
    mixture = kernel_sample({"mixture": [{"weight": 3, "of": 1}, {"weight": 1, "of": 5}]}, 40_000)
    assert set(np.unique(mixture)) == {1.0, 5.0}
    assert np.mean(mixture == 5.0) == pytest.approx(0.25, abs=0.01)
    rare = kernel_sample({"scale": -1e4, "of": {"bernoulli": 0.02}}, 50_000)
    assert set(np.unique(rare)) == {-1e4, 0.0}
    assert np.mean(rare < 0) == pytest.approx(0.02, abs=0.003)


def test_kernel_normal_quantiles():
    draws = np.sort(kernel_sample({"normal": [0, 1]}, 100_000, seed=7))
    for q, value in ((0.01, -2.3263), (0.1, -1.2816), (0.5, 0.0), (0.9, 1.2816), (0.99, 2.3263)):
        assert draws[int(q * draws.size)] == pytest.approx(value, abs=0.03)


@pytest.mark.parametrize("leaf", [{"constant": 3.0}, {"uniform": [1, 4]}, {"normal": [2, 3]}])
@pytest.mark.parametrize("k", [200.0, -0.5])
def test_a_scaled_leaf_compiles_to_one_op_that_draws_k_times_the_leaf(leaf, k):
    """scale folds into its leaf (k*U[a,b], k*N(m,s), k*c): one op, the same draws up to rounding, any sign of k."""
    ops, _ = D.compile_program(D.parse({"scale": k, "of": leaf}))
    assert len(ops) == 1
    np.testing.assert_allclose(
        kernel_sample({"scale": k, "of": leaf}, 1000), k * kernel_sample(leaf, 1000), rtol=1e-12, atol=1e-12
    )


# ---------------------------------------------------------------------------------------------- overflow and nesting


@pytest.mark.parametrize("weights", [[1e308, 1e308], [1.7e308, 1.7e308, 1.7e308, 1.7e308], [1.5e308, 1.5e308]])
def test_mixture_weights_whose_sum_overflows_still_pick_each_component_equally(weights):
    # sum(w) is inf, so w / sum(w) was 0 for every component: the kernel always drew the last one, numpy raised
    data = {"mixture": [{"weight": w, "of": k} for k, w in enumerate(weights)]}
    n, k = 20_000, len(weights)
    for draws in (kernel_sample(data, n, seed=3), D.sample(D.parse(data), np.random.default_rng(3), n)):
        counts = np.bincount(draws.astype(int), minlength=k)
        p = 1.0 / k
        assert np.all(np.abs(counts / n - p) < 5 * np.sqrt(p * (1 - p) / n)), counts


def test_normalised_weights_are_unchanged_when_the_sum_is_finite():
    weights = (0.99, 0.01, 3.0)
    assert D.normalised(weights) == [w / sum(weights) for w in weights]
    assert D.normalised((1e308, 1e308)) == [0.5, 0.5]


@pytest.mark.parametrize(
    "data, where",
    [
        (1e200, "reward"),
        ({"uniform": [-1e308, 1e308]}, "reward"),  # hi - lo overflows to inf in the kernel's lo + (hi - lo) u
        ({"normal": [0, 1e300]}, "reward"),
        ({"scale": 1e300, "of": {"uniform": [0, 1]}}, "reward"),
        ({"sum": [1, {"constant": 1e101}]}, "reward.sum.1"),
        ({"clip": [-1, 1], "of": {"sum": [6e99, 6e99]}}, "reward.of"),  # an intermediate beyond the limit
        ({"mixture": [{"weight": 1, "of": 0}, {"weight": 1, "of": {"normal": [1e100, 1e98]}}]}, "reward.mixture.1.of"),
    ],
)
def test_programs_that_could_overflow_are_rejected_naming_the_node(data, where):
    with pytest.raises(BadInput) as err:
        D.check_bound(D.parse(data), "reward")
    assert err.value.where == where
    assert "beyond the limit of 1e+100" in err.value.problem


def test_bounds_are_interval_arithmetic():
    assert D.bound(D.parse(PAPER_RISKY)) == 200 + 40 * 100  # clip [-1e4, 1e4] does not bind
    assert D.bound(D.parse({"clip": [5, 7], "of": {"normal": [0, 1e6]}})) == 7
    assert D.bound(D.parse({"clip": [5, 7], "of": 1})) == 5  # clipped up to the lower bound
    assert D.bound(D.parse({"scale": 0, "of": {"sum": [1e308, 1e308]}})) == 0  # never 0 * inf
    assert D.bound(D.parse({"sum": [{"bernoulli": 0.5}, {"uniform": [-3, 2]}]})) == 4
    assert D.check_bound(D.parse({"normal": [0, 1e98]})) == pytest.approx(4e99)


def test_a_deeply_nested_program_is_one_line_not_a_recursion_error():
    data: object = 1.0
    for _ in range(5000):
        data = {"scale": 1, "of": data}
    with pytest.raises(BadInput) as err:
        D.parse(data)
    assert "nests more than 32 levels deep" in str(err.value)
    assert err.value.where == "reward" + ".of" * 32
    shallow: object = 1.0
    for _ in range(31):
        shallow = {"scale": 1, "of": shallow}
    assert D.bound(D.parse(shallow)) == 1
