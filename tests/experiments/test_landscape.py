"""`riskplan landscape`: mean and CVaR on a theta grid with common random numbers, a run-like directory the report
recognises, bad input, and the paper world's optima where the trained policies end."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest
import yaml
from support import FAST
from typer.testing import CliRunner

import riskplan
from riskplan.cli import app
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.experiments import landscape as L
from riskplan.experiments.reporting.collect import collect
from riskplan.risk import cvar, value_at_risk
from riskplan.run.build import build_setup

runner = CliRunner()


@pytest.fixture(scope="module")
def setup():
    return build_setup(riskplan.compose(FAST))


def direct(setup, theta, episodes, seed=0):
    """One theta simulated on its own with the landscape's stream key."""
    key = np.array([rng.stream_key(seed, rng.LANDSCAPE)], dtype=np.uint64)
    return simulate(setup.world, setup.kernel, np.array([theta], float), setup.world.starts[:1], key, episodes)


def test_every_grid_point_replays_the_same_episode_streams(setup):
    thetas = L.grid_thetas(setup.theta0, (0, 1), ((-10.0, 50.0), (-10.0, 50.0)), 4)
    assert thetas.shape == (16, 2) and sorted(set(thetas[:, 0])) == [-10.0, 10.0, 30.0, 50.0]
    table = L.evaluate_grid(setup, thetas, 300, 0.1, seed=0)
    for i in (0, 6, 15):
        batch = direct(setup, thetas[i], 300)
        z = batch.total_reward
        assert table.loc[i, "mean"] == pytest.approx(z.mean(), rel=1e-12)
        assert table.loc[i, "cvar"] == pytest.approx(cvar(z, 0.1), rel=1e-12)
        assert table.loc[i, "value_at_risk"] == value_at_risk(z, 0.1)
        assert table.loc[i, "risky_fraction"] == (batch.risky_steps > 0).mean()
        assert table.loc[i, "reached_safe"] == (batch.source_reached == 0).mean()
        tail = np.minimum(z - value_at_risk(z, 0.1), 0)
        assert table.loc[i, "cvar_se"] == pytest.approx(tail.std(ddof=1) / (0.1 * np.sqrt(300)))
    # common random numbers: where a point sits in the grid (and how the grid is chunked) changes nothing
    again = L.evaluate_grid(setup, thetas[[15, 0, 15]], 300, 0.1, seed=0)
    assert again.loc[0, "cvar"] == again.loc[2, "cvar"] == table.loc[15, "cvar"]
    assert again.loc[1, "mean"] == table.loc[0, "mean"]
    # ... and the seed does: another seed is another set of streams
    other = L.evaluate_grid(setup, thetas[:1], 300, 0.1, seed=1)
    assert other.loc[0, "mean"] != table.loc[0, "mean"]


def test_chunking_does_not_change_the_numbers(setup, monkeypatch):
    thetas = L.grid_thetas(setup.theta0, (0, 1), ((0.0, 40.0), (0.0, 40.0)), 3)
    whole = L.evaluate_grid(setup, thetas, 200, 0.1, seed=3)
    monkeypatch.setattr(L, "CHUNK_EPISODES", 400)  # two grid points per kernel call
    pd.testing.assert_frame_equal(L.evaluate_grid(setup, thetas, 200, 0.1, seed=3), whole)


LANDSCAPE_COMMAND = ["landscape", *FAST, "seed=4", "--points", "5", "--episodes", "200", "--range=-10,50,-20,40"]


