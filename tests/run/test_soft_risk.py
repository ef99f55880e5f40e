"""Soft risk (risk.schedule, CeSoR): the level beta_l of the CVaR gradient, its values, its log, resume, and that
kind=none is the paper's update bit for bit."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pandas as pd
import pytest
from support import TINY, assert_same_outputs, kill_after_iteration, resume_cli

from riskplan import compose
from riskplan.config.schema import RiskConf, ScheduleConf
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.engine.schedules import risk_level, step_size
from riskplan.engine.step import starts
from riskplan.risk import cvar_gradient
from riskplan.run.build import build_setup
from riskplan.run.compose import expand_overrides, expand_shorthands
from riskplan.run.log_reader import read_log
from riskplan.run.training import train

# 8 iterations of 400 samples from theta0 = (0, 0), a checkpoint every 3: the tests know these numbers
RUN = [*TINY, "train.iterations=8", "train.samples=400", "train.checkpoint_every=3", "train.theta0=[0,0]"]
LINEAR = ["risk.schedule=linear", "risk.schedule.iterations=5"]


def risk(kind: str, beta: float, start: float = 1.0, iterations: int = 4) -> RiskConf:
    return RiskConf(measure="cvar", beta=beta, schedule=ScheduleConf(kind=kind, start=start, iterations=iterations))


def test_linear_schedule_is_the_straight_line_from_start_to_beta_then_beta():
    plan = risk("linear", 0.5, start=1.0, iterations=4)
    assert [risk_level(l, plan) for l in range(7)] == [1.0, 0.875, 0.75, 0.625, 0.5, 0.5, 0.5]
    midpoint = risk("linear", 0.25, start=0.75, iterations=10)
    assert risk_level(5, midpoint) == 0.5  # (start + beta) / 2, exactly
    assert risk_level(10, midpoint) == 0.25 and risk_level(10**9, midpoint) == 0.25


def test_exponential_schedule_is_geometric_from_start_to_beta_then_beta():
    plan = risk("exponential", 0.25, start=1.0, iterations=2)
    assert [risk_level(l, plan) for l in range(5)] == [1.0, 0.5, 0.25, 0.25, 0.25]  # 0.5: the geometric mean
    quarter = risk("exponential", 0.2, start=0.8, iterations=4)
    assert risk_level(2, quarter) == pytest.approx(math.sqrt(0.8 * 0.2), abs=1e-15)  # 0.4
    levels = [risk_level(l, quarter) for l in range(5)]
    assert all(a > b for a, b in itertools.pairwise(levels))  # falls monotonically
    ratios = np.array(levels[1:]) / np.array(levels[:-1])
    np.testing.assert_allclose(ratios, ratios[0], rtol=1e-12)  # by a constant factor per iteration


def test_no_schedule_is_beta_at_every_iteration_and_one_iteration_reaches_beta_at_once():
    assert {risk_level(l, risk("none", 0.1, start=0.5, iterations=3)) for l in range(10)} == {0.1}
    assert [risk_level(l, risk("linear", 0.1, iterations=1)) for l in range(3)] == [1.0, 0.1, 0.1]


def test_the_shorthand_names_the_kind_on_the_command_line():
    assert expand_shorthands(["risk.schedule=linear", "seed=1"]) == ["risk.schedule.kind=linear", "seed=1"]
    assert expand_shorthands(["risk.schedule=none,linear"]) == ["risk.schedule.kind=none,linear"]
    assert expand_shorthands(["risk.schedule.start=0.5"]) == ["risk.schedule.start=0.5"]
    assert "risk.schedule.kind=exponential" in expand_overrides(["risk.schedule=exponential"])
    cfg = compose(["risk.schedule=exponential"])
    assert cfg.risk.schedule.kind == "exponential" and cfg.risk.schedule.start == 1.0


@pytest.mark.slow  # over a second
def test_no_schedule_is_the_papers_update_bit_for_bit(tmp_path):
    """kind=none (whatever its other keys) trains exactly like a config without the schedule, and like a hand-written
    loop of eq. (11) with Algorithm 1's gradient at beta."""
    default = train(compose(RUN), tmp_path / "default").metrics.drop(columns="seconds")
    named = train(
        compose([*RUN, "risk.schedule=none", "risk.schedule.start=0.5", "risk.schedule.iterations=2"]),
        tmp_path / "none",
    ).metrics.drop(columns="seconds")
    pd.testing.assert_frame_equal(default, named, check_exact=True)
    assert (default.beta_l == 0.1).all()

    setup = build_setup(compose(RUN))
    theta = setup.theta0[None, :].copy()
    for l in range(setup.params.train.iterations):
        row = default.loc[default.iteration == l].iloc[0]
        assert [row.theta_0, row.theta_1] == theta[0].tolist()
        batch = simulate(setup.world, setup.kernel, theta, starts(setup), rng.robot_keys(0, rng.TRAIN, l, 1), 400)
        z, scores = batch.total_reward.reshape(1, 400), batch.score.reshape(1, 400, -1)
        theta = theta + step_size(l, setup.params.train.step_size) * cvar_gradient(z, scores, 0.1)
    assert [float(t) for t in theta[0]] == [
        float(t) for t in train(compose(RUN), tmp_path / "again").summary["theta_final"]
    ]


