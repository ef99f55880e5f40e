"""Risk measures by risk node (paper eqs. 4-9): `objective(z, risk)` and `objective_gradient(z, scores, risk)` for any
registered measure, built in (cvar, neutral, wang, mean_cvar, entropic) or from an installed package.

A risk node names the measure and its parameters: the built-in ones take theirs as the node's own keys
({"measure": "wang", "eta": 0.75}, a RiskConf), a package's as `params` ({"measure": "power", "params":
{"gamma": 0.5}}). Each measure is an object (riskplan.engine.measures); the estimators themselves are plain array
functions in riskplan.engine.estimators, re-exported here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from riskplan.engine.estimators import (
    as_count,
    cvar,
    cvar_gradient,
    entropic,
    entropic_gradient,
    mean_gradient,
    normal_cdf,
    normal_quantile,
    summary_stats,
    tail_count,
    value_at_risk,
)
from riskplan.engine.measures.base import Params
from riskplan.engine.measures.registry import BUILT_IN, MEASURES, RiskSpec, risk_spec
from riskplan.engine.measures.spectral import Spectral

__all__ = [
    "MEASURES",
    "RiskSpec",
    "cvar",
    "cvar_gradient",
    "distortion_at",
    "entropic",
    "entropic_gradient",
    "l_statistic",
    "mean_gradient",
    "normal_cdf",
    "normal_quantile",
    "objective",
    "objective_and_gradient",
    "objective_gradient",
    "risk_spec",
    "spectral_gradient",
    "spectral_weights",
    "spectrum",
    "summary_stats",
    "tail_count",
    "value_at_risk",
]


def objective(z: np.ndarray, risk: Any) -> np.ndarray | float:
    """The risk measure of the sample z (..., W) named by `risk`, along the last axis; a float for 1-D z."""
    measure, params = risk_spec(risk)
    return measure.objective(z, params)


def objective_gradient(z: np.ndarray, scores: np.ndarray, risk: Any, *, baseline: bool = True) -> np.ndarray:
    """Score-function estimate of d objective / d theta: z (..., W), scores (..., W, M) -> (..., M).

    neutral: `mean_gradient`; cvar: `cvar_gradient` (eq. 9); mean_cvar: (1 - lambda) mean_gradient + lambda
    cvar_gradient; a spectral measure (wang, a distortion): `spectral_gradient` with the baseline b = mean of h;
    entropic: `entropic_gradient`. `baseline=False` drops the (zero-mean) baseline where there is one.
    """
    measure, params = risk_spec(risk)
    return measure.gradient(z, scores, params, baseline=baseline)


def objective_and_gradient(
    z: np.ndarray, scores: np.ndarray, risk: Any, *, baseline: bool = True
) -> tuple[np.ndarray | float, np.ndarray]:
    """(`objective`, `objective_gradient`) of the same sample, the same numbers as the two calls; a spectral
    measure's (wang) sorts each row once for both."""
    measure, params = risk_spec(risk)
    return measure.objective_and_gradient(z, scores, params, baseline=baseline)


def distortion_at(u: np.ndarray, risk: Any) -> np.ndarray:
    """g(u) of a spectral measure, for u in [0, 1] (wang: Phi(Phi^-1(u) + eta))."""
    measure, params = _spectral(risk)
    return measure.distortion(u, params)


def spectrum(u: np.ndarray, risk: Any) -> np.ndarray:
    """phi(u) = g'(u), the weight of the u-quantile (wang: exp(-eta Phi^-1(u) - eta^2 / 2)); right-continuous."""
    measure, params = _spectral(risk)
    return measure.spectrum(u, params)


def spectral_weights(n: int, risk: Any) -> np.ndarray:
    """L-statistic weights g(k/n) - g((k-1)/n), k = 1..n, of a spectral measure (read-only, cached per n and risk)."""
    measure, params = _spectral(risk)
    return measure.tables(params, as_count(n))[0]


def l_statistic(z: np.ndarray, risk: Any) -> np.ndarray | float:
    """sum_k z_(k) [g(k/W) - g((k-1)/W)] along the last axis: the plug-in spectral measure (cvar's equals `cvar`)."""
    measure, params = _spectral(risk)
    return measure.l_statistic(z, params)


def spectral_gradient(z: np.ndarray, scores: np.ndarray, risk: Any, *, baseline: bool = True) -> np.ndarray:
    """(1/W) sum_i S_i (h(z_i) - b), h(z_(k)) = -sum_{j=k}^{W-1} phi(j/W) (z_(j+1) - z_(j)); b = mean(h) or 0.

    The plug-in of grad rho = E[S h(Z)], h(z) = -int_z^max phi(F(t)) dt, with the step CDF F(t) = j/W on
    [z_(j), z_(j+1)). E[S] = 0, so the baseline b = mean(h) (variance reduction) keeps it unbiased. With cvar's
    spectrum (phi = 1/beta for j < ceil(beta W), else 0) and b = 0 this is eq. (9) up to round-off.
    """
    measure, params = _spectral(risk)
    return measure.spectral_gradient(z, scores, params, baseline=baseline)


def _spectral(risk: Any) -> tuple[Spectral, Params]:
    """The measure and parameters of a spectral risk node (one with a distortion); entropic has none."""
    measure, params = risk_spec(risk)
    if not isinstance(measure, Spectral):
        spectral = ", ".join(name for name, m in BUILT_IN.items() if isinstance(m, Spectral))
        raise ValueError(
            f"risk measure {measure.name!r} is not spectral; spectral measures: {spectral} and any "
            f"riskplan.risk.distortion"
        )
    return measure, params
