"""`riskplan check` through the CLI (typer's CliRunner): the team's assumptions, the warning when Assumption 6 fails,
and how it describes the order of consensus and gradient steps. It runs nothing and writes nothing."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from riskplan.cli import app

runner = CliRunner()


@pytest.mark.slow  # riskplan check composes a team and checks its graph (near a second)
def test_check_reports_team_assumptions(in_tmp):
    result = runner.invoke(app, ["check", "experiment=paper_team", "team.graph=ring"])
    assert result.exit_code == 0, result.output
    assert "Assumption 5: holds" in result.output and "SLEM" in result.output
    assert "Assumption 6" in result.output and "config OK" in result.output
    assert not (in_tmp / "outputs").exists()


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
def test_check_warns_when_assumption_6_fails(in_tmp):
    with pytest.warns(UserWarning, match="Assumption 6"):
        result = runner.invoke(app, ["check", "train.step_size.power=2"])
    assert result.exit_code == 0
    assert "Assumption 6" in result.output and "FAILS" in result.output


def test_a_step_size_of_zero_fails_assumption_6(in_tmp):
    """sum eps = 0, not infinity: check said "holds" for a run that learns nothing."""
    with pytest.warns(UserWarning, match=r"train.step_size.initial=0 breaks Assumption 6 \(sum eps = 0"):
        result = runner.invoke(app, ["check", "train.step_size.initial=0"])
    assert result.exit_code == 0 and "Assumption 6 (sum eps = inf, sum eps^2 < inf): FAILS" in result.output


def test_check_describes_the_order(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exact = runner.invoke(app, ["check", "experiment=paper_team", "team.order=gradient_tracking"])
    assert exact.exit_code == 0, exact.output
    assert "order: gradient_tracking" in exact.output and "sum_i y^i = sum_i Delta^i exactly" in exact.output
    late = runner.invoke(app, ["check", "experiment=paper_team", "team.order=gradient_tracking", "team.delay.max=2"])
    assert "the mass in flight" in late.output and "B + B0 = 12" in late.output
    paper = runner.invoke(app, ["check", "experiment=paper_team"])
    assert "order: combine_then_adapt (eq. 14)" in paper.output