@pytest.mark.slow  # over a second
def test_the_schedule_is_used_logged_in_parquet_and_mcap_and_metrics_stay_at_beta(tmp_path):
    run = train(compose([*RUN, *LINEAR]), tmp_path / "linear")
    params = build_setup(compose([*RUN, *LINEAR])).params
    expected = [risk_level(l, params.risk) for l in range(8)]
    np.testing.assert_allclose(expected[:5], [1.0, 0.82, 0.64, 0.46, 0.28], rtol=1e-12)
    assert expected[5:] == [0.1, 0.1, 0.1]  # exactly beta once the schedule is over
    metrics = pd.read_parquet(tmp_path / "linear" / "metrics.parquet")
    assert metrics.beta_l.tolist() == expected
    assert list(metrics.columns).index("beta_l") == list(metrics.columns).index("step_size") + 1
    log = read_log(tmp_path / "linear" / "run.mcap")
    assert log.metrics.beta_l.tolist() == expected
    pd.testing.assert_frame_equal(log.metrics, metrics, check_exact=True)

    plain = train(compose(RUN), tmp_path / "plain").metrics
    same = plain.iteration == 0
    # iteration 0 draws the same episodes at the same theta: its statistics (at beta) agree, its step does not
    pd.testing.assert_series_equal(plain.loc[same, "cvar"], run.metrics.loc[same, "cvar"], check_exact=True)
    assert plain.loc[1, "theta_0"] != run.metrics.loc[1, "theta_0"]
    assert summary_beta(run) == 0.1


def summary_beta(run) -> float:
    return run.summary["beta"]


def test_risk_neutral_runs_log_the_mean_gradients_level_one(tmp_path):
    run = train(compose([*RUN, "risk=neutral", *LINEAR]), tmp_path / "neutral")
    plain = train(compose([*RUN, "risk=neutral"]), tmp_path / "plain")
    assert (run.metrics.beta_l == 1.0).all()
    pd.testing.assert_frame_equal(
        run.metrics.drop(columns="seconds"), plain.metrics.drop(columns="seconds"), check_exact=True
    )  # the schedule does not touch the mean gradient


@pytest.mark.slow  # `riskplan train` in subprocesses
def test_a_killed_scheduled_run_resumes_to_the_uninterrupted_run(tmp_path):
    """SIGKILL between checkpoints, inside the schedule (after iteration 4 of its 5; checkpoint at 3), resume."""
    overrides = [*RUN, *LINEAR]
    reference = tmp_path / "reference"
    train(compose(overrides), reference)  # here: the same numbers as a `riskplan train` (tests/e2e/test_determinism.py)
    out = tmp_path / "run"
    kill_after_iteration(overrides, out, 4)
    result = resume_cli(out)
    assert result.returncode == 0, result.stderr
    assert_same_outputs(out, reference)
    assert pd.read_parquet(out / "metrics.parquet").beta_l.iloc[6] == 0.1


@pytest.mark.slow  # renders a report
def test_the_report_compares_a_schedule_with_its_fixed_beta_twin(tmp_path):
    from riskplan.experiments.reporting import write_report

    for name, extra in (("none", []), ("linear", LINEAR)):
        train(compose([*RUN, *extra]), tmp_path / "runs" / name)
    with pytest.warns(UserWarning, match=r"1 group\(s\) learned something degenerate \(schedule=none\)"):
        made = write_report([tmp_path / "runs"], tmp_path / "report", ["png"])  # 8 iterations from theta0 = (0, 0)
    assert "soft_risk" in made.figures, made.skipped
    table = pd.read_csv(tmp_path / "report" / "soft_risk.csv")
    assert table.schedule.tolist() == ["none", "linear"] and table.seed.tolist() == [0, 0]
    assert table.schedule_iterations.tolist() == [100, 5]
    assert {"cvar", "mean", "reached_safe", "theta_final"} <= set(table.columns)
    page = (tmp_path / "report" / "report.html").read_text()
    assert "<h2>Soft risk</h2>" in page and "linear (1.00 → β = 0.1 over 5 iterations)" in page
