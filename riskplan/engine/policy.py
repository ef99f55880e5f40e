"""Softmax policy of eqs. (2)-(3) and its score function d log mu / d theta (errata to eq. 10).

`probabilities` and `scores` state the maths in numpy; `tables` builds the same quantities for the rollout kernel
in one numba pass, for every policy of a batch.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from riskplan.engine.world import World


def move_features(world: World, signals: np.ndarray | None = None) -> np.ndarray:
    """Features s^j(x + u) of every (cell, move), shape (C, 5, M); a blocked move sees its own cell."""
    signals = world.signals() if signals is None else signals
    return signals[world.next_cell]


def probabilities(features: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """mu_theta(u | x) for every cell, shape (..., C, 5) for theta (..., M); stable for any finite theta."""
    logits = np.einsum("cam,...m->...ca", features, np.asarray(theta, dtype=float))
    logits = logits - logits.max(axis=-1, keepdims=True)  # max-shift: no overflow for large theta
    weights = np.exp(logits)
    return weights / weights.sum(axis=-1, keepdims=True)


def scores(features: np.ndarray, probs: np.ndarray) -> np.ndarray:
    """d log mu(u|x) / d theta_j = s^j(x+u) - sum_v mu(v|x) s^j(x+v), shape (..., C, 5, M)."""
    expected = np.einsum("...ca,cam->...cm", probs, features)
    return features - expected[..., None, :]


PARALLEL_POLICIES = 16  # from this many policies on, `tables` fills them in parallel (below: no parallel region)
CHUNK = 8  # policies per parallel work item


def tables(world: World, thetas: np.ndarray, features: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-policy cumulative move probabilities (P, C, 5) and scores (P, C, 5, M) for thetas (P, M).

    `features` is move_features(world) when the caller keeps it (riskplan.engine.rollout.Kernel does: computing it is
    most of a small batch's fixed cost).
    """
    features = move_features(world) if features is None else features
    cum = np.empty(thetas.shape[:1] + features.shape[:2])
    score = np.empty(thetas.shape[:1] + features.shape)
    thetas = np.ascontiguousarray(thetas, dtype=np.float64)
    if len(thetas) >= PARALLEL_POLICIES:
        _fill_tables_parallel(features, thetas, cum, score)
    else:
        _fill_tables(features, thetas, cum, score, 0, len(thetas))
    return cum, score


@njit(parallel=True, cache=True)
def _fill_tables_parallel(features, thetas, cum, score):
    """`_fill_tables` of all policies, CHUNK at a time in parallel: each policy's numbers are one thread's, the
    same whatever the thread count."""
    chunks = (thetas.shape[0] + CHUNK - 1) // CHUNK
    for chunk in prange(chunks):
        _fill_tables(features, thetas, cum, score, chunk * CHUNK, min(thetas.shape[0], (chunk + 1) * CHUNK))


@njit(cache=True)
def _fill_tables(features, thetas, cum, score, first, last):
    """`probabilities` (cumulated) and `scores` for policies first..last-1 and every cell, in one pass.

    The same maths as the numpy functions above, as loops: every iteration of a 100-robot team builds 100 tables,
    and this is ~6x faster than the numpy composition (tests/test_policy.py checks they agree).
    """
    mu = np.empty(5)
    for p in range(first, last):
        for c in range(features.shape[0]):
            best = -np.inf
            for a in range(5):
                mu[a] = 0.0
                for j in range(thetas.shape[1]):
                    mu[a] += thetas[p, j] * features[c, a, j]
                best = max(best, mu[a])
            total = 0.0
            for a in range(5):
                mu[a] = math.exp(mu[a] - best)  # max-shift: no overflow for large theta
                total += mu[a]
            running = 0.0
            for a in range(5):
                mu[a] /= total
                running += mu[a]
                cum[p, c, a] = running
            cum[p, c, 4] = 1.0  # guard the last bin against round-off so a uniform draw always lands
            for j in range(thetas.shape[1]):
                expected = 0.0
                for a in range(5):
                    expected += mu[a] * features[c, a, j]
                for a in range(5):
                    score[p, c, a, j] = features[c, a, j] - expected
