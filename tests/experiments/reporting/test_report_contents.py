"""`riskplan report` on small real runs: figures (checked on the matplotlib objects), report.csv recomputed from the
run tables, broken/partial runs skipped with their reason, tables rebuilt from run.mcap, bad input, defaults."""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from matplotlib.artist import Artist
from PIL import Image
from support import FAST
from typer.testing import CliRunner

import riskplan
from riskplan.cli import app
from riskplan.experiments.landscape import compute_landscape
from riskplan.experiments.reporting import PHASES, build_report, write_report
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.reporting.figures import FIGURES, make_figures
from riskplan.experiments.reporting.figures.naming import names
from riskplan.experiments.reporting.parallel import WORKERS_ENV
from riskplan.experiments.reporting.stats import seed_interval, wilson
from riskplan.risk import cvar, value_at_risk

pytestmark = pytest.mark.slow  # six runs, a landscape and reports drawn from them

CONDITIONS = {
    "cvar_s0": [],
    "cvar_s1": ["seed=1"],
    "neutral_s0": ["risk=neutral"],
    "neutral_s1": ["risk=neutral", "seed=1"],
    "team_s0": ["experiment=paper_team"],
    "team_s1": ["experiment=paper_team", "seed=1"],
}
NEUTRAL, AVERSE = "risk-neutral", "risk-averse (CVaR β=0.1)"  # the paper's pair, in a reproduction's figures
USER_NAMES = {  # what differs, in a user's runs: the measure and team as report.csv's groups say them
    "neutral": "risk-neutral, centralized",
    "cvar": "risk-averse (CVaR β=0.1), centralized",
    "team": "risk-averse (CVaR β=0.1), distributed N=3",
}
runner = CliRunner()


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="session")
def sweep(tmp_path_factory) -> Path:
    """Six small real runs (CVaR, risk-neutral, team; seeds 0 and 1) and a small landscape on their world."""
    root = tmp_path_factory.mktemp("sweep")
    for name, extra in CONDITIONS.items():
        riskplan.train(riskplan.compose(FAST + extra), root / name)
    compute_landscape(
        riskplan.compose(FAST), root / "landscape", points=7, episodes=300, ranges=((-20.0, 60.0), (-20.0, 60.0))
    )
    return root


@pytest.fixture(scope="session")
def collected(sweep):
    return collect([sweep])


OTHER_RUNS = {"soft_risk", "consensus_orders"}  # figures of runs this sweep does not hold (drawn in
# tests/run/test_soft_risk.py and tests/experiments/reporting/test_figures.py)
# and the figures of reproduce's studies beyond the paper (drawn in tests/experiments/reporting/test_study_tables.py)
OTHER_RUNS |= {"risk_measures", "richer_policies", "hetero_team", "faults"}


@pytest.fixture(scope="session")
def figures(collected):
    specs, skipped = make_figures(collected)
    assert set(skipped) <= OTHER_RUNS, skipped
    return {s.name: s for s in specs}


@pytest.fixture(scope="session")
def reproduction(sweep, tmp_path_factory) -> Path:
    """The same runs laid out as riskplan reproduce lays them out: the paper's pair in single/, the team in team/."""
    root = tmp_path_factory.mktemp("reproduction")
    for name in CONDITIONS:
        shutil.copytree(sweep / name, root / ("team" if name.startswith("team") else "single") / name)
    return root


@pytest.fixture(scope="session")
def paper_figures(reproduction):
    specs, _ = make_figures(collect([reproduction]))
    return {s.name: s for s in specs}


@pytest.fixture(scope="session")
def page(sweep, tmp_path_factory) -> Path:
    """The report over the whole sweep, figures in PNG and PDF."""
    return build_report([sweep], tmp_path_factory.mktemp("report") / "out", ["png", "pdf"])


def headline(run_dir: Path) -> int:
    return -1 if yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())["team"]["robots"] > 1 else 0


def metrics_of(run_dir: Path, robot: int | None = None) -> pd.DataFrame:
    m = pd.read_parquet(run_dir / "metrics.parquet")
    return m.loc[m.robot == (headline(run_dir) if robot is None else robot)].sort_values("iteration")


def eval_of(run_dir: Path) -> pd.DataFrame:
    e = pd.read_parquet(run_dir / "eval.parquet")
    return e.loc[e.robot == headline(run_dir)]


