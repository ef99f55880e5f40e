"""The studies beyond the paper on tiny real runs laid out as riskplan reproduce lays them out (study folders beside
the paper's): each study's table equals the numbers recomputed from the runs' own tables (eval.parquet,
metrics.parquet, summary.json, the landscape), its figure is drawn, its CSV and section are in the report, and the
paper's figures and report.csv do not change when the study folders are added."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY

from riskplan import compose, train
from riskplan.config.validate import IgnoredKey
from riskplan.experiments.landscape import compute_landscape
from riskplan.experiments.reporting import write_report
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.reporting.figures import make_figures
from riskplan.experiments.reporting.stats import seed_interval
from riskplan.experiments.reporting.study_tables import faults_table, hetero_table, measures_table, policies_table
from riskplan.risk import cvar, objective

pytestmark = pytest.mark.slow  # about 35 tiny runs, a small landscape and three reports

SEEDS = (0, 1)
BYZANTINE = "team.faults=[{robot:4,kind:byzantine,from:0,value:[-10,40]}]"
STARTS = "team.starts=[[0,0],[11,0],[11,11],[0,11]]"
HETERO = ["experiment=paper_team", "team.robots=4", STARTS, "train.step_size.power=0", "train.step_size.initial=0.05"]
FAULTY = ["experiment=paper_team", "team.robots=5", "team.graph=complete"]
# folder -> condition -> overrides, as reproduce's sweeps (with TINY, 2 seeds each); the paper's pair in single/
LAYOUT = {
    "single": {"neutral": ["risk=neutral"], "cvar": []},
    "measures": {m: [f"risk={m}"] for m in ("cvar", "neutral", "wang", "mean_cvar", "entropic")},
    "policies": {
        "signals": ["train.theta0=[0,0]"],
        "risky": ["train.theta0=[0,0]", "policy.features=[signals,risky]"],
    },
    "tabular": {"tabular": ["train.theta0=[0,0]", "policy.kind=tabular"]},
    "hetero_team": {
        "gradient_tracking": [*HETERO, "team.graph=ring", "team.order=gradient_tracking"],
        "combine_then_adapt": [*HETERO, "team.graph=ring", "team.order=combine_then_adapt"],
    },
    "hetero_central": {
        "central": [*HETERO, "team.graph=complete", "team.weights=max_degree", "team.order=adapt_then_combine"]
    },
    "faults": {
        "mean": [*FAULTY, BYZANTINE, "team.aggregate=mean", "team.trim=1"],
        "trimmed_mean": [*FAULTY, BYZANTINE, "team.aggregate=trimmed_mean", "team.trim=1"],
    },
    "faults_free": {"free": FAULTY},
}


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A reproduction-like directory of tiny runs, and the paper world's landscape."""
    out = tmp_path_factory.mktemp("studies")
    with pytest.warns(UserWarning, match="Assumption 6"), warnings.catch_warnings():  # hetero's constant step
        warnings.simplefilter("ignore", IgnoredKey)  # the faults study's mean runs carry the sweep's team.trim=1
        for folder, conditions in LAYOUT.items():
            for name, overrides in conditions.items():
                for seed in SEEDS:
                    train(compose([*TINY, *overrides, f"seed={seed}"]), out / folder / f"{name},seed={seed}")
    compute_landscape(compose(TINY), out / "landscape", points=5, episodes=200, ranges=((-20.0, 60.0), (-20.0, 60.0)))
    return out


@pytest.fixture(scope="module")
def collected(root):
    return collect([root])


def runs_of(root: Path, folder: str, name: str) -> list[Path]:
    return [root / folder / f"{name},seed={s}" for s in SEEDS]


def eval_rewards(run: Path, robot: int) -> np.ndarray:
    e = pd.read_parquet(run / "eval.parquet")
    return e.loc[e.robot == robot].total_reward.to_numpy().copy()  # writable, as training's (one numba signature)


def study(collected, name: str):
    (found,) = [s for s in collected.studies if s.name == name]
    return found.collection


def row_of(table: pd.DataFrame, column: str, value) -> pd.Series:
    (index,) = table.index[table[column] == value]
    return table.loc[index]


def test_the_study_folders_are_collected_apart_from_the_papers_runs(collected):
    assert sorted(s.name for s in collected.studies) == ["faults", "hetero_team", "measures", "policies"]
    assert [g.measure for g in collected.groups] == ["neutral", "cvar"] and len(collected.runs) == 4  # single/ only
    assert {g.label for g in study(collected, "measures").groups} >= {"Wang (η=0.5)", "entropic (η=0.001)"}
    assert collected.landscapes and study(collected, "policies").landscapes == collected.landscapes


