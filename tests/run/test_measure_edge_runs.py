"""Whole runs of the entropic and Wang measures at aversions whose naive arithmetic overflows: they finish, and
summary.json holds only finite numbers (it failed with NaN, "Out of range float values are not JSON compliant", for
risk=entropic risk.eta=2, and with an OverflowError for risk=wang risk.eta=1e155). A non-finite eta is still bad
input: exit 2, one line naming the key, nothing written."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan import compose
from riskplan.cli import app
from riskplan.engine.estimators import entropic
from riskplan.run.training import train_summary

runner = CliRunner()
PROBE = ["train.iterations=5", "train.samples=200", "train.eval_episodes=200"]  # the hostile-input probe's run


def finite_numbers(value, where: str = "summary") -> list[str]:
    """The places in a summary.json value that hold a non-finite float."""
    if isinstance(value, float):
        return [] if math.isfinite(value) else [where]
    if isinstance(value, dict):
        return [bad for k, v in value.items() for bad in finite_numbers(v, f"{where}.{k}")]
    if isinstance(value, list):
        return [bad for i, v in enumerate(value) for bad in finite_numbers(v, f"{where}[{i}]")]
    return []


@pytest.mark.parametrize("eta", [2.0, 1e300, 1.7e308])
def test_an_entropic_run_with_a_large_aversion_finishes_with_finite_figures(tmp_path, eta):
    out = tmp_path / "run"
    summary = train_summary(compose([*TINY, *PROBE, "risk=entropic", f"risk.eta={eta}"]), out)
    assert finite_numbers(summary) == []
    figure = summary["objective"]
    assert figure["measure"] == "entropic" and figure["low"] <= figure["value"] <= figure["high"]
    written = json.loads((out / "summary.json").read_text())
    assert written["objective"] == figure
    # the point value is the estimator's, on the evaluated total rewards (no more than their mean)
    rewards = pd.read_parquet(out / "eval.parquet")
    z = rewards["total_reward"][rewards["robot"] == 0].to_numpy()
    assert figure["value"] == entropic(z, eta)
    assert z.min() <= figure["value"] <= z.mean()


def test_a_team_with_overflowing_measures_per_robot_finishes_with_finite_figures(tmp_path):
    """team.risk's nodes take the same path: a Wang robot past eta^2's overflow and two entropic ones, each from its
    own start (its own bootstrap terms)."""
    nodes = "[{measure:wang,eta:1e155},{measure:entropic,eta:2},{measure:entropic,eta:1.7e308}]"
    config = compose(
        [*TINY, "experiment=paper_team", "team.robots=3", f"team.risk={nodes}", "team.starts=[[0,0],[1,0],[0,1]]"]
    )
    summary = train_summary(config, tmp_path / "team")
    assert finite_numbers(summary) == []
    terms = [robot["objective_at_average"] for robot in summary["robots"]]
    assert [t["measure"] for t in terms] == ["wang", "entropic", "entropic"]
    assert summary["team_objective"]["value"] == pytest.approx(sum(t["value"] for t in terms), rel=1e-12)


@pytest.mark.slow  # the probe's run through the CLI
def test_the_wang_run_that_overflowed_runs_through_the_cli_as_eta_1e154_does(tmp_path, monkeypatch):
    """risk=wang risk.eta=1e155 exited 1 with an OverflowError and left its directory behind; past eta = 1e154 the
    spectrum is 0 and the measure the minimum, so it gives eta=1e154's figures."""
    monkeypatch.chdir(tmp_path)
    figures = {}
    for eta in ("1e154", "1e155"):
        result = runner.invoke(app, ["train", *PROBE, "risk=wang", f"risk.eta={eta}", f"hydra.run.dir=run_{eta}"])
        assert result.exit_code == 0, result.output
        summary = json.loads((tmp_path / f"run_{eta}" / "summary.json").read_text())
        assert finite_numbers(summary) == []
        figures[eta] = summary["objective"]
    assert figures["1e155"] == figures["1e154"]


@pytest.mark.parametrize(
    "args, key",
    [
        (["risk=wang", "risk.eta=inf"], "risk.eta"),
        (["risk=entropic", "risk.eta=nan"], "risk.eta"),
        (["risk=wang", "risk.eta=-1e155"], "risk.eta"),
        (
            ["experiment=paper_team", "team.robots=2", "team.risk=[{measure:entropic},{measure:wang,eta:0}]"],
            "team.risk.1.eta",
        ),
    ],
)
def test_an_eta_that_is_not_finite_and_positive_is_refused_before_anything_is_written(tmp_path, monkeypatch, args, key):
    """Every finite eta > 0 runs (above); anything else is bad input, whichever node: exit 2, one line naming the
    key and the valid values, and no run directory."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    result = runner.invoke(app, ["train", *TINY, *args, "hydra.run.dir=out"])
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert key in lines[0] and "expected a finite eta > 0" in lines[0], lines[0]
    assert list(Path(tmp_path).rglob("*")) == [work]


def test_the_entropic_value_of_the_probe_run_is_the_estimator_of_its_evaluation(tmp_path):
    """Two-point sanity of the reported interval: it is a percentile interval of resample values, each between the
    sample's smallest and largest reward (no resample at +inf)."""
    summary = train_summary(compose([*TINY, *PROBE, "risk=entropic", "risk.eta=2"]), tmp_path / "run")
    rewards = pd.read_parquet(tmp_path / "run" / "eval.parquet")
    z = rewards["total_reward"][rewards["robot"] == 0].to_numpy()
    figure = summary["objective"]
    assert z.min() <= figure["low"] <= figure["high"] <= z.max()
    assert np.isfinite(summary["diagnosis"]["initial_objective"]["high"])
