"""What a risk measure is: a name, float parameters with their valid ranges, an objective of the total reward Z and
its policy gradient (the likelihood-ratio form), and what the training loop, the summary and the report ask of it.

A measure is one object (`Measure`). Its methods take the parameter values that `Measure.check` returned (a
`Params`); the risk nodes of a config, {"measure": "wang", "eta": 0.75} or {"measure": "power", "params": {...}},
are resolved to a measure and its checked values by `riskplan.engine.measures.registry.risk_spec`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from riskplan.engine.estimators import normal_quantile
from riskplan.engine.rng import resample_counts
from riskplan.util.errors import BadInput


@dataclass(frozen=True)
class Parameter:
    """One float parameter of a measure and its valid values: low < value < high, a bound itself valid where it is
    closed; the value is always finite."""

    name: str
    low: float = -math.inf
    high: float = math.inf
    low_closed: bool = False
    high_closed: bool = False
    symbol: str = ""  # how a label writes it ("η"); the name when empty

    def valid(self, value: float) -> bool:
        """Whether value lies in the range."""
        above = value >= self.low if self.low_closed else value > self.low
        below = value <= self.high if self.high_closed else value < self.high
        return above and below and math.isfinite(value)

    def describe(self) -> str:
        """The valid values in words: '0 < beta <= 1', 'a finite eta > 0'."""
        low = f"{self.low:g} {'<=' if self.low_closed else '<'} " if math.isfinite(self.low) else ""
        high = f" {'<=' if self.high_closed else '<'} {self.high:g}" if math.isfinite(self.high) else ""
        if low and high:
            return f"{low}{self.name}{high}"
        if low:
            return f"a finite {self.name} {'>=' if self.low_closed else '>'} {self.low:g}"
        if high:
            return f"a finite {self.name}{high}"
        return f"a finite {self.name}"

    def check(self, value: Any, key: str) -> float:
        """value as a float in the range, or BadInput naming the key, the value and the range."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise BadInput(key, f"got {value!r}; expected a number: {self.describe()}")
        try:
            number = float(value)
        except OverflowError:  # an integer with hundreds of digits
            number = math.inf
        if not self.valid(number):
            raise BadInput(key, f"got {number:g}; expected {self.describe()}")
        return number


class Params(Mapping):
    """A measure's checked parameter values by name (params.beta, as a mapping too), in the order the measure lists
    them: read-only and hashable (a spectral measure keeps its tables per Params)."""

    __slots__ = ("_hash", "_values")

    def __init__(self, values: Mapping[str, float] | None = None):
        self._values = dict(values or {})
        self._hash = hash(tuple(self._values.items()))

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __getattr__(self, name: str) -> float:
        """A value by attribute: params.beta."""
        if name.startswith("_"):  # not a parameter (and never _values itself, before it is set)
            raise AttributeError(name)
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(f"no parameter {name!r} among {list(self._values)}") from None

    def __reduce__(self) -> tuple:
        return Params, (self._values,)

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Mapping) and self._values == dict(other)

    def __repr__(self) -> str:
        return f"Params({self._values!r})"


class Statistics(NamedTuple):
    """The iteration's statistics of the robots that share a risk node, taken at the run's reporting level `beta`
    (`riskplan.engine.estimators.summary_stats`): what a measure's training step may reuse."""

    beta: float
    mean: np.ndarray
    cvar: np.ndarray
    value_at_risk: np.ndarray


# the CVaR level, a parameter of cvar and mean_cvar (and the level every run reports CVaR at)
BETA = Parameter("beta", 0.0, 1.0, high_closed=True, symbol="β")


def normal_tail(beta: float) -> float:
    """phi(Phi^-1(beta)) / beta: how many standard deviations CVaR_beta of a normal lies below its mean."""
    x = float(normal_quantile(beta))
    return math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi) / beta


def field(risk: Any, key: str) -> Any:
    """risk[key] of a mapping (a dict, an OmegaConf node) or risk.key of an object (a RiskConf); None when absent."""
    if isinstance(risk, Mapping):
        return risk.get(key)
    return getattr(risk, key, None)


