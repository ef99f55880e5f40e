"""report.csv and the page's table (riskplan.experiments.reporting.tables, .page) on two seeds of a tiny run,
without drawing a figure: the numbers recomputed from the runs' evaluation tables, a Student-t interval across the
seeds, and missing values as empty cells. The whole report over a sweep is in test_report_contents.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY

from riskplan import compose, train
from riskplan.experiments.reporting import write_report
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.reporting.page import comparison_section
from riskplan.experiments.reporting.study_tables import study_tables
from riskplan.experiments.reporting.tables import comparison_table, csv_text, degenerate_notes, runs_table
from riskplan.risk import cvar


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tables")
    for seed in (0, 1):
        train(compose([*TINY, f"seed={seed}"]), root / f"seed_{seed}")
    return root


def test_a_group_of_two_seeds_is_their_mean_with_a_t_interval(runs):
    collected = collect([runs])
    table = comparison_table(collected)
    (row,) = table.to_dict("records")
    z = [pd.read_parquet(runs / f"seed_{s}" / "eval.parquet").total_reward.to_numpy() for s in (0, 1)]
    means, cvars = [x.mean() for x in z], [cvar(x, 0.1) for x in z]
    assert (row["seeds"], row["seed_list"], row["eval_episodes"]) == (2, "0 1", 200)
    assert row["interval"] == "95% Student-t over 2 seeds"
    assert row["mean"] == pytest.approx(np.mean(means), rel=1e-12)
    assert row["cvar"] == pytest.approx(np.mean(cvars), rel=1e-12)
    half = 12.706 * abs(means[0] - means[1]) / 2  # t(0.975, 1 df) * sd / sqrt(2), with sd = |a - b| / sqrt(2)
    assert (row["mean_low"], row["mean_high"]) == pytest.approx((np.mean(means) - half, np.mean(means) + half))
    used = runs_table(collected)
    assert used.status.tolist() == ["used", "used"] and used.iterations.tolist() == [3, 3]
    assert used.cvar.tolist() == pytest.approx(cvars, rel=1e-12)
    html = comparison_section(table)
    assert f"{row['cvar']:,.1f} [{row['cvar_low']:,.1f}, {row['cvar_high']:,.1f}]" in html
    assert "95% Student-t over 2 seeds" in html
    assert pd.isna(row["degenerate"]) and "degenerate" not in html  # a CVaR run alone: nothing to flag


@pytest.mark.slow  # over a second
def test_a_risk_averse_group_below_its_worlds_risk_neutral_group_is_marked(tmp_path):
    """The CVaR run is pushed away from the sources (θ0 negative) and reaches none, nor did its θ0; the
    risk-neutral run heads for the safe source: on CVaR itself, the CVaR run ends far below it."""
    train(compose([*TINY, "risk=neutral", "train.theta0=[60.0,-20.0]"]), tmp_path / "neutral")
    train(compose([*TINY, "train.theta0=[-20.0,-20.0]"]), tmp_path / "cvar")
    collected = collect([tmp_path])
    table = comparison_table(collected).set_index("measure")
    assert pd.isna(table.loc["neutral", "degenerate"])
    notes = degenerate_notes(collected.groups)
    averse = table.loc["cvar", "group"]
    assert [note.split(" ", 1)[0] for note in notes[averse]] == ["reached_no_source", "below_neutral:"]
    z = {k: pd.read_parquet(tmp_path / k / "eval.parquet").total_reward.to_numpy() for k in ("neutral", "cvar")}
    below = notes[averse][1]
    assert f"{cvar(z['cvar'], 0.1):.1f} [" in below and f"against {cvar(z['neutral'], 0.1):.1f} [" in below
    assert "risk-averse (CVaR β=0.1)" in below and "train.theta0" in below
    assert table.loc["cvar", "degenerate"] == "; ".join(notes[averse])
    html = comparison_section(comparison_table(collected))
    assert html.count("⚠ degenerate") == 1 and "1 group(s) learned something degenerate" in html
    assert "below the risk-neutral group" in html
    with pytest.warns(UserWarning, match=r"^1 group\(s\) learned something degenerate \(risk-averse \(CVaR β=0.1\)\)"):
        write_report([tmp_path], tmp_path / "report", ["svg"])  # the command's one warning line


def test_missing_and_infinite_values_are_empty_cells():
    table = pd.DataFrame({"x": [1.5, np.nan, np.inf], "label": ["a", float("-inf"), None]})
    assert csv_text(table) == "x,label\n1.5,a\n,\n,\n"


@pytest.mark.slow  # about a second
def test_the_floor_plan_table_holds_the_floor_plan_study_alone(tmp_path):
    """A user's own map experiment (here the shipped map under another experiment's name) is in report.csv, not in
    floor_plan.csv, the study's table."""
    train(compose([*TINY, "experiment=floor_plan"]), tmp_path / "study")  # not reproduce's floor_plan/ folder
    depot = compose([*TINY, "experiment=floor_plan", "seed=1"])  # another sample: not a duplicate of the study's
    depot.experiment = "depot"
    train(depot, tmp_path / "depot")
    alone = collect([tmp_path / "depot"])
    assert len(comparison_table(alone)) == 1 and study_tables(alone)["floor_plan"].empty
    both = collect([tmp_path])
    (row,) = study_tables(both)["floor_plan"].to_dict("records")
    assert row["config.experiment"] == "floor_plan" and len(comparison_table(both)) == 2
