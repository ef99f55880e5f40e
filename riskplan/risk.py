"""Risk measures and their policy-gradient estimators: the public face of `riskplan.engine.risk_measures`.

from riskplan.risk import cvar, cvar_gradient, mean_gradient, value_at_risk
"""

from riskplan.engine.risk_measures import cvar, cvar_gradient, mean_gradient, summary_stats, tail_count, value_at_risk

__all__ = ["cvar", "cvar_gradient", "mean_gradient", "summary_stats", "tail_count", "value_at_risk"]