class Measure:
    """A risk measure of the total reward Z: higher is better, and low z is the bad tail.

    A spectral measure needs only its distortion function (`riskplan.risk.distortion`). For any other, subclass
    this: set `name` and `parameters`, and give `objective` and `gradient`; the rest has defaults that follow from
    those two. An installed package adds its measure to riskplan through the entry-point group
    `riskplan.risk_measures` (docs: "Extending riskplan").

    Attributes:
        name: what `risk.measure=NAME` selects, and summary.json's `objective.measure`.
        title: how labels name it (the name when empty).
        parameters: its float parameters and their valid ranges, set by `risk.params.KEY=VALUE`.
        built_in: the parameters are the risk node's own keys (`risk.beta`, `risk.eta`, `risk.weight`).
        scheduled: soft risk (`risk.schedule`) moves its CVaR level, which is `risk.beta`.
    """

    name: str = ""
    title: str = ""
    parameters: tuple[Parameter, ...] = ()
    built_in: bool = False
    scheduled: bool = False

    def __repr__(self) -> str:
        return f"<risk measure {self.name!r}>"

    # --- parameters ---------------------------------------------------------------------------------------------

    def key(self, parameter: str, where: str = "risk") -> str:
        """The config key of a parameter: risk.eta for a built-in measure, risk.params.gamma for one from a package."""
        return f"{where}.{parameter}" if self.built_in else f"{where}.params.{parameter}"

    def check(self, params: Mapping[str, Any], where: str = "risk") -> Params:
        """The parameter values checked: each one given, a number, and in its range; BadInput naming the first key
        that is not, or that the measure does not have."""
        known = [p.name for p in self.parameters]
        for name in params:
            if name not in known:
                valid = ", ".join(known) if known else "none"
                raise BadInput(
                    self.key(str(name), where), f"unknown parameter of measure {self.name!r}; its parameters: {valid}"
                )
        values = {}
        for p in self.parameters:
            value = params.get(p.name)
            if value is None:
                raise BadInput(self.key(p.name, where), f"missing; measure {self.name!r} needs {p.describe()}")
            values[p.name] = p.check(value, self.key(p.name, where))
        return Params(values)

    def params_of(self, risk: Any, where: str = "risk") -> Params:
        """The checked parameter values of a risk node: its own keys for a built-in measure, its `params` for one
        from a package."""
        given = field(risk, "params") or {}
        if not isinstance(given, Mapping):
            raise BadInput(f"{where}.params", f"got {given!r}; expected a mapping of parameter names to numbers")
        if not self.built_in:
            return self.check(given, where)
        if given:
            own = ", ".join(self.key(p.name, where) for p in self.parameters) or "no parameters"
            raise BadInput(
                f"{where}.params.{next(iter(given))}",
                f"the built-in measure {self.name!r} takes {own}; {where}.params is for measures from packages",
            )
        return self.check({p.name: v for p in self.parameters if (v := field(risk, p.name)) is not None}, where)

    # --- the measure --------------------------------------------------------------------------------------------

    def objective(self, z: np.ndarray, params: Params) -> np.ndarray | float:
        """The plug-in estimate of the measure of the sample z (..., W), along the last axis; a float for 1-D z."""
        raise NotImplementedError

    def gradient(self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True) -> np.ndarray:
        """Score-function (likelihood-ratio) estimate of d objective / d theta: z (..., W), scores (..., W, M) ->
        (..., M). `baseline=False` drops a zero-mean baseline where the estimator has one."""
        raise NotImplementedError

    def objective_and_gradient(
        self, z: np.ndarray, scores: np.ndarray, params: Params, *, baseline: bool = True
    ) -> tuple[np.ndarray | float, np.ndarray]:
        """(`objective`, `gradient`) of the same sample: the same numbers as the two calls."""
        return self.objective(z, params), self.gradient(z, scores, params, baseline=baseline)

    def level(self, params: Params) -> float | None:
        """The CVaR level of its gradient (the metrics' beta_l): 1 for the mean, None (NaN) for a measure without one."""
        return None

    def training(
        self, z: np.ndarray, scores: np.ndarray, params: Params, level: float | None, stats: Statistics, baseline: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """(gradients, objective values) of the robots of one training iteration, z (R, W), scores (R, W, M): the
        gradient at CVaR level `level` (beta_l) where the measure has one. A measure may reuse the iteration's
        statistics `stats` (its VaR, mean and CVaR at the reporting level); the numbers are those of
        `objective_and_gradient`."""
        values, grads = self.objective_and_gradient(z, scores, params, baseline=baseline)
        return grads, values

    def reported(self, params: Params, figures: dict, beta: float) -> dict | None:
        """The summary's figure of this measure when it is one of the run's `figures` (mean, cvar at the reporting
        level beta, with intervals), else None: it is then estimated from the same bootstrap resamples."""
        return None

    def bootstrap(self, z_sorted: np.ndarray, params: Params, key: np.uint64, out: np.ndarray) -> None:
        """out[b] = the measure of bootstrap resample b of the sorted sample (`riskplan.engine.rng.resample_counts`
        of `key`). This default evaluates `objective` on each resample; the built-in measures have kernels."""
        for b in range(out.size):
            out[b] = self.objective(np.repeat(z_sorted, resample_counts(key, b, z_sorted.size)), params)

    def bootstrap_rows(self, z_rows: np.ndarray, params_rows: list[Params], key: np.uint64, out: np.ndarray) -> None:
        """out[r] = `bootstrap` of sorted row r of z_rows (R, n) with params_rows[r]. The rows share every
        resample's counts (one stream, one n), so a kernel may draw each resample once for all of them (a team's
        terms); this default bootstraps row by row."""
        for row, params, values in zip(z_rows, params_rows, out):
            self.bootstrap(row, params, key, values)

    def of_normal(self, mu: float, sigma: float, params: Params) -> float | None:
        """The measure of a normal total reward N(mu, sigma^2), where there is a closed form (the docs' and the
        tests' known answer); None where there is none."""
        return None

    def of_distribution(self, values: np.ndarray, probabilities: np.ndarray, params: Params) -> float | None:
        """The measure of a discrete distribution: ascending values and their probabilities (an exactly enumerated
        world); None where the measure cannot say."""
        return None

    def label(self, params: Params, *, short: bool = False, beta: float | None = None) -> str:
        """The measure by name and parameters, for legends and tables: 'Wang (η=0.5)', 'power (gamma=0.5)'.

        `short`: the groups told apart share the measure's CVaR level (CVaR's label leaves it out). `beta`: the runs'
        reporting level, when it tells groups apart and the measure does not take it as a parameter.
        """
        shown = [f"{p.symbol or p.name}={params[p.name]:g}" for p in self.parameters]
        if beta is not None and "beta" not in params:
            shown.append(f"β={beta:g}")
        title = self.title or self.name
        return f"{title} ({', '.join(shown)})" if shown else title
