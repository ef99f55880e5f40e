"""The gradient estimate of each robot that shares a risk node, its CVaR level beta_l and its objective: one
function for both backends, by the node's measure (riskplan.engine.measures: Algorithm 1 for CVaR, REINFORCE for
the mean, and each other measure's own estimator)."""

from __future__ import annotations

import math

import numpy as np

from riskplan.engine.measures.base import Statistics
from riskplan.engine.measures.registry import risk_spec
from riskplan.engine.schedules import risk_level


def gradients(z, scores, risk, l, stats, robots, baseline, beta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gradients, the CVaR levels beta_l (NaN for a measure without one) and the objective values of robots
    that share the risk node `risk`: z (R, W), scores (R, W, M). `stats` are the iteration's statistics of every
    robot at the run's beta (summary_stats), which the measure may reuse for these `robots`; a measure that soft
    risk schedules (cvar, mean_cvar) takes its gradient at beta_l."""
    measure, params = risk_spec(risk)
    level = risk_level(l, risk) if measure.scheduled else measure.level(params)
    shared = Statistics(beta, stats["mean"][robots], stats["cvar"][robots], stats["value_at_risk"][robots])
    grads, values = measure.training(z, scores, params, level, shared, baseline)
    return grads, np.full(len(z), math.nan if level is None else level), values
