"""neutral: the mean of the total reward, by REINFORCE (eq. 4)."""

from __future__ import annotations

import numpy as np

from riskplan.engine.estimators import as_sample, as_scores, mean, mean_gradient
from riskplan.engine.measures.base import Measure, Params, Statistics
from riskplan.engine.measures.spectral import Spectral


class Neutral(Spectral):
    """E[Z], and REINFORCE with the batch mean as its baseline (`train.baseline`). Spectral, with g(u) = u: CVaR_1."""

    name = "neutral"
    title = "risk-neutral"
    built_in = True

    def objective(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        return mean(z)

    def gradient(self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True) -> np.ndarray:
        z = as_sample(z)
        return mean_gradient(z, as_scores(z, scores), baseline)

    objective_and_gradient = Measure.objective_and_gradient

    def level(self, params: Params) -> float:
        return 1.0  # the mean gradient is CVaR_1's

    def distortion(self, u: np.ndarray, params: Params) -> np.ndarray:
        return np.asarray(u, dtype=float).copy()

    def spectrum(self, u: np.ndarray, params: Params) -> np.ndarray:
        return np.ones_like(np.asarray(u, dtype=float))

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        return np.diff(self.distortion(np.arange(n + 1) / n, params)), np.ones(n - 1)

    def training(
        self, z: np.ndarray, scores: np.ndarray, params: Params, level: float | None, stats: Statistics, baseline: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        return mean_gradient(z, scores, baseline, parallel=True), stats.mean

    def of_normal(self, mu: float, sigma: float, params: Params) -> float:
        return mu

    def reported(self, params: Params, figures: dict, beta: float) -> dict | None:
        return figures["mean"]
