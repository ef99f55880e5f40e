"""engine.gradients: the training loop's estimates are riskplan.risk's objective and gradient bit for bit, also where
mean-CVaR reuses the iteration's statistics (its VaR, mean and CVaR) instead of computing them again."""

from __future__ import annotations

import numpy as np
import pytest

from riskplan.config.schema import RiskConf, ScheduleConf
from riskplan.engine.gradients import gradients
from riskplan.engine.risk_measures import objective, objective_gradient, summary_stats
from riskplan.engine.schedules import risk_level

BETA = 0.1  # the run's risk.beta, at which the iteration's statistics are taken


def _sample():
    z = np.random.default_rng(11).normal(500.0, 80.0, (3, 1500)).round(1)  # rounded: ties at the VaR
    return z, np.random.default_rng(12).normal(size=(3, 1500, 2))


@pytest.mark.parametrize("weight", [0.0, 0.3, 1.0])
@pytest.mark.parametrize(
    ("beta", "schedule"),
    [(BETA, "none"), (0.25, "none"), (BETA, "linear")],  # the shared VaR; another beta; beta_l != beta
)
@pytest.mark.parametrize("iteration", [0, 3])
def test_mean_cvar_from_the_statistics_is_the_two_calls_bit_for_bit(weight, beta, schedule, iteration):
    z, scores = _sample()
    risk = RiskConf(measure="mean_cvar", beta=beta, weight=weight, schedule=ScheduleConf(kind=schedule, iterations=4))
    robots = np.array([0, 2])
    grads, levels, values = gradients(
        z[robots], scores[robots], risk, iteration, summary_stats(z, BETA), robots, True, BETA
    )
    level = risk_level(iteration, risk)
    at_level = {"measure": "mean_cvar", "beta": level, "weight": weight}
    np.testing.assert_array_equal(grads, objective_gradient(z[robots], scores[robots], at_level))
    np.testing.assert_array_equal(values, objective(z[robots], risk))
    np.testing.assert_array_equal(levels, [level, level])


@pytest.mark.parametrize(
    "risk", [RiskConf(measure="wang", eta=0.75), RiskConf(measure="entropic", eta=0.01), RiskConf(measure="cvar")]
)
def test_other_measures_are_the_two_calls_bit_for_bit(risk):
    z, scores = _sample()
    grads, _, values = gradients(z, scores, risk, 0, summary_stats(z, BETA), slice(None), True, BETA)
    np.testing.assert_array_equal(grads, objective_gradient(z, scores, risk))
    np.testing.assert_array_equal(values, objective(z, risk))
