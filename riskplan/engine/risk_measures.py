"""Risk measures and policy-gradient estimators (paper eqs. 5-9, Algorithm 1).

CVaR is the Rockafellar-Uryasev form at the empirical quantile (design.md):
    cvar = v + (1 / (beta W)) * sum_i (z_i - v) 1{z_i <= v},   v = z_(m), m = ceil(beta W)
which equals the mean of the m lowest samples when beta W is whole and there are no ties (eq. 6), and whose
score-function gradient is eq. (9).
"""

from __future__ import annotations

import math

import numpy as np


def tail_count(beta: float, n: int) -> int:
    """m = ceil(beta * n), guarded against float error (0.07 * 100 gives 7, not 8)."""
    if not 0.0 < beta <= 1.0:
        raise ValueError(f"beta must be in (0, 1], got {beta}")
    if n < 1:
        raise ValueError("need at least one sample")
    product = beta * n
    nearest = round(product)
    m = nearest if abs(product - nearest) <= 1e-9 * max(1.0, product) else math.ceil(product)
    return int(min(max(m, 1), n))


def value_at_risk(z: np.ndarray, beta: float) -> np.ndarray | float:
    """beta-VaR (eq. 5/8): the ceil(beta W)-th smallest sample, along the last axis."""
    z = np.asarray(z, dtype=float)
    m = tail_count(beta, z.shape[-1])
    return np.partition(z, m - 1, axis=-1)[..., m - 1][()]  # [()] gives a scalar for 1-D input


def cvar(z: np.ndarray, beta: float) -> np.ndarray | float:
    """beta-CVaR, Rockafellar-Uryasev form at the empirical quantile (last axis); cvar(z, 1) == mean(z)."""
    z = np.asarray(z, dtype=float)
    v = value_at_risk(z, beta)
    return v + _tail_weights(z, v).sum(axis=-1) / (beta * z.shape[-1])


def cvar_gradient(z: np.ndarray, scores: np.ndarray, beta: float, var=None) -> np.ndarray:
    """Eq. (9): (1 / (beta W)) sum_i score_i (z_i - v) 1{z_i <= v}; z (..., W), scores (..., W, M) -> (..., M).

    `var`: value_at_risk(z, beta) when the caller has it already (it costs a partition of z).
    """
    z = np.asarray(z, dtype=float)
    weights = _tail_weights(z, value_at_risk(z, beta) if var is None else var)
    return np.einsum("...w,...wm->...m", weights, np.asarray(scores, dtype=float)) / (beta * z.shape[-1])


def mean_gradient(z: np.ndarray, scores: np.ndarray, baseline: bool = True) -> np.ndarray:
    """REINFORCE estimate of grad E[Z] (eq. 4): mean of score_i (z_i - b), b = mean(z) by default, else 0."""
    z = np.asarray(z, dtype=float)
    centred = z - z.mean(axis=-1, keepdims=True) if baseline else z
    return np.einsum("...w,...wm->...m", centred, np.asarray(scores, dtype=float)) / z.shape[-1]


def summary_stats(z: np.ndarray, beta: float) -> dict[str, np.ndarray | float]:
    """mean, cvar, value_at_risk at beta and std along the last axis, with one partition."""
    z = np.asarray(z, dtype=float)
    v = value_at_risk(z, beta)
    return {
        "mean": z.mean(axis=-1),
        "cvar": v + _tail_weights(z, v).sum(axis=-1) / (beta * z.shape[-1]),
        "value_at_risk": v,
        "std": z.std(axis=-1),
    }


def _tail_weights(z: np.ndarray, v: np.ndarray | float) -> np.ndarray:
    """(z_i - v) 1{z_i <= v}, broadcasting v over the last axis."""
    return np.minimum(z - np.expand_dims(v, -1), 0.0)