def labelled(ax) -> dict:
    return {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}


def seed_mean(sweep: Path, names: list[str], column: str, robot: int | None = None) -> np.ndarray:
    return np.mean([metrics_of(sweep / n, robot)[column].to_numpy() for n in names], axis=0)


# ------------------------------------------------------------------------------------------------ grouping
def test_runs_are_grouped_by_what_differs(collected):
    assert len(collected.runs) == 6 and not collected.broken and len(collected.landscapes) == 1
    assert {"risk.measure", "team.robots", "experiment"} <= set(collected.differing)
    assert "seed" not in collected.differing
    kinds = {(g.measure, g.robots): g for g in collected.groups}
    assert set(kinds) == {("neutral", 1), ("cvar", 1), ("cvar", 3)}
    assert all(g.seeds == [0, 1] for g in collected.groups)
    assert "risk-neutral" in kinds["neutral", 1].label and "N=3" in kinds["cvar", 3].label
    assert len({g.label for g in collected.groups}) == 3 and len({g.color for g in collected.groups}) == 3
    neutral, averse = collected.paper_pair()
    assert (neutral, averse) == (kinds["neutral", 1], kinds["cvar", 1])
    assert collected.team_comparison() == (kinds["cvar", 1], [kinds["cvar", 3]])


# ------------------------------------------------------------------------------------------------ paper figures
def test_a_team_runs_evaluation_is_held_for_its_headline_policy_alone(collected, sweep):
    """The report reads a run's headline evaluation only: a team's robots' own episodes stay on disk."""
    (team,) = [info for info in collected.runs if info.path == sweep / "team_s0"]
    on_disk = pd.read_parquet(sweep / "team_s0" / "eval.parquet")
    assert team.headline == -1 and set(on_disk.robot) == {-1, 0, 1, 2}
    kept = on_disk[on_disk.robot == -1]
    assert team.run.eval.reset_index(drop=True).equals(kept.reset_index(drop=True))


def test_fig1_world_sources_start_and_final_paths(paper_figures, sweep):
    spec = paper_figures["fig1_paths"]
    assert spec.paper and spec.title.startswith("Fig. 1")  # a reproduction's runs: the paper's figure
    ax = spec.figure.axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (cell)", "y (cell)")
    shade = np.asarray(ax.images[0].get_array())
    x, y = np.meshgrid(np.arange(12), np.arange(12))
    assert shade.shape == (12, 12) and np.array_equal(shade == 1, y > x)  # the risky half-plane y > x, grey
    stars = [ln for ln in ax.get_lines() if ln.get_marker() == "*"]
    assert len(stars) == 1 and sorted(zip(stars[0].get_xdata(), stars[0].get_ydata())) == [(3, 9), (9, 3)]
    starts = [ln for ln in ax.get_lines() if ln.get_marker() == "o"]
    assert [(float(a), float(b)) for a, b in zip(starts[0].get_xdata(), starts[0].get_ydata())] == [(0.0, 0.0)]
    lines = labelled(ax)
    assert {NEUTRAL, AVERSE} <= set(lines)
    assert lines[NEUTRAL].get_color() != lines[AVERSE].get_color()
    for name, run in ((NEUTRAL, "neutral_s0"), (AVERSE, "cvar_s0")):
        assert_paths(ax, lines[name].get_color(), sweep / run, robot=0)


def assert_paths(ax, colour: str, run: Path, robot: int) -> None:
    """The axis draws the run's logged final paths in this colour, each with its end point."""
    paths = [ln for ln in ax.get_lines() if ln.get_color() == colour and ln.get_linestyle() == "-"]
    ends = [ln for ln in ax.get_lines() if ln.get_color() == colour and ln.get_marker() == "s"]
    t = pd.read_parquet(run / "trajectories.parquet")
    t = t.loc[(t.policy == "final") & (t.robot == robot)]
    assert len(paths) == len(ends) == t.episode.nunique() == 3
    for line, end, (_, episode) in zip(paths, ends, t.groupby("episode")):
        episode = episode.sort_values("step")
        assert np.array_equal(np.round(line.get_xdata()), episode.x) and np.array_equal(
            np.round(line.get_ydata()), episode.y
        )  # the logged path, jittered by < 0.5 cell
        assert (round(end.get_xdata()[0]), round(end.get_ydata()[0])) == (episode.x.iloc[-1], episode.y.iloc[-1])