def test_the_measures_table_is_recomputed_from_the_evaluation_episodes(root, collected):
    table = measures_table(study(collected, "measures"))
    assert table.measure.tolist() == ["cvar", "neutral", "wang", "mean_cvar", "entropic"]
    for measure, risk in (
        ("wang", {"measure": "wang", "eta": 0.5}),
        ("entropic", {"measure": "entropic", "eta": 0.001}),
        ("mean_cvar", {"measure": "mean_cvar", "beta": 0.1, "weight": 0.5}),
    ):
        row = row_of(table, "measure", measure)
        z = [eval_rewards(run, 0) for run in runs_of(root, "measures", measure)]
        values = [objective(x, risk) for x in z]
        assert (row.objective, row.objective_low, row.objective_high) == pytest.approx(seed_interval(values))
        assert row.cvar == pytest.approx(np.mean([cvar(x, 0.1) for x in z]), rel=1e-12)
        assert row["name"] == {"wang": "Wang (η=0.5)", "entropic": "entropic (η=0.001)"}.get(
            measure, "mean-CVaR (λ=0.5, β=0.1)"
        )
        # the trained objective is summary.json's, seed by seed
        own = [
            json.loads((run / "summary.json").read_text())["objective"]["value"]
            for run in runs_of(root, "measures", measure)
        ]
        assert values == pytest.approx(own, rel=1e-12)
    cvar_row = row_of(table, "measure", "cvar")
    assert cvar_row.objective == pytest.approx(cvar_row.cvar, rel=1e-12)  # CVaR's objective is its CVaR


def test_the_policies_table_holds_the_landscapes_best_cvar_and_the_gap(root, collected):
    table = policies_table(study(collected, "policies"))
    assert table.policy.tolist() == ["features=[signals]", "features=[signals, risky]", "tabular policy"]
    assert table.theta_length.tolist() == [2, 3, 720]
    best = pd.read_parquet(root / "landscape" / "landscape.parquet").cvar.max()
    assert table.landscape_best_cvar.tolist() == pytest.approx([best] * 3, rel=1e-12)
    for name, policy in (("signals", "features=[signals]"), ("risky", "features=[signals, risky]")):
        row = row_of(table, "policy", policy)
        z = [eval_rewards(run, 0) for run in runs_of(root, "policies", name)]
        assert row.cvar == pytest.approx(np.mean([cvar(x, 0.1) for x in z]), rel=1e-12)
        assert row.gap_to_landscape_best == pytest.approx(best - row.cvar, rel=1e-12)
        safe = sum(
            int((pd.read_parquet(run / "eval.parquet").source_reached == 0).mean() > 0.5)
            for run in runs_of(root, "policies", name)
        )
        assert row.seeds_reaching_safe == safe
    tabular = row_of(table, "kind", "tabular")
    assert tabular.theta_names == "720 (cell, move) logits" and tabular.theta0 == "[0.0, 0.0]"


def test_the_hetero_table_is_recomputed_from_metrics_and_summaries(root, collected):
    table = hetero_table(study(collected, "hetero_team"))
    assert table.order.tolist() == ["combine_then_adapt", "gradient_tracking", "adapt_then_combine"]
    assert table.centralized.tolist() == [False, False, True]
    assert table.constant_step.all() and table.step_size.tolist() == pytest.approx([0.05] * 3)
    central = {
        s: json.loads((r / "summary.json").read_text())
        for s, r in zip(SEEDS, runs_of(root, "hetero_central", "central"))
    }
    for order in ("combine_then_adapt", "gradient_tracking"):
        row = row_of(table, "order", order)
        floors, gaps, distances = [], [], []
        for seed, run in zip(SEEDS, runs_of(root, "hetero_team", order)):
            m = pd.read_parquet(run / "metrics.parquet")
            team = m[m.robot == -1].sort_values("iteration")
            floors.append(team.consensus_error.iloc[-1:].mean())  # 3 iterations: the last quarter is the last one
            summary = json.loads((run / "summary.json").read_text())
            assert summary["team_objective"]["value"] == pytest.approx(
                sum(r["objective_at_average"]["value"] for r in summary["robots"])
            )
            gaps.append(central[seed]["team_objective"]["value"] - summary["team_objective"]["value"])
            distances.append(np.linalg.norm(np.subtract(summary["theta_final"], central[seed]["theta_final"])))
        assert (row.consensus_floor, row.consensus_floor_low, row.consensus_floor_high) == pytest.approx(
            seed_interval(floors)
        )
        assert (row.gap_to_central, row.gap_to_central_low, row.gap_to_central_high) == pytest.approx(
            seed_interval(gaps)
        )
        assert row.distance_to_central == pytest.approx(np.mean(distances))
    centralized = row_of(table, "order", "adapt_then_combine")
    assert centralized.consensus_floor == 0.0 and centralized.theta_disagreement == 0.0  # the exact average


