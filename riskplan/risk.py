"""Risk measures and their policy-gradient estimators: the public face of `riskplan.engine.risk_measures` and
`riskplan.engine.measures`.

from riskplan.risk import cvar, cvar_gradient, mean_gradient, value_at_risk
from riskplan.risk import objective, objective_gradient  # any measure: {"measure": "wang", "eta": 0.75}, ...
power = riskplan.risk.distortion("power", lambda u, gamma: u**gamma, gamma=(0, 1))  # a measure of your own
"""

from riskplan.engine.measures.base import Measure, Parameter, Params
from riskplan.engine.measures.registry import GROUP, lookup, names
from riskplan.engine.measures.spectral import Spectral, distortion
from riskplan.engine.risk_measures import (
    MEASURES,
    RiskSpec,
    cvar,
    cvar_gradient,
    distortion_at,
    entropic,
    entropic_gradient,
    l_statistic,
    mean_gradient,
    objective,
    objective_and_gradient,
    objective_gradient,
    risk_spec,
    spectral_gradient,
    spectral_weights,
    spectrum,
    summary_stats,
    tail_count,
    value_at_risk,
)

__all__ = [
    "GROUP",
    "MEASURES",
    "Measure",
    "Parameter",
    "Params",
    "RiskSpec",
    "Spectral",
    "cvar",
    "cvar_gradient",
    "distortion",
    "distortion_at",
    "entropic",
    "entropic_gradient",
    "l_statistic",
    "lookup",
    "mean_gradient",
    "names",
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
