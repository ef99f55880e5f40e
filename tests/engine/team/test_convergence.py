"""Consensus error and SLEM (riskplan.engine.team.convergence): the SLEM's closed forms and numpy's eigenvalues, and
the consensus error's known values and its pruned computation against the brute-force definition, bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support import net_of, team_conf

from riskplan.engine.team.convergence import consensus_error, second_largest_eigenvalue_modulus
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import build_network


def ring_metropolis_slem(n):
    return max(abs(1 / 3 + 2 / 3 * math.cos(2 * math.pi * k / n)) for k in range(1, n))


@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_slem_closed_forms(n):
    slem = lambda **kw: net_of(robots=n, **kw).slem
    assert slem(graph="line") == pytest.approx((1 + 2 * math.cos(math.pi / n)) / 3, abs=1e-12)
    assert slem(graph="ring") == pytest.approx(ring_metropolis_slem(n), abs=1e-12)
    assert slem(graph="ring", weights="lazy") == pytest.approx(math.cos(math.pi / n) ** 2, abs=1e-12)
    assert slem(graph="star") == pytest.approx(1 - 1 / n, abs=1e-12)
    assert slem(graph="complete") == pytest.approx(0.0, abs=1e-12)
    assert slem(graph="complete", weights="max_degree") == pytest.approx(0.0, abs=1e-12)
    # Directed lazy ring: eigenvalues (1 + e^{2 pi i k/n}) / 2 have moduli |cos(pi k / n)|.
    assert slem(graph="ring", directed=True, weights="lazy") == pytest.approx(math.cos(math.pi / n), abs=1e-12)


def test_slem_matches_numpy_eig_on_grid_and_geometric():
    for kw in ({"graph": "grid", "robots": 9}, {"graph": "random_geometric", "robots": 9, "radius": 0.6}):
        w = net_of(**kw).weights[:, :, 0]
        moduli = np.sort(np.abs(np.linalg.eigvals(w)))
        assert second_largest_eigenvalue_modulus(w) == pytest.approx(moduli[-2], abs=1e-10)
    assert second_largest_eigenvalue_modulus(np.eye(2)) == pytest.approx(1.0)  # no links: no consensus
    assert second_largest_eigenvalue_modulus([[1.0]]) == 0.0


def test_consensus_error_known_values():
    assert consensus_error(np.array([[0.0, 0.0], [3.0, 4.0], [1.0, 0.0]])) == 5.0
    assert consensus_error(np.array([[1.0, 2.0], [1.0, 2.0]])) == 0.0


def brute_force_error(thetas: np.ndarray) -> float:
    """The definition, over all N^2 pairs at once (consensus_error's former body)."""
    t = np.asarray(thetas, dtype=float)
    if len(t) <= 1:
        return 0.0
    gaps = t[:, None, :] - t[None, :, :]
    return float(np.sqrt((gaps**2).sum(axis=-1)).max())


def test_consensus_error_known_answers_beyond_the_first_block():
    grid = np.array([[i, j] for i in range(30) for j in range(20)], dtype=float)  # 600 rows: the pruned path
    grid = grid[np.random.default_rng(0).permutation(len(grid))]
    assert consensus_error(grid) == math.sqrt(29**2 + 19**2)
    ball = np.random.default_rng(1).normal(size=(500, 3))
    ball /= 2 * np.linalg.norm(ball, axis=1, keepdims=True)  # radius 1/2 around 0
    cloud = np.vstack([ball[:200], [[3.0, 4.0, 0.0]], ball[200:], [[-3.0, -4.0, 0.0]]])
    assert consensus_error(cloud) == 10.0  # the two far points; any other pair is at most 5.5 apart
    assert consensus_error(np.full((100, 2), 0.1)) == 0.0
    assert consensus_error(np.zeros((3, 0))) == 0.0


def test_consensus_error_finds_a_diameter_away_from_the_farthest_rows():
    """65 rows evenly on the unit circle (no two opposite: at most 2 cos(pi / 130) = 1.99942 apart) and two opposite
    rows just inside it, 1.9999 apart, whose directions are a quarter spacing off the circle's rows (so they are at
    most 1.99995 - 0.00015 from any): the widest pair is of the two rows nearest the centroid, and the first 64 rows
    already see a gap within 3e-4 of the bound 1 + 0.99995 on the pairs left."""
    step = 2 * np.pi / 65
    circle = np.column_stack([np.cos(step * np.arange(65)), np.sin(step * np.arange(65))])
    p = 0.99995 * np.array([np.cos(step / 4), np.sin(step / 4)])
    thetas = np.vstack([circle[:20], p, circle[20:], -p])
    assert abs(consensus_error(thetas) - 1.9999) < 1e-12
    assert consensus_error(thetas) == brute_force_error(thetas)


def _cloud(kind: str, n: int, m: int, seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    if kind == "normal":
        return g.normal(size=(n, m)) * 10
    if kind == "sphere":  # every row as far from the centroid: nothing can be pruned
        t = g.normal(size=(n, m))
        return t / np.linalg.norm(t, axis=1, keepdims=True)
    if kind == "ties":
        return np.round(g.normal(size=(n, m)) * 2)
    if kind == "near_consensus":
        return 20.0 + g.normal(size=(n, m)) * 1e-13
    if kind == "wide_magnitudes":
        return g.normal(size=(n, m)) * 10.0 ** g.integers(-150, 150, size=(n, m))
    if kind == "tiny":  # squares underflow
        return g.normal(size=(n, m)) * 1e-160
    if kind == "huge":  # squares overflow to inf
        return g.normal(size=(n, m)) * 1e155
    if kind == "one_apart":
        t = np.full((n, m), 3.0)
        t[n // 2, 0] = 3.5
        return t
    if kind == "nan":
        t = g.normal(size=(n, m))
        t[n // 3, m - 1] = np.nan
        return t
    if kind == "inf":
        t = g.normal(size=(n, m))
        t[n // 3, 0] = np.inf
        return t
    raise ValueError(kind)


@pytest.mark.parametrize(
    "kind", ["normal", "sphere", "ties", "near_consensus", "wide_magnitudes", "tiny", "huge", "one_apart", "nan", "inf"]
)
@pytest.mark.parametrize(
    "n,m", [(1, 2), (2, 2), (2, 1), (5, 3), (32, 2), (33, 2), (64, 1), (65, 2), (300, 2), (257, 3), (200, 7), (150, 9)]
)
def test_consensus_error_is_the_brute_force_bit_for_bit(kind, n, m):
    """Huge rows, whose squared gaps overflow (the brute force's inf), are the brute force of the rows scaled by a
    power of two, scaled back: exact scalings, so bit for bit too."""
    thetas = _cloud(kind, n, m, seed=n * 31 + m)
    with np.errstate(over="ignore", invalid="ignore"):
        expected = brute_force_error(thetas)
        if kind == "huge":
            expected = float(np.ldexp(brute_force_error(np.ldexp(thetas, -600)), 600))
        got = consensus_error(thetas)
    assert type(got) is float
    assert got == expected or (math.isnan(got) and math.isnan(expected))


def test_consensus_error_of_team_thetas_is_the_brute_force():
    """Clouds as a team run makes them: a 1000-robot team's thetas after a few consensus steps."""
    team = team_conf(robots=400, graph="random_geometric")
    net = build_network(team, 2, 0)
    mixer, g = Mixer(net, team, 0), np.random.default_rng(5)
    thetas = 20.0 + g.normal(size=(400, 2))
    for l in range(6):
        thetas = mixer.mix(thetas, l) + 0.1 * g.normal(size=(400, 2))
        assert consensus_error(thetas) == brute_force_error(thetas)