@pytest.mark.slow  # landscapes and a report through the CLI
def test_cli_writes_a_run_like_directory_the_report_recognises(tmp_path):
    out = tmp_path / "scan"
    result = runner.invoke(app, [*LANDSCAPE_COMMAND, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"landscape directory: {out}" in result.output and "max CVaR_0.1" in result.output
    table = pd.read_parquet(out / "landscape.parquet")
    assert len(table) == 25
    assert sorted(table.theta_0.unique()) == [-10.0, 5.0, 20.0, 35.0, 50.0]
    assert sorted(table.theta_1.unique()) == [-20.0, -5.0, 10.0, 25.0, 40.0]
    assert {
        "mean",
        "cvar",
        "value_at_risk",
        "std",
        "mean_se",
        "cvar_se",
        "risky_fraction",
        "reached_safe",
        "reached_risky",
        "reached_none",
    } <= set(table.columns)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kind"] == "landscape" and summary["seed"] == 4 and summary["episodes"] == 200
    best = table.loc[table.cvar.idxmax()]
    assert summary["best"]["cvar"] == {"theta": [best.theta_0, best.theta_1], "value": best.cvar}
    assert yaml.safe_load((out / ".hydra" / "config.yaml").read_text())["seed"] == 4
    assert json.loads((out / "status.json").read_text())["status"] == "done"
    # reproducible: the same command gives the same table
    again = tmp_path / "again"
    runner.invoke(app, [*LANDSCAPE_COMMAND, "--out", str(again)])
    pd.testing.assert_frame_equal(pd.read_parquet(again / "landscape.parquet"), table)

    collected = collect([out])
    assert (
        len(collected.landscapes) == 1 and not collected.runs and not collected.broken
    )  # not mistaken for a broken run
    report = tmp_path / "report"
    result = runner.invoke(app, ["report", str(out), "--out", str(report), "--format", "png"])
    assert result.exit_code == 0, result.output
    assert (report / "landscape.png").is_file() and "0 skipped" in result.output
    runs = pd.read_csv(report / "runs.csv")
    assert list(runs.status) == ["landscape"]


@pytest.mark.parametrize(
    "args",
    [
        ["--range=5,1"],
        ["--range=1,2,3"],
        ["--range=-1e308,1e308"],  # its step overflows: theta NaN at the grid's points
        ["--range=0,1e308"],  # a theta whose logits overflow, which riskplan train refuses
        ["--axes", "0,0"],
        ["--axes", "0,2"],
        ["--points", "1"],
        ["--episodes", "0"],
        ["risk.beta=2"],
        ["no_such_key=1"],
    ],
)
@pytest.mark.slow  # 10 commands through the CLI
def test_bad_input_exits_2_and_leaves_nothing(tmp_path, args):
    out = tmp_path / "scan"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # the CLI prints a warning as a line of its own
        result = runner.invoke(app, ["landscape", *FAST, *args, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: ") and "Traceback" not in result.output
    assert not out.exists()


def test_broken_landscape_is_listed_not_fatal(tmp_path, setup):
    out = tmp_path / "scan"
    L.compute_landscape(riskplan.compose(FAST), out, points=3, episodes=50)
    (out / "landscape.parquet").unlink()
    collected = collect([tmp_path])
    assert not collected.landscapes and len(collected.broken) == 1 and "landscape" in collected.broken[0].reason


def test_paper_world_optima_sit_where_the_paper_policies_end():
    """Coarse (9 x 9, 2000 episodes) but on the paper's world: CVaR peaks with a strong weight on the safe source
    and none on the risky one (trained CVaR theta ends near (46.5, -0.7)); the mean peaks towards the risky source
    (risk-neutral theta near (-8, 35)); theta0 = 0 sits in the lower 'wander' plateau (no source reached)."""
    setup = build_setup(riskplan.compose([]))
    thetas = L.grid_thetas(setup.theta0, (0, 1), ((-20.0, 60.0), (-20.0, 60.0)), 9)
    table = L.evaluate_grid(setup, thetas, 2000, 0.1, seed=0)
    best_cvar = table.loc[table.cvar.idxmax()]
    assert best_cvar.theta_0 >= 40 and best_cvar.theta_1 <= 0
    near_trained = table.loc[(table.theta_0 == 50) & (table.theta_1 == 0)].iloc[0]
    assert near_trained.cvar > best_cvar.cvar - 5 * best_cvar.cvar_se  # the trained theta is on the optimum
    best_mean = table.loc[table["mean"].idxmax()]
    assert best_mean.theta_1 >= 30 and best_mean.theta_0 <= 0 and best_mean.reached_risky > 0.9
    origin = table.loc[(table.theta_0 == 0) & (table.theta_1 == 0)].iloc[0]
    assert origin.reached_none > 0.95 and origin.cvar < best_cvar.cvar - 400