def test_the_faults_table_compares_each_seed_with_the_fault_free_run(root, collected):
    table = faults_table(study(collected, "faults"))
    assert table["name"].tolist() == [
        "robot 4 byzantine, mean",
        "robot 4 byzantine, trimmed_mean F=1",
        "fault-free, mean",
    ]
    free = [cvar(eval_rewards(run, -1), 0.1) for run in runs_of(root, "faults_free", "free")]
    for name in ("mean", "trimmed_mean"):
        row = row_of(table, "aggregate", name) if name == "trimmed_mean" else table.iloc[0]
        cvars = [cvar(eval_rewards(run, -1), 0.1) for run in runs_of(root, "faults", name)]
        relative = [(c - f) / abs(f) for c, f in zip(cvars, free)]
        assert row.cvar == pytest.approx(np.mean(cvars), rel=1e-12)
        assert row.cvar_vs_fault_free == pytest.approx(np.mean(relative), rel=1e-9)
        assert row.worst_cvar_vs_fault_free == pytest.approx(max(abs(x) for x in relative), rel=1e-9)
        assert row.within_tolerance == (max(abs(x) for x in relative) <= 0.05)
        assert row.faulty_robots == 1
    # the healthy robots' figures: eval's robot -1 rows are marked healthy, the byzantine robot's own are not
    e = pd.read_parquet(runs_of(root, "faults", "mean")[0] / "eval.parquet")
    assert e.loc[e.robot == -1, "healthy"].all() and not e.loc[e.robot == 4, "healthy"].any()


def test_every_study_figure_is_drawn_and_the_report_holds_the_studies(root, collected, tmp_path):
    specs, skipped = make_figures(collected)
    names = {s.name: s for s in specs}
    assert {"risk_measures", "richer_policies", "hetero_team", "faults"} <= set(names)
    assert not {"risk_measures", "richer_policies", "hetero_team", "faults"} & set(skipped)
    assert names["hetero_team"].study == "hetero_team" and names["fig2_cvar"].study == ""
    legend = [t.get_text() for t in names["risk_measures"].figure.legends[0].get_texts()]
    assert any(t.startswith("Wang (η=0.5)") for t in legend) and any(t.startswith("entropic") for t in legend)
    report = write_report([root], tmp_path / "report", ["png"])
    for name in ("measures", "policies", "hetero_team", "faults"):
        assert (tmp_path / "report" / f"{name}.csv").is_file()
    page = report.page.read_text()
    for heading in ("Risk measures", "Policies that see more", "A heterogeneous team", "A Byzantine robot"):
        assert f">{heading}" in page
    runs = pd.read_csv(tmp_path / "report" / "runs.csv")
    assert len(runs[runs.status == "used"]) == sum(len(c) for c in LAYOUT.values()) * len(SEEDS)
    assert (
        runs.loc[runs.group.str.startswith("policies: tabular", na=False), "theta_final"]
        .str.startswith("720 values")
        .all()
    )


def test_the_papers_figures_and_tables_do_not_change_with_the_studies_beside_them(root, tmp_path):
    paper = tmp_path / "paper"
    for folder in ("single", "landscape"):
        shutil.copytree(root / folder, paper / folder)
    alone = write_report([paper], tmp_path / "alone", ["png"])
    beside = write_report([root], tmp_path / "beside", ["png"])
    assert set(alone.figures) <= set(beside.figures)
    for name in alone.figures:
        assert (tmp_path / "alone" / f"{name}.png").read_bytes() == (
            tmp_path / "beside" / f"{name}.png"
        ).read_bytes(), name
    assert (tmp_path / "alone" / "report.csv").read_text() == (tmp_path / "beside" / "report.csv").read_text()
