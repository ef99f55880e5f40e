"""Spectral (distortion) risk measures, and `distortion(name, G, **ranges)`: a spectral measure from its distortion
function alone.

A spectral measure is rho = int z dg(F(z)) = int_0^1 phi(u) F^-1(u) du, with an increasing distortion g on [0, 1],
g(0) = 0, g(1) = 1, and its spectrum phi = g'. Low z is the bad tail: a concave g weighs it up (risk-averse).
Its plug-in estimate is the L-statistic sum_k z_(k) [g(k/W) - g((k-1)/W)] over the ascending sort, and its
gradient the L-statistic's influence function in the likelihood-ratio form:

    grad rho = E[S (h(Z) - b)],  h(z) = -int_z^max phi(F(t)) dt,

with the empirical F, so h(z_(k)) = -sum_{j=k}^{W-1} phi(j/W) (z_(j+1) - z_(j)), and the baseline b = mean(h)
(E[S] = 0 keeps it unbiased). With CVaR's spectrum and b = 0 this is eq. (9).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from numba import njit

from riskplan.engine import threads
from riskplan.engine.estimators import (
    as_count,
    as_sample,
    as_scores,
    kernel_input,
    l_statistics,
    normal_cdf,
    spectral_estimates,
)
from riskplan.engine.measures.base import Measure, Parameter, Params
from riskplan.engine.rng import count_resample
from riskplan.util.errors import BadInput

NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")  # a measure's name, as `risk.measure=NAME` takes it
STEP = 2.0**-20  # the central difference that gives a distortion's spectrum phi = G' from G alone
TOLERANCE = 1e-9  # of G(0) = 0, G(1) = 1 and of G's increase, for round-off in a user's G
PROBE = np.linspace(0.0, 1.0, 1025)  # where a distortion is checked when its parameters are


class Spectral(Measure):
    """A spectral measure: give `distortion` (g) and `spectrum` (phi = g'); the estimates follow (the L-statistic
    and its influence-function gradient, one sort of each row for both)."""

    def distortion(self, u: np.ndarray, params: Params) -> np.ndarray:
        """g(u) for u in [0, 1]."""
        raise NotImplementedError

    def spectrum(self, u: np.ndarray, params: Params) -> np.ndarray:
        """phi(u) = g'(u), the weight of the u-quantile (right-continuous where g has a kink)."""
        raise NotImplementedError

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(the L-statistic weights g(k/n) - g((k-1)/n), k = 1..n; phi(j/n), j = 1..n-1)."""
        k = np.arange(n + 1)
        return np.diff(self.distortion(k / n, params)), self.spectrum(k[1:-1] / n, params)

    def tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        """`make_tables`, read-only and kept for the last few (params, n)."""
        return _tables(self, Params(params), as_count(n))

    def l_statistic(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        """sum_k z_(k) [g(k/W) - g((k-1)/W)] along the last axis: the plug-in estimate (CVaR's equals `cvar`)."""
        z = as_sample(z)
        return l_statistics(z, self.tables(params, z.shape[-1])[0])

    def spectral_estimates(
        self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True
    ) -> tuple[np.ndarray | float, np.ndarray]:
        """(`l_statistic`, `spectral_gradient`) from one sort of each row."""
        z = as_sample(z)
        scores = as_scores(z, scores)
        weights, phi = self.tables(params, z.shape[-1])
        return spectral_estimates(z, scores, weights, phi, baseline)

    def spectral_gradient(
        self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True
    ) -> np.ndarray:
        """(1/W) sum_i S_i (h(z_i) - b), b = mean(h) or 0: the influence-function gradient (module docstring)."""
        return self.spectral_estimates(z, scores, params, baseline=baseline)[1]

    def objective(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        return self.l_statistic(z, params)

    def gradient(self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True) -> np.ndarray:
        return self.spectral_gradient(z, scores, params, baseline=baseline)

    def objective_and_gradient(
        self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True
    ) -> tuple[np.ndarray | float, np.ndarray]:
        return self.spectral_estimates(z, scores, params, baseline=baseline)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float | None:
        """mu + sigma E_g[X], X standard normal, by the quantile identity rho = int_0^1 F^-1(u) dg(u) integrated by
        parts: E_g[X] = int_0^inf (1 - g(Phi(x))) dx - int_-inf^0 g(Phi(x)) dx (trapezoids of 1/1000 to |x| = 40)."""
        x = np.linspace(0.0, 40.0, 40_001)
        above = 1.0 - self.distortion(normal_cdf(x), params)
        below = self.distortion(normal_cdf(-x), params)
        total = above.sum() - below.sum() - 0.5 * (above[0] + above[-1]) + 0.5 * (below[0] + below[-1])
        return mu + sigma * float(total * (x[1] - x[0]))

    def of_distribution(self, values: np.ndarray, probabilities: np.ndarray, params: Params) -> float | None:
        """sum_k z_k [g(P_k) - g(P_(k-1))], P the cumulative probabilities."""
        cumulative = np.concatenate([[0.0], np.cumsum(probabilities)[:-1], [1.0]])
        return float(np.asarray(values, dtype=float) @ np.diff(self.distortion(cumulative, params)))

    def bootstrap(self, z_sorted: np.ndarray, params: Params, key: np.uint64, out: np.ndarray) -> None:
        """Each resample's sum_k z_(k) [g(C_k / n) - g(C_(k-1) / n)] over its cumulative counts C."""
        self.bootstrap_rows(z_sorted[None], [params], key, out[None])

    def bootstrap_rows(self, z_rows: np.ndarray, params_rows: list[Params], key: np.uint64, out: np.ndarray) -> None:
        """`bootstrap` of each row, every resample's counts drawn once for all rows."""
        n = z_rows.shape[1]
        tables = np.stack([self.distortion(np.arange(n + 1) / n, params) for params in params_rows])
        ends = np.array([_flat_from(table) for table in tables], dtype=np.int64)
        threads.over_threads(
            _bootstrap_distorted, out.shape[1], kernel_input(z_rows), kernel_input(tables), ends, key, out
        )


def _flat_from(table: np.ndarray) -> int:
    """The first c from which table[c:] is constant (CVaR_beta's g(c / n) from c = beta n on): from there on every
    term of the L-statistic is z * 0.0."""
    changes = np.flatnonzero(table != table[-1])
    return int(changes[-1]) + 1 if changes.size else 0


@functools.lru_cache(maxsize=64)
def _tables(measure: Spectral, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A spectral measure's tables for W = n, read-only."""
    weights, phi = measure.make_tables(params, n)
    weights.flags.writeable = False
    phi.flags.writeable = False
    return weights, phi


@njit(cache=True, nogil=True)
def _bootstrap_distorted(z_sorted, tables, ends, key, out, begin, end):
    """A distortion risk measure of each row of resamples begin..end-1: out[r, b] = sum_k z_(k) [table[C_k] -
    table[C_{k-1}]] of row r, table[c] = g_r(c / n); the rows share resample b's counts (`count_resample`, into
    arrays reused from one resample to the next).

    Without a branch on a count of 0 (a third of them, at random): its term is z * 0.0, and adding a zero leaves
    the sum as it was, so the numbers are those of skipping it (z is finite), 3.5 times quicker. For the same reason
    a row's sum stops once C_k reaches ends[r], where its table turns flat (CVaR_beta: a beta-th of the terms)."""
    n = z_sorted.shape[1]
    counts = np.empty(n, dtype=np.int32)
    drawn = np.empty(n, dtype=np.uint32)
    for b in range(begin, end):
        count_resample(key, b, counts, drawn)
        for r in range(z_sorted.shape[0]):
            total, cumulative, flat = 0.0, 0, ends[r]
            for i in range(n):
                if cumulative >= flat:
                    break
                count = counts[i]
                total += z_sorted[r, i] * (tables[r, cumulative + count] - tables[r, cumulative])
                cumulative += count
            out[r, b] = total


class Distortion(Spectral):
    """The spectral measure of a distortion function G(u, **params) (`distortion`): g = G, and phi = G' by a
    central difference of G (one-sided at 0 and 1)."""

    def __init__(self, name: str, function: Callable[..., Any], parameters: tuple[Parameter, ...]):
        self.name = name
        self.function = function
        self.parameters = parameters
        self._fine: set[Params] = set()  # the parameter values whose G passed the check

    def distortion(self, u: np.ndarray, params: Params) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        return np.array(np.broadcast_to(np.asarray(self.function(u, **params), dtype=float), u.shape))

    def spectrum(self, u: np.ndarray, params: Params) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        low, high = np.maximum(u - STEP, 0.0), np.minimum(u + STEP, 1.0)
        return (self.distortion(high, params) - self.distortion(low, params)) / (high - low)

    def make_tables(self, params: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
        k = np.arange(n + 1)
        g = self.distortion(k / n, params)
        self._require(g, params, "risk")
        return np.diff(g), self.spectrum(k[1:-1] / n, params)

    def check(self, params: Mapping[str, Any], where: str = "risk") -> Params:
        """The parameter values checked, and G with them: G(0) = 0, G(1) = 1, increasing and finite on [0, 1]."""
        values = super().check(params, where)
        if values not in self._fine:
            try:
                g = self.distortion(PROBE, values)
            except Exception as err:  # a user's G: whatever it raises is the measure's problem, said in one line
                raise BadInput(f"{where}.params", f"{self._call(values)} raised {type(err).__name__}: {err}") from None
            self._require(g, values, where)
            self._fine.add(values)
        return values

    def _require(self, g: np.ndarray, params: Params, where: str) -> None:
        """BadInput unless g, G on an ascending grid from 0 to 1, is a distortion's."""
        problem = None
        if not np.all(np.isfinite(g)):
            problem = "values that are not finite"
        elif abs(g[0]) > TOLERANCE or abs(g[-1] - 1.0) > TOLERANCE:
            problem = f"G(0) = {g[0]:g} and G(1) = {g[-1]:g}"
        elif np.any(np.diff(g) < -TOLERANCE):
            problem = "a G that decreases"
        if problem:
            raise BadInput(
                f"{where}.params",
                f"{self._call(params)} gives {problem}; a distortion needs G(0) = 0, G(1) = 1 and G increasing on [0, 1]",
            )

    def _call(self, params: Params) -> str:
        """How G was called, for a message: "power's G(u, gamma=0.5)"."""
        return f"{self.name}'s G(u{''.join(f', {k}={v:g}' for k, v in params.items())})"


def distortion(name: str, G: Callable[..., Any], **ranges: tuple[float, float]) -> Distortion:
    """A spectral risk measure from its distortion function alone.

    The objective is rho = int z dG(F(z)): low z is the bad tail, and a concave G is risk-averse. It is estimated by
    sum_i z_(i) [G(i/W) - G((i-1)/W)] over the ascending sort of the W samples, and its policy gradient by the
    L-statistic's influence function in the likelihood-ratio form (as for `wang`), with G' from G by central
    differences.

    Args:
        name: what `risk.measure=NAME` selects: letters, digits and underscores.
        G: `G(u, **params)`, vectorised over the array u in [0, 1], increasing, with G(0) = 0 and G(1) = 1.
        **ranges: one `(low, high)` per float parameter of G: the open bounds of its valid values.

    Returns:
        The measure: name it in an entry point of the group `riskplan.risk_measures`, or pass it as a risk node's
        measure (`{"measure": power, "params": {"gamma": 0.5}}`).

    Example:
        `power = distortion("power", lambda u, gamma: u**gamma, gamma=(0, 1))`
    """
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ValueError(f"a measure's name is letters, digits and underscores (risk.measure=NAME), got {name!r}")
    if not callable(G):
        raise TypeError(f"G must be a function G(u, **params), got {G!r}")
    parameters = []
    for key, bounds in ranges.items():
        try:
            low, high = (float(b) for b in bounds)
        except (TypeError, ValueError):
            raise TypeError(f"the range of {key} is (low, high), the open bounds of a float; got {bounds!r}") from None
        if not low < high:
            raise ValueError(f"the range of {key} is (low, high) with low < high; got {bounds!r}")
        parameters.append(Parameter(key, low, high))
    return Distortion(name, G, tuple(parameters))