def test_fig1_of_a_users_runs_has_a_panel_per_group(figures, sweep):
    spec = figures["fig1_paths"]
    assert not spec.paper and "Fig." not in spec.title
    panels = {ax.get_title().replace("\n", " "): ax for ax in spec.figure.axes}  # a long title wraps
    assert set(panels) == {f"{name}, seed 0" for name in USER_NAMES.values()}
    for run, name in USER_NAMES.items():
        ax = panels[f"{name}, seed 0"]
        colour = next(ln.get_color() for ln in ax.get_lines() if ln.get_linestyle() == "-")
        assert_paths(ax, colour, sweep / f"{run}_s0", robot=-1 if run == "team" else 0)


def test_fig2_cvar_per_iteration_is_the_across_seed_mean_with_a_band(paper_figures, sweep):
    spec = paper_figures["fig2_cvar"]
    ax = spec.figure.axes[0]
    assert ax.get_xlabel() == "iteration" and "CVaR" in ax.get_ylabel()
    lines = labelled(ax)
    assert set(lines) == {NEUTRAL, AVERSE} and "2 seeds" in spec.caption
    for name, runs in ((NEUTRAL, ["neutral_s0", "neutral_s1"]), (AVERSE, ["cvar_s0", "cvar_s1"])):
        line = lines[name]
        assert np.array_equal(line.get_xdata(), np.arange(5))
        np.testing.assert_allclose(line.get_ydata(), seed_mean(sweep, runs, "cvar"), rtol=1e-12)
    assert len(ax.collections) == 2  # one 95% band per curve
    assert ax.get_legend() is None and spec.figure.legends  # the legend outside the axes


def test_fig2_of_a_users_runs_draws_every_group(figures, sweep):
    spec = figures["fig2_cvar"]
    assert not spec.paper and spec.title == "Learning curves: CVaR of the total reward"
    (ax,) = spec.figure.axes
    lines = labelled(ax)
    assert set(lines) == set(USER_NAMES.values())
    for run, name in USER_NAMES.items():
        robot = -1 if run == "team" else None
        expected = seed_mean(sweep, [f"{run}_s0", f"{run}_s1"], "cvar", robot)
        np.testing.assert_allclose(lines[name].get_ydata(), expected, rtol=1e-12)
    assert len(ax.collections) == 3


def test_fig3_centralized_and_team_both_seen_with_their_difference(figures, sweep):
    fig = figures["fig3_team"].figure
    mean_ax, cvar_ax, difference = fig.axes
    assert mean_ax.get_ylabel() == "mean total reward" and "CVaR" in cvar_ax.get_ylabel()
    for ax, column in ((mean_ax, "mean"), (cvar_ax, "cvar")):
        assert ax.get_xlabel() == "iteration"
        lines = labelled(ax)
        assert set(lines) == {"distributed N=3", "centralized"}
        team, central = lines["distributed N=3"], lines["centralized"]
        np.testing.assert_allclose(
            team.get_ydata(), seed_mean(sweep, ["team_s0", "team_s1"], column, robot=-1), rtol=1e-12
        )
        np.testing.assert_allclose(central.get_ydata(), seed_mean(sweep, ["cvar_s0", "cvar_s1"], column), rtol=1e-12)
        # the centralized curve over the team's: another colour, dashed, with markers
        assert team.get_color() != central.get_color()
        assert (team.get_linestyle(), team.get_marker()) == ("-", "None")
        assert (central.get_linestyle(), central.get_marker()) == ("--", "o")
        assert central.get_zorder() > team.get_zorder()
    assert difference.get_ylabel() == "team − centralized"
    for column in ("mean", "cvar"):
        (line,) = [ln for ln in difference.get_lines() if ln.get_label().endswith(f" {column}")]
        expected = seed_mean(sweep, ["team_s0", "team_s1"], column, robot=-1) - seed_mean(
            sweep, ["cvar_s0", "cvar_s1"], column
        )
        np.testing.assert_allclose(line.get_ydata(), expected, rtol=1e-9, atol=1e-9)
    assert len(difference.collections) == 2  # each difference with its band over the seeds


