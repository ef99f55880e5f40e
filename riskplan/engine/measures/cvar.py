"""cvar: CVaR_beta of the total reward, the paper's objective (Algorithm 1, eq. 9)."""

from __future__ import annotations

import numpy as np

from riskplan.engine.estimators import as_sample, as_scores, cvar, cvar_gradient, tail_count
from riskplan.engine.measures.base import BETA, Measure, Params, Statistics, normal_tail
from riskplan.engine.measures.spectral import Spectral


class CVaR(Spectral):
    """CVaR_beta, the Rockafellar-Uryasev form at the empirical quantile (`riskplan.engine.estimators.cvar`), and
    its gradient eq. (9). Spectral, with g(u) = min(u / beta, 1)."""

    name = "cvar"
    parameters = (BETA,)
    built_in = True
    scheduled = True

    def objective(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        return cvar(as_sample(z), params.beta)

    def gradient(self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True) -> np.ndarray:
        z = as_sample(z)
        return cvar_gradient(z, as_scores(z, scores), params.beta)

    objective_and_gradient = Measure.objective_and_gradient

    def level(self, params: Params) -> float:
        return params.beta

    def distortion(self, u: np.ndarray, params: Params) -> np.ndarray:
        return np.minimum(np.asarray(u, dtype=float) / params.beta, 1.0)

    def spectrum(self, u: np.ndarray, params: Params) -> np.ndarray:
        beta = params.beta
        return np.where(np.asarray(u, dtype=float) < beta, 1.0 / beta, 0.0)

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        """phi(j/n) = 1/beta for j < ceil(beta n), with `tail_count`'s guard against round-off."""
        k = np.arange(n + 1)
        tail = k[1:-1] < tail_count(params.beta, n)
        return np.diff(self.distortion(k / n, params)), np.where(tail, 1.0 / params.beta, 0.0)

    def training(
        self, z: np.ndarray, scores: np.ndarray, params: Params, level: float | None, stats: Statistics, baseline: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Eq. (9) at the soft-risk level beta_l, with the statistics' VaR when it is this partition's, and the
        statistics' CVaR as the objective when the run reports CVaR at this beta."""
        beta = params.beta
        shared = level == stats.beta and beta == stats.beta
        grads = cvar_gradient(z, scores, level, var=stats.value_at_risk if shared else None, parallel=True)
        return grads, stats.cvar if beta == stats.beta else self.objective(z, params)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float:
        """mu - sigma phi(Phi^-1(beta)) / beta."""
        return mu - sigma * normal_tail(params.beta)

    def reported(self, params: Params, figures: dict, beta: float) -> dict | None:
        return figures["cvar"] if params.beta == beta else None

    def label(self, params: Params, *, short: bool = False, beta: float | None = None) -> str:
        return "risk-averse (CVaR)" if short else f"risk-averse (CVaR β={params.beta:g})"
