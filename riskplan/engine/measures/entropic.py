"""entropic: -(1/eta) log E[exp(-eta Z)] (mu - eta sigma^2 / 2 for a normal total reward)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from riskplan.engine import threads
from riskplan.engine.estimators import as_sample, entropic, entropic_gradient
from riskplan.engine.measures.base import Measure, Parameter, Params
from riskplan.engine.rng import LANES, count_lanes, lane_sums

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
    smallest z so that no exponential overflows.

    The exponentials are the sample's, the same for every resample: taken once, not once per draw. A count of 0
    adds 0 * w = +0.0 (w is in [0, 1], the sum starts at +0.0), which leaves the sum as skipping it did, so there
    is no branch, and LANES resamples are summed side by side (`lane_sums`): the same numbers as one at a time."""
    n = z_sorted.size
    shift = z_sorted[0]
    weights = np.empty(n)
    for i in range(n):
        weights[i] = math.exp(-eta * (z_sorted[i] - shift))
    lanes = np.zeros((LANES, n), dtype=np.int32)  # reused from one group to the next; an unused lane's sum is dropped
    drawn = np.empty(n, dtype=np.uint32)
    for first in range(begin, end, LANES):
        used = min(LANES, end - first)
        count_lanes(key, first, used, lanes, drawn)
        totals = lane_sums(lanes, weights)
        for lane in range(used):
            out[first + lane] = shift - math.log(totals[lane] / n) / eta
