"""What changes from one training iteration to the next: the step size eps_l, the gradient's CVaR level beta_l
(soft risk) and the samples W_l."""

from __future__ import annotations

import math

from riskplan.config.schema import RiskConf, ScheduleKind, StepSizeConf, TrainConf


def step_size(iteration: int, schedule: StepSizeConf) -> float:
    """eps_l = initial / (1 + l / decay)^power (0 once the denominator overflows a float)."""
    try:
        return schedule.initial / (1.0 + iteration / schedule.decay) ** schedule.power
    except OverflowError:  # (1 + l/decay)^power beyond 1.8e308: the step is 0 to double precision
        return 0.0


def risk_level(iteration: int, risk: RiskConf) -> float:
    """beta_l, the CVaR level of iteration l's gradient (soft risk, CeSoR): risk.beta with kind=none; otherwise
    from start at l = 0 to risk.beta at l = schedule.iterations, linearly or geometrically, then risk.beta."""
    plan, beta = risk.schedule, risk.beta
    if plan.kind == ScheduleKind.none or iteration >= plan.iterations:
        return beta
    if iteration <= 0:
        return plan.start
    fraction = iteration / plan.iterations
    if plan.kind == ScheduleKind.linear:
        return plan.start + (beta - plan.start) * fraction
    return plan.start * (beta / plan.start) ** fraction  # exponential: log beta_l linear in l


def samples_at(iteration: int, train: TrainConf) -> int:
    """W_l = ceil(samples * (1 + l)^samples_growth)."""
    return math.ceil(train.samples * (1.0 + iteration) ** train.samples_growth)
