"""mean_cvar: (1 - lambda) E[Z] + lambda CVaR_beta, a blend of the risk-neutral and the CVaR objective."""

from __future__ import annotations

import numpy as np

from riskplan.engine.estimators import (
    as_sample,
    as_scores,
    cvar,
    cvar_gradient,
    mean_cvar_mix,
    mean_gradient,
    tail_count,
)
from riskplan.engine.measures.base import BETA, Measure, Parameter, Params, Statistics, normal_tail
from riskplan.engine.measures.spectral import Spectral

WEIGHT = Parameter("weight", 0.0, 1.0, low_closed=True, high_closed=True, symbol="λ")


class MeanCVaR(Spectral):
    """(1 - lambda) E[Z] + lambda CVaR_beta; its gradient the same blend of REINFORCE and eq. (9). Spectral, with
    g(u) = (1 - lambda) u + lambda min(u / beta, 1)."""

    name = "mean_cvar"
    title = "mean-CVaR"
    parameters = (WEIGHT, BETA)
    built_in = True
    scheduled = True

    def objective(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        z = as_sample(z)
        return mean_cvar_mix(z.mean(axis=-1), cvar(z, params.beta), params.weight)[()]

    def gradient(self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True) -> np.ndarray:
        z = as_sample(z)
        scores = as_scores(z, scores)
        parts = mean_gradient(z, scores, baseline), cvar_gradient(z, scores, params.beta)
        return mean_cvar_mix(*parts, params.weight)

    objective_and_gradient = Measure.objective_and_gradient

    def level(self, params: Params) -> float:
        return params.beta

    def distortion(self, u: np.ndarray, params: Params) -> np.ndarray:
        u, weight = np.asarray(u, dtype=float), params.weight
        return (1.0 - weight) * u + weight * np.minimum(u / params.beta, 1.0)

    def spectrum(self, u: np.ndarray, params: Params) -> np.ndarray:
        weight, beta = params.weight, params.beta
        return (1.0 - weight) + np.where(np.asarray(u, dtype=float) < beta, weight / beta, 0.0)

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        """phi(j/n) = (1 - lambda) + (lambda / beta) 1{j < ceil(beta n)}, with `tail_count`'s guard."""
        k = np.arange(n + 1)
        weight, beta = params.weight, params.beta
        tail = k[1:-1] < tail_count(beta, n)
        return np.diff(self.distortion(k / n, params)), (1.0 - weight) + np.where(tail, weight / beta, 0.0)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float:
        """(1 - lambda) mu + lambda (mu - sigma phi(Phi^-1(beta)) / beta)."""
        return (1.0 - params.weight) * mu + params.weight * (mu - sigma * normal_tail(params.beta))

    def training(
        self, z: np.ndarray, scores: np.ndarray, params: Params, level: float | None, stats: Statistics, baseline: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """CVaR's part at beta_l as `CVaR.training` takes it, the mean's by REINFORCE; the statistics reused."""
        weight, beta = params.weight, params.beta
        shared = level == stats.beta and beta == stats.beta
        cvar_part = cvar_gradient(z, scores, level, var=stats.value_at_risk if shared else None, parallel=True)
        grads = mean_cvar_mix(mean_gradient(z, scores, baseline, parallel=True), cvar_part, weight)
        if beta == stats.beta:
            return grads, mean_cvar_mix(stats.mean, stats.cvar, weight)
        return grads, self.objective(z, params)
