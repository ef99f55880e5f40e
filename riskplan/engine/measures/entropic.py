"""entropic: -(1/eta) log E[exp(-eta Z)] (mu - eta sigma^2 / 2 for a normal total reward)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from riskplan.engine import threads
from riskplan.engine.estimators import as_sample, entropic, entropic_gradient
from riskplan.engine.measures.base import Measure, Parameter, Params
from riskplan.engine.rng import count_resample

ETA = Parameter("eta", 0.0, math.inf, symbol="η")  # the aversion per unit of reward


class Entropic(Measure):
    """The entropic risk, and its self-normalised likelihood-ratio gradient (`riskplan.engine.estimators`)."""

    name = "entropic"
    parameters = (ETA,)
    built_in = True

    def objective(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        return entropic(as_sample(z), params.eta)

    def gradient(self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True) -> np.ndarray:
        return entropic_gradient(z, scores, params.eta, baseline=baseline)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float:
        """mu - eta sigma^2 / 2."""
        return mu - params.eta * sigma**2 / 2.0

    def of_distribution(self, values: np.ndarray, probabilities: np.ndarray, params: Params) -> float:
        """-(1/eta) log sum_k p_k exp(-eta z_k), shifted by the smallest z."""
        z, eta = np.asarray(values, dtype=float), params.eta
        low = z.min()
        return float(low - math.log(np.sum(probabilities * np.exp(-eta * (z - low)))) / eta)

    def bootstrap(self, z_sorted: np.ndarray, params: Params, key: np.uint64, out: np.ndarray) -> None:
        threads.over_threads(_bootstrap_entropic, out.shape[0], z_sorted, params.eta, key, out)


@njit(cache=True, nogil=True)
def _bootstrap_entropic(z_sorted, eta, key, out, begin, end):
    """The entropic risk of resamples begin..end-1, -(1/eta) log (sum_k C_k exp(-eta z_k) / n), shifted by the
    smallest z so that no exponential overflows."""
    n = z_sorted.size
    shift = z_sorted[0]
    counts = np.empty(n, dtype=np.int32)  # reused from one resample to the next
    drawn = np.empty(n, dtype=np.uint32)
    for b in range(begin, end):
        count_resample(key, b, counts, drawn)
        total = 0.0
        for i in range(n):
            if counts[i]:
                total += counts[i] * math.exp(-eta * (z_sorted[i] - shift))
        out[b] = shift - math.log(total / n) / eta
