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
_TINY = float(np.finfo(np.float64).tiny)  # the smallest normal float: a sum below it has lost relative accuracy


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
    smallest z so that no exponential overflows. A resample that misses the smallest z's may find all its weights
    underflowed (eta (z - min z) > 708: eta = 2 and rewards hundreds apart), a sum of 0 and an infinite value: one
    whose sum is below the smallest normal float is summed again, shifted by its own smallest z
    (`_resample_entropic`); the others keep the shared weights' numbers.

    Where eta (max z - min z) < 1, the weights are summed as exp(x) - 1 (expm1) and the logarithm taken by log1p, as
    riskplan.engine.estimators does: log(sum / n) of weights all within 1e-16 of 1 rounds to 0, which put every
    resample at the smallest z for eta below about 1e-16 / (max z - min z). Every such weight is above 1/e, so no sum
    underflows there.

    The exponentials are the sample's, the same for every resample: taken once, not once per draw. A count of 0
    adds 0 * w = +-0.0, which leaves the sum as skipping it did (x + -0.0 is x), so there is no branch, and LANES
    resamples are summed side by side (`lane_sums`): the same numbers as one at a time."""
    n = z_sorted.size
    shift = z_sorted[0]
    near = eta * (z_sorted[n - 1] - shift) < 1.0  # every weight above 1/e: summed less one, for log1p
    weights = np.empty(n)
    for i in range(n):
        weights[i] = math.expm1(-eta * (z_sorted[i] - shift)) if near else math.exp(-eta * (z_sorted[i] - shift))
    lanes = np.zeros((LANES, n), dtype=np.int32)  # reused from one group to the next; an unused lane's sum is dropped
    drawn = np.empty(n, dtype=np.uint32)
    for first in range(begin, end, LANES):
        used = min(LANES, end - first)
        count_lanes(key, first, used, lanes, drawn)
        totals = lane_sums(lanes, weights)
        for lane in range(used):
            if near:
                out[first + lane] = shift - math.log1p(totals[lane] / n) / eta
            elif totals[lane] >= _TINY:
                out[first + lane] = shift - math.log(totals[lane] / n) / eta
            else:  # the resample misses the sample's lowest z's, and its weights underflow (eta dz > 708)
                out[first + lane] = _resample_entropic(z_sorted, lanes[lane], eta)


@njit(cache=True, nogil=True)
def _resample_entropic(z_sorted, counts, eta):
    """The entropic risk of one resample by its counts, shifted by its own smallest z (the first with a count):
    its sum is then >= 1, so the logarithm is finite and accurate however far its z's lie above the sample's."""
    n = z_sorted.size
    first = 0
    while counts[first] == 0:
        first += 1
    shift = z_sorted[first]
    total = 0.0
    for i in range(first, n):
        total += counts[i] * math.exp(-eta * (z_sorted[i] - shift))
    return shift - math.log(total / n) / eta