def test_fig4_consensus_error_on_a_log_scale(figures, sweep):
    ax = figures["fig4_consensus"].figure.axes[0]
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "iteration" and "theta" in ax.get_ylabel()
    (line,) = labelled(ax).values()
    errors = np.array([metrics_of(sweep / n, -1).consensus_error.to_numpy() for n in ("team_s0", "team_s1")])
    assert np.all(errors[:, 0] == 0) and np.all(errors[:, 1:] > 0)
    with np.errstate(divide="ignore"):
        geometric = 10 ** np.log10(errors).mean(axis=0)
    y = np.asarray(line.get_ydata(), float)
    assert np.isnan(y[0])  # all robots start at theta0: zero error is not drawn on a log axis
    np.testing.assert_allclose(y[1:], geometric[1:], rtol=1e-12)


# ------------------------------------------------------------------------------------------------ beyond the paper
def test_reward_distribution_marks_var_and_cvar(figures, sweep, collected):
    full, _tail = figures["reward_distribution"].figure.axes[:2]
    assert full.get_xlabel() == "total reward" and "CDF" in full.get_ylabel()
    assert set(labelled(full)) == set(USER_NAMES.values())
    for g, name in zip(collected.groups, names(collected.groups)):
        z = np.concatenate([eval_of(r.path).total_reward.to_numpy() for r in g.runs])
        var = [ln for ln in full.get_lines() if ln.get_label() == f"_VaR {g.label}"]
        cv = [ln for ln in full.get_lines() if ln.get_label() == f"_CVaR {g.label}"]
        assert var[0].get_xdata()[0] == pytest.approx(value_at_risk(z, 0.1))
        assert cv[0].get_xdata()[0] == pytest.approx(cvar(z, 0.1))
        ecdf = labelled(full)[name]
        assert np.all(np.diff(ecdf.get_ydata()) > 0) and ecdf.get_ydata()[-1] == 1.0


def test_reward_distribution_with_a_beta_of_1_keeps_a_lower_tail(collected):
    """A beta sweep reaching 1 (CVaR = mean) once broke the tail panel: it asked for quantiles up to 2."""
    import copy

    from riskplan.experiments.reporting.figures import fig_distribution

    swept = copy.deepcopy(collected)
    swept.groups[0].first.config["risk"]["beta"] = 1.0
    spec = fig_distribution(swept)
    tail = spec.figure.axes[1]
    assert tail.get_ylim() == (0.0, 0.5)
    marks = [ln for ln in tail.get_lines() if ln.get_label() == f"_beta {swept.groups[0].label}"]
    assert marks[0].get_ydata()[0] == 1.0  # its (VaR, beta) mark sits above the panel, drawn but clipped


def test_risk_frontier_has_one_point_per_group(figures, collected):
    ax = figures["risk_frontier"].figure.axes[0]
    assert ax.get_xlabel() == "mean total reward" and "CVaR" in ax.get_ylabel()
    assert len(ax.containers) == len(collected.groups)
    for container, g in zip(ax.containers, collected.groups):
        point = container.lines[0]
        values = [
            (eval_of(r.path).total_reward.mean(), cvar(eval_of(r.path).total_reward.to_numpy(), 0.1)) for r in g.runs
        ]
        assert point.get_xdata()[0] == pytest.approx(np.mean([v[0] for v in values]))
        assert point.get_ydata()[0] == pytest.approx(np.mean([v[1] for v in values]))


def test_team_theta_trajectories_per_robot(figures, sweep):
    axes = figures["team_thetas"].figure.axes
    assert len(axes) == 2 and [ax.get_ylabel() for ax in axes] == [r"$\theta_{0}$", r"$\theta_{1}$"]
    lines = labelled(axes[0])
    assert set(lines) == {"robot 0", "robot 1", "robot 2", "network average"}
    np.testing.assert_allclose(
        lines["robot 2"].get_ydata(), seed_mean(sweep, ["team_s0", "team_s1"], "theta_0", robot=2), rtol=1e-12
    )


