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
        return _phi(normal_quantile(np.asarray(u, dtype=float)), params.eta)

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        """g and 1 - g = Phi(-Phi^-1(u) - eta), each where it is the smaller: the weights keep their relative
        accuracy in both tails."""
        eta = params.eta
        x = normal_quantile(np.arange(n + 1) / n)
        lower, upper = normal_cdf(x + eta), normal_cdf(-x - eta)
        weights = np.where(lower[1:] <= 0.5, np.diff(lower), -np.diff(upper))
        return weights, _phi(x[1:-1], eta)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float:
        """mu - eta sigma."""
        return mu - params.eta * sigma


def _phi(x: np.ndarray, eta: float) -> np.ndarray:
    """phi = exp(-eta x - eta^2 / 2) at x = Phi^-1(u). Where eta^2 overflows (eta > 1.3e154, a shift of that many
    standard deviations), phi is 0 at every finite x, as exp of anything below -745 is (and infinite at x = -inf, as
    its limit u -> 0 is): computed as it is written, it would be an OverflowError, or inf - inf."""
    try:
        with np.errstate(over="ignore"):  # a numpy eta's square is inf, a float's an OverflowError
            half_square = 0.5 * eta**2
    except OverflowError:
        half_square = math.inf
    if half_square == math.inf:
        return np.where(x == -np.inf, np.inf, np.where(np.isnan(x), np.nan, 0.0))
    return np.exp(-eta * x - half_square)
