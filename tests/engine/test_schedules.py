"""Per-iteration schedules (riskplan.engine.schedules): the step size eps_l when its denominator overflows, and the
growing number of samples W_l = W (1 + l)^g. The soft-risk level beta_l is in test_soft_risk.py."""

from __future__ import annotations

from support import TINY

from riskplan import compose, train
from riskplan.config.schema import StepSizeConf
from riskplan.engine.schedules import step_size


def test_a_step_size_whose_denominator_overflows_is_zero_not_an_error():
    assert step_size(199, StepSizeConf(initial=0.1, decay=50.0, power=1000.0)) == 0.0
    assert step_size(10, StepSizeConf(initial=0.1, decay=50.0, power=1.0)) == 0.1 / 1.2


def test_growing_sample_schedule(tmp_path):
    run = train(
        compose([*TINY, "train.iterations=4", "train.samples=100", "train.samples_growth=1.0"]),
        tmp_path / "grow",
    )
    assert run.metrics.samples.tolist() == [100, 200, 300, 400]  # W_l = W (1 + l)^g