def test_landscape_heatmaps_with_training_paths(figures, sweep, collected):
    fig = figures["landscape"].figure
    heat = [ax for ax in fig.axes if ax.images]
    assert len(heat) == 2
    table = pd.read_parquet(sweep / "landscape" / "landscape.parquet")
    for ax, column in zip(heat, ("mean", "cvar")):
        assert ax.get_xlabel().startswith(r"$\theta_{0}$") and ax.get_ylabel().startswith(r"$\theta_{1}$")
        grid = table.pivot(index="theta_1", columns="theta_0", values=column).to_numpy()
        np.testing.assert_array_equal(np.asarray(ax.images[0].get_array()), grid)
        best = table.loc[table[column].idxmax()]
        star = labelled(ax)["grid maximum"]
        assert (star.get_xdata()[0], star.get_ydata()[0]) == (best.theta_0, best.theta_1)
        paths = [ln for ln in ax.get_lines() if ln.get_linestyle() == "-"]
        assert len(paths) == 6  # every run was trained on this world
        first = next(ln for ln in paths if ln.get_label() == collected.groups[0].label)
        run = collected.groups[0].runs[0]
        np.testing.assert_allclose(first.get_xdata()[:-1], metrics_of(run.path).theta_0)
        assert first.get_xdata()[-1] == pytest.approx(run.run.summary["theta_final"][0])


# ------------------------------------------------------------------------------------------------ tables and page
def test_report_csv_equals_numbers_recomputed_from_the_run_tables(sweep, page):
    out = page.parent
    table = pd.read_csv(out / "report.csv")
    assert len(table) == 3
    for _, row in table.iterrows():
        names = {
            ("neutral", 1): ["neutral_s0", "neutral_s1"],
            ("cvar", 1): ["cvar_s0", "cvar_s1"],
            ("cvar", 3): ["team_s0", "team_s1"],
        }[(row["measure"], row["robots"])]
        per_seed = []
        for name in names:
            e = eval_of(sweep / name)
            z = e.total_reward.to_numpy()
            per_seed.append(
                {
                    "mean": z.mean(),
                    "cvar": cvar(z, 0.1),
                    "value_at_risk": value_at_risk(z, 0.1),
                    "risky_fraction": (e.risky_steps > 0).mean(),
                    "reached_safe": (e.source_reached == 0).mean(),
                    "reached_risky": (e.source_reached == 1).mean(),
                    "reached_none": (e.source_reached == -1).mean(),
                }
            )
        for key in per_seed[0]:
            mean, low, high = seed_interval([v[key] for v in per_seed])
            assert row[key] == pytest.approx(mean, rel=1e-12, abs=1e-12), key
            assert (row[f"{key}_low"], row[f"{key}_high"]) == (
                pytest.approx(low, rel=1e-9, abs=1e-12),
                pytest.approx(high, rel=1e-9, abs=1e-12),
            )
        assert row["seeds"] == 2 and "Student-t" in row["interval"]
    assert table["degenerate"].isna().all()  # the paper's runs learned nothing degenerate
    html = page.read_text()
    for _, row in table.iterrows():
        assert row["group"] in html and f"{row['cvar']:,.1f}" in html
    assert "degenerate" not in html


def test_single_run_intervals_are_the_run_summaries_bootstrap(sweep, tmp_path):
    page = build_report([sweep / "cvar_s0"], tmp_path / "one", ["svg"])
    assert sorted(p.suffix for p in page.parent.glob("fig*")) == [".svg"] * 2  # Figs. 1-2 only: one policy
    (row,) = pd.read_csv(page.parent / "report.csv").to_dict("records")
    summary = json.loads((sweep / "cvar_s0" / "summary.json").read_text())
    for key in ("mean", "cvar", "value_at_risk"):
        assert row[key] == pytest.approx(summary[key]["value"], rel=1e-12)
        assert row[f"{key}_low"] == pytest.approx(summary[key]["low"], rel=1e-12)
        assert row[f"{key}_high"] == pytest.approx(summary[key]["high"], rel=1e-12)
    e = eval_of(sweep / "cvar_s0")
    low, high = wilson(float((e.risky_steps > 0).sum()), len(e))
    assert (row["risky_fraction_low"], row["risky_fraction_high"]) == (pytest.approx(low), pytest.approx(high))


