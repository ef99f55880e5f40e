"""A large sample's statistics and gradients on every core (riskplan.engine.reductions) are numpy's numbers bit for
bit: its pairwise sums (mean, std, CVaR's tail), the element its partition selects (VaR), its einsum's order
(the gradients), at 1 thread and at 2; and a training step takes them from PARALLEL_SAMPLES samples on, with the
same estimates as numpy's."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from support import setup_of

from riskplan.engine import estimators, reductions
from riskplan.engine.step import estimate, initial_state, rollouts

W = reductions.PARALLEL_SAMPLES


def bits(values) -> np.ndarray:
    """The float64 bits, so that 0.0 and -0.0 differ and NaN equals itself."""
    return np.ascontiguousarray(values, dtype=np.float64).view(np.uint64)


def samples(kind: str, rows: int, n: int, seed: int = 0) -> np.ndarray:
    """Rows of n samples: smooth, heavily tied, two-valued, heavy-tailed, or one value repeated."""
    rng = np.random.default_rng(seed)
    if kind == "normal":
        return rng.normal(1500.0, 400.0, (rows, n))
    if kind == "ties":
        return np.round(rng.normal(1500.0, 400.0, (rows, n)) / 100.0) * 100.0
    if kind == "two":
        return np.where(rng.random((rows, n)) < 0.3, 1000.0, 3000.0)
    if kind == "cauchy":
        return rng.standard_cauchy((rows, n)) * 1e3
    return np.full((rows, n), 1234.5)


@pytest.fixture(params=[1, 2], ids=["1 thread", "2 threads"])
def threads(request):
    before = numba.get_num_threads()
    numba.set_num_threads(min(request.param, numba.config.NUMBA_NUM_THREADS))
    yield request.param
    numba.set_num_threads(before)


@pytest.mark.parametrize("kind", ["normal", "ties", "two", "cauchy", "constant"])
@pytest.mark.parametrize(("rows", "n"), [(1, W), (3, W + 4097)])
def test_sums_selection_and_products_are_numpys(threads, kind, rows, n):
    z = samples(kind, rows, n)
    mean = z.mean(axis=-1)
    assert np.array_equal(bits(reductions.row_sums(z)), bits(z.sum(axis=-1)))
    assert np.array_equal(bits(reductions.row_sums(z, reductions.SQUARES, mean) / n), bits(z.var(axis=-1)))
    for m in (1, 7, int(0.1 * n) + 1, n // 2, n):
        v = np.partition(z, m - 1, axis=-1)[:, m - 1]
        assert np.array_equal(bits(reductions.value_at_risk(z, m)), bits(v)), m
        tail = np.minimum(z - v[:, None], 0.0)
        assert np.array_equal(bits(reductions.row_sums(z, reductions.TAIL, v)), bits(tail.sum(axis=-1)))
    scores = np.random.default_rng(1).normal(0.0, 1.0, (rows, n, 3))
    expected = np.einsum("...w,...wm->...m", tail, scores)
    assert np.array_equal(bits(reductions.tail_products(z, scores, v)), bits(expected))
    centred = np.einsum("...w,...wm->...m", z - mean[:, None], scores)
    assert np.array_equal(bits(reductions.centred_products(z, scores, mean)), bits(centred))


@pytest.mark.parametrize("dims", [2, 8, 11])  # below, at and past a block of COLUMNS gradient columns
def test_the_gradients_keep_einsums_order_for_any_number_of_columns(threads, dims):
    z = samples("normal", 2, W + 11, seed=dims)
    scores = np.random.default_rng(dims).normal(0.0, 1.0, z.shape + (dims,))
    v = np.partition(z, 999, axis=-1)[:, 999]
    expected = np.einsum("...w,...wm->...m", np.minimum(z - v[:, None], 0.0), scores)
    assert np.array_equal(bits(reductions.tail_products(z, scores, v)), bits(expected))
    mean = z.mean(axis=-1)
    expected = np.einsum("...w,...wm->...m", z - mean[:, None], scores)
    assert np.array_equal(bits(reductions.centred_products(z, scores, mean)), bits(expected))


def test_a_negative_zero_leaves_the_selection_to_numpy():
    z = samples("two", 1, W) - 1000.0  # 0.0 and 2000.0
    z[0, ::3] = -0.0
    m = W // 2
    assert np.array_equal(bits(reductions.value_at_risk(z, m)), bits(np.partition(z, m - 1, axis=-1)[:, m - 1]))


def test_the_leaves_are_numpys_pairwise_tree():
    first, count = reductions.leaves(100_003)
    assert len(first) == reductions.LEAVES and first[0] == 0 and count.sum() == 100_003
    assert np.array_equal(first[1:], np.cumsum(count)[:-1]) and count.min() > reductions.BLOCK
    with pytest.raises(ValueError, match="too few"):
        reductions.leaves(1000)


@pytest.mark.parametrize("shape", [(W,), (2, W + 3)])
def test_the_parallel_estimators_give_numpys_numbers(threads, shape):
    z = samples("normal", 1, int(np.prod(shape)), seed=3).reshape(shape)
    scores = np.random.default_rng(4).normal(0.0, 1.0, shape + (2,))
    for beta in (0.05, 0.1, 1.0):
        serial, parallel = estimators.summary_stats(z, beta), estimators.summary_stats(z, beta, parallel=True)
        assert list(serial) == list(parallel)
        for name in serial:
            assert type(serial[name]) is type(parallel[name]), name
            assert np.array_equal(bits(serial[name]), bits(parallel[name])), name
        var = serial["value_at_risk"]
        for given in (None, var):
            assert np.array_equal(
                bits(estimators.cvar_gradient(z, scores, beta, var=given)),
                bits(estimators.cvar_gradient(z, scores, beta, var=given, parallel=True)),
            )
    for baseline in (True, False):
        assert np.array_equal(
            bits(estimators.mean_gradient(z, scores, baseline)),
            bits(estimators.mean_gradient(z, scores, baseline, parallel=True)),
        )
    one = scores[..., :1]  # M = 1: numpy's einsum sums in SIMD lanes, so numpy computes it
    assert np.array_equal(bits(estimators.mean_gradient(z, one)), bits(estimators.mean_gradient(z, one, parallel=True)))


@pytest.mark.parametrize("risk", ["risk=cvar", "risk=neutral", "risk=mean_cvar", "risk.schedule.kind=linear"])
def test_a_large_steps_estimates_are_numpys(risk, monkeypatch):
    setup = setup_of(f"train.samples={W}", risk, "experiment=paper_team")
    thetas = initial_state(setup).thetas
    z, scores = rollouts(setup, 0, thetas)
    calls = []
    original = reductions.row_sums
    monkeypatch.setattr(reductions, "row_sums", lambda *args: calls.append(1) or original(*args))
    parallel = estimate(setup, 0, z, scores)
    assert calls  # the step took the kernels
    monkeypatch.setattr(reductions, "PARALLEL_SAMPLES", 10 * W)  # numpy alone
    serial = estimate(setup, 0, z, scores)
    assert np.array_equal(bits(parallel.grads), bits(serial.grads))
    for name in serial.stats:
        assert np.array_equal(bits(parallel.stats[name]), bits(serial.stats[name])), name
