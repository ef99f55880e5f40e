"""Softmax policy of eqs. (2)-(3) and its score function d log mu / d theta (errata to eq. 10)."""

from __future__ import annotations

import numpy as np

from riskplan.world import World


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


def tables(world: World, thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-policy cumulative move probabilities (P, C, 5) and scores (P, C, 5, M) for thetas (P, M)."""
    features = move_features(world)
    probs = probabilities(features, thetas)
    cum = np.cumsum(probs, axis=-1)
    cum[..., -1] = 1.0  # guard the last bin against round-off so a uniform draw always lands
    return cum, scores(features, probs)
