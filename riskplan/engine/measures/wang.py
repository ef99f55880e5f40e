"""wang: Wang's distortion g(u) = Phi(Phi^-1(u) + eta) of the lower tail (mu - eta sigma for a normal reward)."""

from __future__ import annotations

import math

import numpy as np

from riskplan.engine.estimators import normal_cdf, normal_quantile
from riskplan.engine.measures.base import Parameter, Params
from riskplan.engine.measures.spectral import Spectral

ETA = Parameter("eta", 0.0, math.inf, symbol="η")  # the distortion's shift, in standard deviations


class Wang(Spectral):
    """Wang's transform, estimated by the L-statistic and its influence-function gradient (`Spectral`)."""

    name = "wang"
    title = "Wang"
    parameters = (ETA,)
    built_in = True

    def distortion(self, u: np.ndarray, params: Params) -> np.ndarray:
        return normal_cdf(normal_quantile(np.asarray(u, dtype=float)) + params.eta)

    def spectrum(self, u: np.ndarray, params: Params) -> np.ndarray:
        eta = params.eta
        return np.exp(-eta * normal_quantile(np.asarray(u, dtype=float)) - 0.5 * eta**2)

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        """g and 1 - g = Phi(-Phi^-1(u) - eta), each where it is the smaller: the weights keep their relative
        accuracy in both tails."""
        eta = params.eta
        x = normal_quantile(np.arange(n + 1) / n)
        lower, upper = normal_cdf(x + eta), normal_cdf(-x - eta)
        weights = np.where(lower[1:] <= 0.5, np.diff(lower), -np.diff(upper))
        return weights, np.exp(-eta * x[1:-1] - 0.5 * eta**2)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float:
        """mu - eta sigma."""
        return mu - params.eta * sigma
