"""The gradient estimate of each robot that shares a risk node, its CVaR level beta_l and its objective: one
function for both backends (Algorithm 1 for CVaR, REINFORCE for the mean, riskplan.engine.risk_measures for the
others)."""

from __future__ import annotations

import math

import numpy as np

from riskplan.config.schema import Measure
from riskplan.engine.risk_measures import (
    cvar_gradient,
    mean_cvar_mix,
    mean_gradient,
    objective,
    objective_and_gradient,
)
from riskplan.run.schedules import risk_level


def gradients(z, scores, risk, l, stats, robots, baseline, beta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gradients, the CVaR levels beta_l (NaN for a measure without one) and the objective values of robots
    that share the risk node `risk`: z (R, W), scores (R, W, M). CVaR is Algorithm 1 (eq. 9) at the soft-risk level
    beta_l, the mean REINFORCE (eq. 4); the other measures are riskplan.engine.risk_measures' estimators."""
    if risk.measure == Measure.cvar:
        level = risk_level(l, risk)  # soft risk: beta_l; the paper's beta when risk.schedule.kind=none
        shared = level == beta and risk.beta == beta  # the statistics' VaR is this partition's
        grads = cvar_gradient(z, scores, level, var=stats["value_at_risk"][robots] if shared else None)
        values = stats["cvar"][robots] if risk.beta == beta else objective(z, risk)
    elif risk.measure == Measure.neutral:
        level = 1.0  # the mean gradient is CVaR_1's
        grads, values = mean_gradient(z, scores, baseline), stats["mean"][robots]
    elif risk.measure == Measure.mean_cvar:  # CVaR's part as above, the mean's REINFORCE; the statistics reused
        level = risk_level(l, risk)
        shared = level == beta and risk.beta == beta
        cvar_part = cvar_gradient(z, scores, level, var=stats["value_at_risk"][robots] if shared else None)
        grads = mean_cvar_mix(mean_gradient(z, scores, baseline), cvar_part, risk.weight)
        if risk.beta == beta:
            values = mean_cvar_mix(stats["mean"][robots], stats["cvar"][robots], risk.weight)
        else:
            values = objective(z, risk)
    else:  # wang sorts each row once for both; entropic
        level = math.nan
        values, grads = objective_and_gradient(z, scores, risk, baseline=baseline)
    return grads, np.full(len(z), level), values
