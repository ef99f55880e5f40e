"""Risk measures and their policy-gradient estimators: the public face of `riskplan.engine.risk_measures` and
`riskplan.engine.measures`.

from riskplan.risk import cvar, cvar_gradient, mean_gradient, value_at_risk
from riskplan.risk import objective, objective_gradient  # any measure: {"measure": "wang", "eta": 0.75}, ...
power = riskplan.risk.distortion("power", lambda u, gamma: u**gamma, gamma=(0, 1))  # a measure of your own
"""

from riskplan.engine import risk_measures
from riskplan.engine.measures.base import Measure, Parameter, Params
from riskplan.engine.measures.registry import GROUP, lookup, names
from riskplan.engine.measures.spectral import Spectral, distortion
from riskplan.engine.risk_measures import *  # noqa: F403 (its __all__, the one list of the measures' functions)

__all__ = [
    "GROUP",
    "Measure",
    "Parameter",
    "Params",
    "Spectral",
    "distortion",
    "lookup",
    "names",
    *risk_measures.__all__,
]
