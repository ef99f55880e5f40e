"""`riskplan train` through the CLI (typer's CliRunner): every file of the output contract and its columns, a team's
rows, run directories that never collide, and --cfg job, which prints the config without running."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.run.log_reader import read_log
from riskplan.util.paths import claim_dir

runner = CliRunner()
METRICS = [
    "iteration",
    "robot",
    "healthy",
    "mean",
    "cvar",
    "value_at_risk",
    "std",
    "objective",
    "theta_0",
    "theta_1",
    "grad_norm",
    "step_size",
    "beta_l",
    "consensus_error",
    "samples",
    "seconds",
]
EVAL = ["episode", "robot", "healthy", "total_reward", "risky_steps", "source_reached", "steps"]
TRAJECTORIES = ["policy", "episode", "robot", "step", "x", "y", "reward"]


def only_run(root: Path) -> Path:
    (run,) = list((root / "outputs" / "runs").iterdir())
    return run


@pytest.mark.slow  # a whole run through the CLI
def test_train_writes_every_contract_file(in_tmp, fast_overrides):
    result = runner.invoke(app, ["train", *fast_overrides, "risk=neutral", "seed=3"])
    assert result.exit_code == 0, result.output
    run = only_run(in_tmp)
    assert run.name.endswith("_paper_single")
    assert f"run directory: {Path('outputs/runs') / run.name}" in result.output
    assert "risk=neutral" in result.output and "CVaR" in result.output  # the one-line summary
    for name in (
        ".hydra/config.yaml",
        ".hydra/overrides.yaml",
        "run.mcap",
        "metrics.parquet",
        "eval.parquet",
        "trajectories.parquet",
        "summary.json",
        "checkpoint",
        "foxglove_layout.json",
    ):
        assert (run / name).is_file(), name
    assert yaml.safe_load((run / ".hydra/overrides.yaml").read_text())[-2:] == ["risk=neutral", "seed=3"]
    metrics = pd.read_parquet(run / "metrics.parquet")
    assert list(metrics.columns) == METRICS
    assert list(metrics.iteration) == list(range(5)) and set(metrics.robot) == {0}
    assert list(pd.read_parquet(run / "eval.parquet").columns) == EVAL
    trajectories = pd.read_parquet(run / "trajectories.parquet")
    assert list(trajectories.columns) == TRAJECTORIES
    assert set(trajectories.policy) == {"initial", "final"}
    summary = json.loads((run / "summary.json").read_text())
    for name in ("mean", "cvar", "value_at_risk", "cvar_0.05", "cvar_0.1", "cvar_0.2"):
        assert summary[name]["low"] <= summary[name]["value"] <= summary[name]["high"], name
    assert summary["schema_version"] == 2 and summary["provenance"]["riskplan"]
    assert summary["objective"] == {"measure": "neutral", **summary["mean"]}  # the trained measure: the mean
    assert summary["theta_names"] == ["safe", "risky"] and summary["team_size"] == 1
    assert summary["team_objective"] == {k: summary["mean"][k] for k in ("value", "low", "high")}
    assert metrics.objective.tolist() == metrics["mean"].tolist() and metrics.healthy.all()
    log = read_log(run / "run.mcap")
    assert log.complete and log.metadata["config"]["risk"]["measure"] == "neutral"
    pd.testing.assert_frame_equal(log.metrics, metrics)
    pd.testing.assert_frame_equal(log.eval, pd.read_parquet(run / "eval.parquet"))


@pytest.mark.slow  # a whole run through the CLI
def test_team_run_has_per_robot_and_average_rows(in_tmp, fast_overrides):
    result = runner.invoke(app, ["train", "experiment=paper_team", *fast_overrides])
    assert result.exit_code == 0, result.output
    run = only_run(in_tmp)
    metrics = pd.read_parquet(run / "metrics.parquet")
    assert set(metrics.robot) == {-1, 0, 1, 2}
    per_iteration = metrics.groupby("iteration").consensus_error.nunique()
    assert (per_iteration == 1).all()  # repeated on every row of an iteration
    average = metrics[metrics.robot == -1].set_index("iteration")
    robots = metrics[metrics.robot >= 0].groupby("iteration")
    pd.testing.assert_series_equal(average.theta_0, robots.theta_0.mean(), check_names=False)
    assert (average.samples == 3 * 500).all()
    assert set(pd.read_parquet(run / "eval.parquet").robot) == {-1, 0, 1, 2}
    log = read_log(run / "run.mcap")
    assert log.metadata["network"]["edges"] and log.metadata["network"]["robots"] == 3


@pytest.mark.slow  # a whole run through the CLI
def test_explicit_run_dir_and_same_second_runs_do_not_collide(in_tmp, fast_overrides):
    result = runner.invoke(app, ["train", *fast_overrides, "hydra.run.dir=mine"])
    assert result.exit_code == 0, result.output
    assert (in_tmp / "mine" / "summary.json").is_file()
    first, second = claim_dir(in_tmp / "r", "_x"), claim_dir(in_tmp / "r", "_x")
    assert first != second and first.is_dir() and second.is_dir()
    assert second.name == first.name + "_1" and first.name.endswith("_x")


def test_cfg_job_prints_the_config_without_running(in_tmp):
    result = runner.invoke(app, ["train", "--cfg", "job", "risk=neutral", "train.samples=77"])
    assert result.exit_code == 0, result.output
    printed = yaml.safe_load(result.output)
    assert printed["risk"]["measure"] == "neutral" and printed["train"]["samples"] == 77
    assert not (in_tmp / "outputs").exists()


EXAMPLE = json.loads(
    (Path(__file__).resolve().parents[2] / "docs" / "data" / "reproduction" / "example_summary.json").read_text()
)


def test_the_run_line_names_beta_only_where_it_was_trained_and_the_level_of_every_figure():
    from riskplan.commands.train import summary_line

    cvar = summary_line(EXAMPLE, Path("out"))
    assert f"risk=cvar beta=0.1 robots=1: 200 iterations in {EXAMPLE['wall_time']:.2f} s" in cvar
    assert "CVaR_0.1 1442.4 [1440.6, 1444.1]" in cvar and "VaR_0.1 1504.9" in cvar
    objective = {**EXAMPLE["objective"], "measure": "neutral"}
    robots = [{**EXAMPLE["robots"][0], "objective_at_average": objective}]
    neutral = summary_line({**EXAMPLE, "risk": "neutral", "objective": objective, "robots": robots}, "o")
    assert "risk=neutral robots=1:" in neutral and "beta=" not in neutral and "CVaR_0.1 " in neutral


def test_a_team_of_its_own_measures_says_them_and_its_team_objective_beside_the_reported_measure():
    from riskplan.commands.train import summary_line

    own = [{"objective_at_average": {**EXAMPLE["objective"], "measure": m}} for m in ("cvar", "wang")]
    team = {"value": 2458.87, "low": 1988.94, "high": 2864.64}
    line = summary_line({**EXAMPLE, "robots": own, "team_objective": team}, "o")
    assert "risk=cvar beta=0.1 robots=1 (own measures: cvar, wang; team objective 2458.9 [1988.9, 2864.6]): " in line
    same = [{"objective_at_average": EXAMPLE["objective"]}] * 2
    assert "own measures" not in summary_line({**EXAMPLE, "robots": same, "team_objective": team}, "o")


def test_a_resumed_run_line_says_which_part_its_time_is():
    from riskplan.commands.train import summary_line

    line = summary_line({**EXAMPLE, "iterations": 600, "resumed_at": 400, "wall_time": 0.98}, "o")
    assert "600 iterations (resumed at 400: the last 200 in 0.98 s)" in line
