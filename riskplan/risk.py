"""Risk measures and their policy-gradient estimators: the public face of `riskplan.engine.risk_measures`.

from riskplan.risk import cvar, cvar_gradient, mean_gradient, value_at_risk
from riskplan.risk import objective, objective_gradient  # any measure: {"measure": "wang", "eta": 0.75}, ...
"""

from riskplan.engine.risk_measures import (
    MEASURES,
    RiskSpec,
    cvar,
    cvar_gradient,
    distortion,
    entropic,
    entropic_gradient,
    l_statistic,
    mean_gradient,
    objective,
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
    "MEASURES",
    "RiskSpec",
    "cvar",
    "cvar_gradient",
    "distortion",
    "entropic",
    "entropic_gradient",
    "l_statistic",
    "mean_gradient",
    "objective",
    "objective_gradient",
    "risk_spec",
    "spectral_gradient",
    "spectral_weights",
    "spectrum",
    "summary_stats",
    "tail_count",
    "value_at_risk",
]
