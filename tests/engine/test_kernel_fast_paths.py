"""The kernel's fast paths against the reference kernel: the ziggurat normal sampler against the exact normal, the
affine reward path against the program interpreter, and the episode returns of the paper world from the fast
kernel against `simulate(..., reference=True)` (the interpreter and inverse-CDF normals everywhere).

Every tolerance is a number of standard errors estimated from the samples themselves; nothing is timed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from riskplan.engine import distributions as D
from riskplan.engine import rng
from riskplan.engine.dynamics import _pick, _pick_bits
from riskplan.engine.rollout import affine_form, move_bins, simulate
from riskplan.risk import cvar
from riskplan.run.build import build_setup
from riskplan.run.compose import compose

N = 2_000_000
KS_999 = 1.95  # P(sqrt(n) * KS distance > 1.95) ~ 0.001 under the exact law (Kolmogorov's limit distribution)


@njit(cache=True)
def ziggurat_draws(n, key):
    out = np.empty(n)
    state = rng.episode_state(np.uint64(key), 0)
    for i in range(n):
        state, out[i] = rng.next_normal(state)
    return out


@njit(cache=True)
def inverse_cdf_draws(n, key):
    out = np.empty(n)
    state = rng.episode_state(np.uint64(key), 0)
    for i in range(n):
        state, u = rng.next_uniform(state)
        out[i] = rng.normal_quantile(u)
    return out


@njit(cache=True)
def normal_cdf(x):
    out = np.empty(x.size)
    for i in range(x.size):
        out[i] = 0.5 * math.erfc(-x[i] / math.sqrt(2.0))
    return out


def ks_distance(draws: np.ndarray) -> float:
    """sup |F_n - Phi| of the draws against the exact standard normal CDF."""
    x = np.sort(draws)
    cdf = normal_cdf(x)
    n = x.size
    return float(max(np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n)))


@pytest.mark.parametrize("sampler", [ziggurat_draws, inverse_cdf_draws])
def test_normal_sampler_is_the_standard_normal(sampler):
    z = sampler(N, 12)
    n = z.size
    assert abs(z.mean()) < 4 / math.sqrt(n)
    assert abs(z.var() - 1.0) < 4 * math.sqrt(2.0 / n)
    assert abs(np.mean(z**3)) < 4 * math.sqrt(15.0 / n)  # Var(Z^3) = 15
    assert abs(np.mean(z**4) - 3.0) < 4 * math.sqrt(96.0 / n)  # Var(Z^4) = 105 - 9
    assert ks_distance(z) < KS_999 / math.sqrt(n)
    # the ziggurat's base strip, wedges and tail are separate code: their masses must each be right
    for cut in (0.2152419, 1.0, 2.0, rng.ZIG_R, 4.5):
        p = math.erfc(cut / math.sqrt(2.0))  # P(|Z| > cut)
        assert abs(np.mean(np.abs(z) > cut) - p) < 4 * math.sqrt(p * (1 - p) / n) + 1.0 / n
    assert np.all(np.abs(z) < 14.0)  # the bound riskplan.engine.distributions.NORMAL_SPREAD relies on


def test_ziggurat_tables_have_equal_strips():
    x = rng.ZIG_X
    f = np.exp(-0.5 * x**2)
    strips = x[1:-1] * (f[2:] - f[1:-1])  # strip i >= 1: [0, x_i] x [f(x_i), f(x_{i+1})]
    base = x[1] * f[1] + math.sqrt(math.pi / 2) * math.erfc(x[1] / math.sqrt(2.0))
    np.testing.assert_allclose(strips, base, rtol=1e-9)
    assert x[0] * f[1] == pytest.approx(base, rel=1e-15)
    assert x[-1] == 0.0 and np.all(np.diff(x[1:]) < 0)


PAPER_RISKY = {"clip": [-1e4, 1e4], "of": {"sum": [{"scale": 200, "of": {"uniform": [0, 1]}}, {"normal": [0, 100]}]}}


@pytest.mark.parametrize(
    "data, form",
    [
        (PAPER_RISKY, (0.0, 200.0, 100.0, -1e4, 1e4)),
        ({"scale": 100, "of": {"uniform": [0, 1]}}, (0.0, 100.0, 0.0, -math.inf, math.inf)),
        (-3.0, (-3.0, 0.0, 0.0, -math.inf, math.inf)),
        (
            {"sum": [{"normal": [1, 3]}, {"scale": -2, "of": {"normal": [0, 2]}}, {"uniform": [-1, 1]}]},
            (0.0, 2.0, 5.0, -math.inf, math.inf),
        ),
        ({"scale": -2, "of": {"sum": [{"uniform": [1, 3]}, 4]}}, (-10.0, -4.0, 0.0, -math.inf, math.inf)),
    ],
)
def test_affine_form_of_linear_programs(data, form):
    assert affine_form(D.parse(data)) == pytest.approx(form)


@pytest.mark.parametrize(
    "data",
    [
        {"bernoulli": 0.5},
        {"mixture": [{"weight": 1, "of": 0}, {"weight": 1, "of": 1}]},
        {"sum": [{"uniform": [0, 1]}, {"uniform": [0, 1]}]},
        {"sum": [1, {"clip": [0, 1], "of": {"normal": [0, 1]}}]},
    ],
)
def test_programs_without_an_affine_form_use_the_interpreter(data):
    assert affine_form(D.parse(data)) is None
    setup = build_setup(compose([f"world.regions.1.reward={_yaml(data)}"]))
    assert not setup.kernel.tables.affine
    batch = simulate(
        setup.world, setup.kernel, setup.theta0[None, :], setup.world.starts, rng.robot_keys(0, rng.TRAIN, 0, 1), 500
    )
    assert np.all(np.isfinite(batch.total_reward)) and np.all(batch.steps > 0)


def _yaml(data) -> str:
    """A Hydra override value for a reward tree."""
    if isinstance(data, dict):
        return "{" + ",".join(f"{k}:{_yaml(v)}" for k, v in data.items()) + "}"
    if isinstance(data, list):
        return "[" + ",".join(_yaml(v) for v in data) + "]"
    return repr(data)


@pytest.mark.parametrize(
    "data",
    [
        PAPER_RISKY,
        {"sum": [{"normal": [1, 3]}, {"scale": -2, "of": {"normal": [0, 2]}}, {"uniform": [-1, 1]}]},
        {"clip": [-1, 2], "of": {"scale": -2, "of": {"sum": [{"uniform": [0, 3]}, {"normal": [0, 0.5]}]}}},
    ],
)
def test_affine_form_has_the_law_of_the_program(data):
    """clip(c + w U + s N, lo, hi) in numpy against the program sampled by riskplan.engine.distributions."""
    n = 400_000
    c, w, s, lo, hi = affine_form(D.parse(data))
    gen = np.random.default_rng(5)
    mine = np.clip(c + w * gen.random(n) + s * gen.standard_normal(n), lo, hi)
    theirs = D.sample(D.parse(data), np.random.default_rng(6), n)
    pooled = np.sort(np.concatenate([mine, theirs]))
    gap = np.abs(np.searchsorted(np.sort(mine), pooled, "right") - np.searchsorted(np.sort(theirs), pooled, "right"))
    assert gap.max() / n < KS_999 * math.sqrt(2.0 / n)  # two-sample KS at the 0.1% level


@pytest.fixture(scope="module")
def paper():
    return build_setup(compose([]))


def batch_se(x: np.ndarray, statistic, batches: int = 50) -> float:
    """Standard error of statistic(x), from its spread over `batches` equal slices of the sample."""
    values = [statistic(part) for part in np.array_split(x, batches)]
    return float(np.std(values, ddof=1) / math.sqrt(batches))


STATISTICS = {
    "mean": np.mean,
    "q0.05": lambda z: np.quantile(z, 0.05),
    "q0.1": lambda z: np.quantile(z, 0.1),
    "q0.5": lambda z: np.quantile(z, 0.5),
    "q0.9": lambda z: np.quantile(z, 0.9),
    "std": np.std,
    "cvar0.1": lambda z: cvar(z, 0.1),
}


@pytest.mark.parametrize("theta", [[20.0, 20.0], [46.6, -0.8], [-7.3, 34.6], [-21.0, 9.0]])
def test_new_kernel_gives_the_old_kernels_distribution_on_the_paper_world(paper, theta):
    """Returns, their quantiles and CVaR, steps, risky steps, sources reached and scores: within 4 standard errors."""
    assert paper.kernel.tables.affine  # the paper world takes the fast path
    episodes = 200_000
    keys = rng.robot_keys(3, rng.EVAL, 0, 1)
    new = simulate(paper.world, paper.kernel, np.array([theta]), paper.world.starts, keys, episodes)
    old = simulate(paper.world, paper.kernel, np.array([theta]), paper.world.starts, keys, episodes, reference=True)
    assert not np.array_equal(new.total_reward, old.total_reward)  # other numbers...
    bad = []
    for name, stat in STATISTICS.items():  # ...the same law
        se = math.hypot(batch_se(new.total_reward, stat), batch_se(old.total_reward, stat))
        gap = stat(new.total_reward) - stat(old.total_reward)
        if abs(gap) > 4 * se:
            bad.append(f"{name}: new - old = {gap:.3g}, 4 se = {4 * se:.3g}")
    others = {
        "steps": lambda b: b.steps,
        "risky": lambda b: b.risky_steps,
        "safe": lambda b: b.source_reached == 0,
        "risky source": lambda b: b.source_reached == 1,
        "score 0": lambda b: b.score[:, 0],
        "score 1": lambda b: b.score[:, 1],
        "z * score 0": lambda b: b.total_reward * b.score[:, 0],
    }
    for name, get in others.items():
        a, b = np.asarray(get(new), float), np.asarray(get(old), float)
        se = math.sqrt(a.var() / a.size + b.var() / b.size)
        if abs(a.mean() - b.mean()) > 4 * se + 1e-12:
            bad.append(f"{name}: new - old = {a.mean() - b.mean():.3g}, 4 se = {4 * se:.3g}")
    assert not bad, "\n".join(bad)


def test_reference_path_is_deterministic_and_thread_independent(paper):
    import numba

    keys = rng.robot_keys(0, rng.TRAIN, 0, 1)
    default = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = simulate(paper.world, paper.kernel, paper.theta0[None, :], paper.world.starts, keys, 3000, reference=True)
    finally:
        numba.set_num_threads(default)
    many = simulate(paper.world, paper.kernel, paper.theta0[None, :], paper.world.starts, keys, 3000, reference=True)
    np.testing.assert_array_equal(one.total_reward, many.total_reward)
    np.testing.assert_array_equal(one.score, many.score)


@pytest.mark.parametrize(
    "overrides", [[], ["world.stop_at_source=false"], ["world.regions.0.reward=-5", "world.regions.1.reward=2"]]
)
def test_fast_loop_gives_the_general_loops_numbers(overrides):
    """`_simulate_affine` (no recording) against `_simulate` (recording): the same draws, bit for bit."""
    setup = build_setup(compose(overrides))
    thetas = np.array([[20.0, 20.0], [46.6, -0.8]])
    starts = np.repeat(setup.world.starts[:1], 2)
    keys = rng.robot_keys(1, rng.TRAIN, 0, 2)
    fast = simulate(setup.world, setup.kernel, thetas, starts, keys, 4000)
    general = simulate(setup.world, setup.kernel, thetas, starts, keys, 4000, record=True)
    for name in ("total_reward", "score", "risky_steps", "source_reached", "steps"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(general, name))


@njit(cache=True)
def _picks_agree(cum, bins, probes):
    for c in range(cum.shape[1]):
        for a in range(4):
            for d in range(-2, 3):
                m = bins[0, c, a] + d
                if 0 <= m < probes:
                    if _pick_bits(bins[0, c], m) != _pick(cum[0, c], rng.bits_uniform(np.uint64(m))):
                        return False
    return True


def test_integer_bins_pick_exactly_the_float_compares_move():
    gen = np.random.default_rng(0)
    raw = gen.random((1, 500, 5)) ** gen.integers(1, 40, (1, 500, 1))  # tiny and ordinary probabilities
    cum = np.cumsum(raw / raw.sum(axis=2, keepdims=True), axis=2)
    cum[0, :4] = [
        [0.5, 0.5, 0.75, 1 - 2**-53, 1.0],
        [0.0, 2**-60, 0.5 - 2**-54, 1.0, 1.0],
        [0.1, 0.2, 0.30000000000000004, 1 + 2**-52, 1.0],
        [2**-53, 2**-52, 3 * 2**-53, 0.25, 1.0],
    ]
    bins = move_bins(cum)
    assert _picks_agree(cum, bins, 2**53)


def test_integer_bins_are_exact_where_the_closed_form_changes_rounding():
    """Around 1/2 (X = 2^52, where m + 0.5 stops being exact), at powers of two and next to 0 and 1."""
    near = [b + k * 2.0**-54 for b in (0.5, 0.25, 0.75, 1.0) for k in range(-6, 7)]
    near += [np.nextafter(b, d) for b in (0.5, 0.25, 0.75, 1.0, 0.0) for d in (-1.0, 2.0)]
    near += [2.0**-e for e in range(1, 60)] + [1 - 2.0**-e for e in range(1, 54)]
    near += [0.5 - 2.0**-e for e in range(2, 55)]
    values = np.array([v for v in near if 0.0 <= v <= 1.0])
    values = np.resize(values, (len(values) + 3) // 4 * 4).reshape(-1, 4)
    for shift in range(4):  # every value at every move index
        cum = np.concatenate([np.roll(values, shift, axis=1), np.ones((len(values), 1))], axis=1)[None]
        assert _picks_agree(cum, move_bins(cum), 2**53)