def test_page_is_self_contained(page):
    html = page.read_text()
    sources = re.findall(r'<img[^>]*\ssrc="([^"]*)"', html)
    # eight figures, and the pictures of the two worlds (the single robot's, the team's)
    assert len(sources) == 10 and all(s.startswith("data:image/png;base64,") for s in sources)
    assert not re.search(r"(src|href)=\"(https?:)?//", html) and "url(" not in html
    assert "<script" not in html and "<link" not in html
    assert "Configurations that differ" in html and "risk.measure" in html and "team.robots" in html
    for name in ("fig1_paths", "fig2_cvar", "fig3_team", "fig4_consensus", "landscape"):
        assert (page.parent / f"{name}.png").is_file() and (page.parent / f"{name}.pdf").is_file()


# ------------------------------------------------------------------------------------------------ broken runs
def test_broken_runs_are_listed_and_missing_tables_rebuilt_from_the_log(sweep, tmp_path):
    mixed = tmp_path / "mixed"
    killed = mixed / "killed"  # a run killed mid-way: a truncated run.mcap and nothing else
    shutil.copytree(sweep / "cvar_s0", killed)
    for name in ("metrics.parquet", "eval.parquet", "trajectories.parquet", "summary.json", "checkpoint"):
        (killed / name).unlink()
    data = (killed / "run.mcap").read_bytes()
    (killed / "run.mcap").write_bytes(data[: len(data) // 2])
    bare = mixed / "bare"  # a finished run whose parquet tables are gone
    shutil.copytree(sweep / "neutral_s0", bare)
    for name in ("metrics.parquet", "eval.parquet", "trajectories.parquet"):
        (bare / name).unlink()
    garbage = mixed / "garbage"
    (garbage / ".hydra").mkdir(parents=True)
    shutil.copy(sweep / "cvar_s1" / ".hydra" / "config.yaml", garbage / ".hydra" / "config.yaml")
    (garbage / "run.mcap").write_bytes(b"not a log at all")
    failed = mixed / "failed"
    (failed / ".hydra").mkdir(parents=True)
    shutil.copy(sweep / "cvar_s1" / ".hydra" / "config.yaml", failed / ".hydra" / "config.yaml")
    (failed / "status.json").write_text(json.dumps({"status": "failed", "error": "boom: theta not finite"}))
    hollow = mixed / "hollow"  # complete files, but no evaluation episodes
    shutil.copytree(sweep / "cvar_s1", hollow)
    pd.read_parquet(hollow / "eval.parquet").iloc[:0].to_parquet(hollow / "eval.parquet")

    out = tmp_path / "report"
    result = runner.invoke(app, ["report", str(mixed), "--out", str(out), "--format", "png"])
    assert result.exit_code == 0, result.output
    assert f"skipped {killed}: truncated" in result.output and f"rebuilt tables of {bare}" in result.output
    runs = pd.read_csv(out / "runs.csv").set_index("path")
    assert runs.loc[str(killed), "status"] == "skipped" and "truncated" in runs.loc[str(killed), "note"]
    assert runs.loc[str(garbage), "status"] == "skipped" and "not an MCAP file" in runs.loc[str(garbage), "note"]
    assert runs.loc[str(failed), "status"] == "skipped" and "boom: theta not finite" in runs.loc[str(failed), "note"]
    assert runs.loc[str(hollow), "status"] == "skipped" and "evaluation" in runs.loc[str(hollow), "note"]
    assert runs.loc[str(bare), "status"] == "used" and "rebuilt" in runs.loc[str(bare), "note"]
    (row,) = pd.read_csv(out / "report.csv").to_dict("records")
    e = eval_of(sweep / "neutral_s0")  # the original tables: the log gives back the same numbers
    assert row["mean"] == pytest.approx(e.total_reward.mean(), rel=1e-12)
    assert row["cvar"] == pytest.approx(cvar(e.total_reward.to_numpy(), 0.1), rel=1e-12)
    assert row["risky_fraction"] == pytest.approx((e.risky_steps > 0).mean())
    html = (out / "report.html").read_text()
    assert "Skipped 4 broken or partial run(s)" in html and str(killed) in html
    assert not any(p.exists() for p in (bare / "metrics.parquet", bare / "eval.parquet"))  # inputs untouched


# ------------------------------------------------------------------------------------------------ command line
def test_a_path_without_runs_is_bad_input(tmp_path, sweep):
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "never"
    for args in (
        ["report", str(empty)],
        ["report", str(tmp_path / "missing")],
        ["report", str(sweep / "cvar_s0"), "--format", "png,gif"],
    ):
        result = runner.invoke(app, [*args, "--out", str(out)])
        assert result.exit_code == 2, result.output
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in result.output
        assert not out.exists()
    assert str(empty) in runner.invoke(app, ["report", str(empty)]).output


def test_default_is_the_latest_reproduction(tmp_path, sweep, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["report"])
    assert result.exit_code == 2 and "riskplan reproduce" in result.output
    older = tmp_path / "outputs" / "reproduce" / "2026-01-01_00-00-00"
    newer = tmp_path / "outputs" / "reproduce" / "2026-01-02_00-00-00"
    shutil.copytree(sweep / "cvar_s0", older / "sweep" / "a")
    shutil.copytree(sweep / "neutral_s0", newer / "sweep" / "risk=neutral")
    result = runner.invoke(app, ["report", "--format", "png"])
    assert result.exit_code == 0, result.output
    assert (newer / "report" / "report.html").is_file() and not (older / "report").exists()
    runs = pd.read_csv(newer / "report" / "runs.csv")
    assert list(runs.path) == [str(Path("outputs/reproduce/2026-01-02_00-00-00/sweep/risk=neutral"))]


def test_landscape_table_measures_where_training_ended(page, sweep, collected):
    table = pd.read_csv(page.parent / "landscape.csv")
    assert sorted(table.group) == sorted(g.label for g in collected.groups)
    grid = pd.read_parquet(sweep / "landscape" / "landscape.parquet")
    for _, row in table.iterrows():
        group = next(g for g in collected.groups if g.label == row["group"])
        target = "mean" if group.measure == "neutral" else "cvar"
        assert row["objective"] == target
        best = grid.loc[grid[target].idxmax()]
        final = np.mean([r.run.summary["theta_final"] for r in group.runs], axis=0)
        assert row["distance_to_optimum"] == pytest.approx(np.hypot(*(final - [best.theta_0, best.theta_1])))
        nearest = grid.iloc[((grid[["theta_0", "theta_1"]].to_numpy() - final) ** 2).sum(axis=1).argmin()]
        assert row["gap_to_optimum"] == pytest.approx(best[target] - nearest[target])


# ------------------------------------------------------------------------------------------------ drawn on every CPU
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="worker processes are forked on Linux")


class Unfinished(Artist):
    """An artist matplotlib fails to draw: in every process, or only in a forked worker (which first leaves a
    marker file, and this process waits for it, so that the worker surely takes a figure)."""

    def __init__(self, marker: Path | None = None):
        super().__init__()
        self.parent, self.marker = os.getpid(), marker

    def draw(self, renderer):
        if self.marker is None or os.getpid() != self.parent:
            if self.marker is not None:
                self.marker.touch()
            raise RuntimeError("half-drawn")
        deadline = time.monotonic() + 60
        while not self.marker.exists() and time.monotonic() < deadline:
            time.sleep(0.01)


def with_artist(monkeypatch, artist: Callable[[], Artist], names: set[str] | None = None) -> None:
    """make_figures, as the report calls it, adds an artist() to the figures named (to every figure when names is
    None)."""
    from riskplan.experiments import reporting

    make = reporting.make_figures

    def patched(collected, progress=None):
        specs, skipped = make(collected, progress)
        for spec in specs:
            if names is None or spec.name in names:
                spec.figure.add_artist(artist())
        return specs, skipped

    monkeypatch.setattr(reporting, "make_figures", patched)


def files_of(out: Path) -> dict[str, bytes]:
    """Every file, report.html without the minute it was generated."""
    files = {p.name: p.read_bytes() for p in out.iterdir()}
    files["report.html"] = re.sub(rb"generated [0-9: -]+", b"", files["report.html"])
    return files


@linux_only
def test_worker_processes_write_the_same_files_as_one_process(sweep, tmp_path, monkeypatch):
    with_artist(monkeypatch, Unfinished, {"fig2_cvar"})
    made = {}
    for workers in (1, 2):
        monkeypatch.setenv(WORKERS_ENV, str(workers))
        made[workers] = write_report([sweep], tmp_path / str(workers), ["png", "pdf", "svg"])
    assert made[1].skipped == made[2].skipped and made[1].figures == made[2].figures
    assert made[2].skipped["fig2_cvar"] == "failed: RuntimeError: half-drawn" and "fig2_cvar" not in made[2].figures
    one, two = files_of(tmp_path / "1"), files_of(tmp_path / "2")
    assert one == two
    assert {f"{name}.{fmt}" for name in made[2].figures for fmt in ("png", "pdf", "svg")} < set(two)
    assert not any(name.startswith("fig2_cvar") for name in two)


def test_the_command_says_on_stderr_which_figure_failed_and_why(sweep, tmp_path, monkeypatch):
    """A failed figure is a fault to see where the command runs, not only in the page's list of figures left out."""
    monkeypatch.setenv(WORKERS_ENV, "1")
    with_artist(monkeypatch, Unfinished, {"fig2_cvar"})
    result = runner.invoke(app, ["report", str(sweep), "--out", str(tmp_path / "report"), "--format", "png"])
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning: figure")]
    assert warnings == ["warning: figure fig2_cvar failed: RuntimeError: half-drawn"]


@pytest.mark.parametrize("workers", ["1", "2"])
def test_the_report_tells_how_far_each_phase_has_come(sweep, tmp_path, monkeypatch, workers):
    monkeypatch.setenv(WORKERS_ENV, workers)
    heard = []
    made = write_report([sweep], tmp_path / "report", ["png"], progress=lambda *told: heard.append(told))
    assert list(dict.fromkeys(phase for phase, _, _ in heard)) == list(PHASES)  # each in turn
    for phase in PHASES:
        done = [d for p, d, _ in heard if p == phase]
        assert done == sorted(done)
    last = {phase: (done, total) for phase, done, total in heard}
    builders = sum(figure.main for figure in FIGURES) + 1  # and the one landscape
    assert last == {
        "loading runs": (len(CONDITIONS), len(CONDITIONS)),  # the runs; the landscape is no run
        "making figures": (builders, builders),
        "drawing figures": (len(made.figures), len(made.figures)),
    }


@linux_only
def test_a_figure_failing_in_a_worker_is_skipped_and_the_others_written(sweep, tmp_path, monkeypatch):
    monkeypatch.setenv(WORKERS_ENV, "2")
    with_artist(monkeypatch, lambda: Unfinished(tmp_path / "worker-failed"))
    made = write_report([sweep], tmp_path / "report", ["png", "pdf"])
    failed = {name for name, why in made.skipped.items() if why == "failed: RuntimeError: half-drawn"}
    assert failed and made.figures  # the worker's figures failed, this process drew the others
    assert set(made.skipped) - failed <= OTHER_RUNS and len(failed) + len(made.figures) == 10  # 2 worlds too
    out = tmp_path / "report"
    manifest = set(json.loads((out / ".riskplan-manifest.json").read_text())["files"])
    drawn = {f"{name}.{fmt}" for name in made.figures for fmt in ("png", "pdf")}
    assert drawn <= manifest and drawn <= {p.name for p in out.iterdir()}
    written = {name for name in manifest | {p.name for p in out.iterdir()} if name.endswith((".png", ".pdf"))}
    assert not any(name.split(".")[0] in failed for name in written)
    html = made.page.read_text()
    assert all(f'<figure id="{name}">' in html for name in made.figures)
    assert all(f"<li><b>{name}</b>: failed: RuntimeError: half-drawn</li>" in html for name in failed)


def test_page_images_are_the_figure_files_at_130_dpi(page):
    html = page.read_text()
    images = re.findall(r'<figure id="([^"]+)"><img src="data:image/png;base64,([^"]+)"', html)
    assert len(images) == 10  # eight figures and two worlds
    for name, data in images:
        shown = Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")
        file = Image.open(page.parent / f"{name}.png")
        assert file.info["dpi"] == pytest.approx((200, 200), abs=0.01)
        assert shown.size == (round(file.width * 130 / 200), round(file.height * 130 / 200))
        same = np.asarray(file.convert("RGB").resize(shown.size, Image.BILINEAR), float)
        assert np.abs(np.asarray(shown, float) - same).mean() < 4  # the same picture (0-255 per channel)
