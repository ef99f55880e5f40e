"""The report's handling of the studies beyond the paper, without training: the labels of the new risk measures,
policies and faults, the paper pair that stays CVaR's, the study folders of riskplan reproduce, and the floor and
disagreement of a team computed on synthetic metrics with known answers. The studies' tables on real runs are in
test_study_tables.py."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from riskplan.experiments.reporting.collect import (
    STUDIES,
    RunInfo,
    flatten,
    group_runs,
    paper_pair,
    study_folders,
    study_of,
)
from riskplan.experiments.reporting.figures import risk_name
from riskplan.experiments.reporting.labels import measure_name
from riskplan.experiments.reporting.study_tables import (
    consensus_floor,
    fault_groups,
    hetero_groups,
    measure_groups,
    policy_groups,
    theta_disagreement,
)
from riskplan.experiments.reporting.tables import theta_text
from riskplan.experiments.reproduction import experiment_jobs
from riskplan.experiments.study_registry import EXPERIMENTS, STUDY_SEEDS


def fake_run(config: dict, seed: int = 0, metrics: pd.DataFrame | None = None) -> RunInfo:
    """A RunInfo over an in-memory run: its config, and metrics when a test needs them (no files)."""
    config = {"seed": seed, **config}
    run = SimpleNamespace(
        path=Path(f"/runs/{len(str(config))}_{seed}"),
        config=config,
        summary={},
        metrics=metrics if metrics is not None else pd.DataFrame(),
    )
    flat = {k: v for k, v in flatten(config).items() if k != "seed"}
    return RunInfo(run, flat, rebuilt=False)


def risk(measure: str, **values) -> dict:
    return {"risk": {"measure": measure, "beta": 0.1, "eta": 0.5, "weight": 0.5, **values}}


def labels(configs: list[dict]) -> dict[str, str]:
    """{measure: label} of the groups of these configs (one run each)."""
    groups, _ = group_runs([fake_run(c) for c in configs])
    return {g.measure: g.label for g in groups}


# ------------------------------------------------------------------------------------------------ labels
def test_the_new_measures_are_labelled_by_their_measure_and_parameters():
    found = labels(
        [
            risk("cvar"),
            risk("neutral"),
            risk("wang"),
            risk("mean_cvar", weight=0.25),
            risk("entropic", eta=0.001),
        ]
    )
    assert found == {
        "cvar": "risk-averse (CVaR β=0.1)",
        "neutral": "risk-neutral",
        "wang": "Wang (η=0.5)",
        "mean_cvar": "mean-CVaR (λ=0.25, β=0.1)",
        "entropic": "entropic (η=0.001)",
    }
    assert not any("risk-averse (CVaR" in found[m] for m in ("wang", "mean_cvar", "entropic"))


def test_a_lone_group_and_the_figures_name_the_measure():
    (group,), _ = group_runs([fake_run(risk("wang", eta=0.75))])
    assert group.label == "Wang (η=0.75), centralized"
    assert risk_name(group) == measure_name(group) == "Wang (η=0.75)"
    (cvar,), _ = group_runs([fake_run(risk("cvar", beta=0.2))])
    assert risk_name(cvar) == "risk-averse (CVaR β=0.2)"  # Figs. 1-2's legend, unchanged


def test_wang_groups_that_differ_only_in_eta_are_told_apart_by_it():
    found = [g.label for g in group_runs([fake_run(risk("wang", eta=e)) for e in (0.25, 1.0)])[0]]
    assert sorted(found) == ["Wang (η=0.25)", "Wang (η=1)"]


def test_the_paper_pair_stays_cvars_beside_other_measures():
    groups, _ = group_runs([fake_run(risk(m)) for m in ("neutral", "wang", "cvar", "entropic")])
    neutral, averse = paper_pair(groups)
    assert (neutral.measure, averse.measure) == ("neutral", "cvar")
    groups, _ = group_runs([fake_run(risk(m)) for m in ("neutral", "wang")])
    assert paper_pair(groups)[1].measure == "wang"  # no CVaR group: the other measure stands in


def test_policies_and_faults_are_labelled_by_what_they_are():
    policies = [
        {"policy": {"kind": "features", "features": ["signals"]}},
        {"policy": {"kind": "features", "features": ["signals", "risky"]}},
        {"policy": {"kind": "tabular", "features": ["signals"]}},
    ]
    groups, _ = group_runs([fake_run(c) for c in policies])
    assert sorted(g.label for g in groups) == ["features=[signals, risky]", "features=[signals]", "tabular policy"]
    byzantine = [{"robot": 6, "kind": "byzantine", "from": 0, "value": [-10, 40]}]
    teams = [
        {"team": {"robots": 7, "faults": [], "aggregate": "mean", "trim": 0}},
        {"team": {"robots": 7, "faults": byzantine, "aggregate": "mean", "trim": 1}},
        {"team": {"robots": 7, "faults": byzantine, "aggregate": "trimmed_mean", "trim": 1}},
    ]
    groups, _ = group_runs([fake_run(c) for c in teams])
    assert sorted(g.label for g in groups) == [
        "fault-free, mean",
        "robot 6 byzantine, mean",
        "robot 6 byzantine, trimmed_mean F=1",
    ]
    faulty, free = fault_groups(SimpleNamespace(groups=groups))
    assert [g.label for g in faulty] == ["robot 6 byzantine, mean", "robot 6 byzantine, trimmed_mean F=1"]
    assert free.label == "fault-free, mean"


def test_teams_of_their_own_measures_are_labelled_by_them_not_by_the_reported_one():
    """Groups that differed in team.risk alone were labelled by its JSON cut at 40 characters."""
    cvar, wang = {"measure": "cvar", "beta": 0.2}, {"measure": "wang", "eta": 0.5}
    teams = [
        {"team": {"robots": 3, "risk": [cvar, cvar, wang]}, **risk("cvar")},
        {"team": {"robots": 3, "risk": [wang, cvar, cvar]}, **risk("cvar")},
        {"team": {"robots": 3, "risk": None}, **risk("cvar")},
    ]
    groups, _ = group_runs([fake_run(c) for c in teams])
    assert sorted(g.label for g in groups) == [
        "one measure for all: risk-averse (CVaR β=0.1)",
        "own measures: Wang (η=0.5) | risk-averse (CVaR β=0.2) ×2",
        "own measures: risk-averse (CVaR β=0.2) ×2 | Wang (η=0.5)",
    ]
    (lone,), _ = group_runs([fake_run(teams[0])])
    assert lone.label.endswith(", own measures: risk-averse (CVaR β=0.2) ×2 | Wang (η=0.5)")


def test_a_tabular_theta_is_summarised_in_the_runs_table():
    assert theta_text([46.4676, -0.45859]) == "46.468 -0.459"
    assert theta_text([float(v) for v in range(720)]) == "720 values in [0.000, 719.000]"


# ------------------------------------------------------------------------------------------------ which groups
def test_each_study_picks_only_its_own_comparison():
    paper = [fake_run(risk(m)) for m in ("neutral", "cvar")] + [fake_run(risk("cvar", beta=b)) for b in (0.05, 0.5)]
    groups, _ = group_runs(paper)
    collected = SimpleNamespace(groups=groups)
    assert measure_groups(collected) == [] and policy_groups(collected) == []  # the paper's runs hold no study
    assert hetero_groups(collected) == ([], None) and fault_groups(collected) == ([], None)
    groups, _ = group_runs(paper + [fake_run(risk("wang")), fake_run({**risk("wang"), "train": {"theta0": [0, 0]}})])
    picked = measure_groups(SimpleNamespace(groups=groups))
    assert [g.measure for g in picked] == ["cvar", "cvar", "cvar", "neutral", "wang"]  # θ0 = 0's is another world


def test_study_folders_are_found_directly_inside_an_input(tmp_path):
    for folder in ("single", "measures", "tabular", "faults_free"):
        (tmp_path / folder / "seed=0").mkdir(parents=True)
    folders = study_folders([tmp_path])
    assert set(folders.values()) == {"measures", "policies", "faults"}
    assert study_of(tmp_path / "tabular" / "seed=0", folders) == "policies"
    assert study_of(tmp_path / "single" / "seed=0", folders) is None
    assert study_folders([tmp_path / "measures"]) == {}  # a study folder given itself is a plain input


def test_reproduce_runs_every_study_folder_the_report_knows():
    folders = [folder for folder, *_ in EXPERIMENTS]
    studied = [f for _, names in STUDIES.values() for f in names]
    assert folders[5:] == studied  # after the paper's five sweeps, in the report's order
    assert all(most == STUDY_SEEDS == 5 for folder, _, _, most in EXPERIMENTS if folder in studied)
    assert experiment_jobs(10)[5:] == [25, 10, 5, 10, 5, 10, 5, 10]  # full: 5 seeds of each condition
    assert experiment_jobs(2)[5:] == [10, 4, 2, 4, 2, 4, 2, 4]  # --quick: 2 seeds


# ------------------------------------------------------------------------------------------------ known answers
def team_metrics(offsets: list[tuple[float, float]], noise: float, iterations: int = 40) -> pd.DataFrame:
    """Metrics of a team whose robot i holds theta = (10, 20) + offsets[i] + alternating noise of size `noise`
    (it averages out over any even number of iterations), and a robot -1 row with the consensus error l."""
    rows = []
    for l in range(iterations):
        sign = 1.0 if l % 2 == 0 else -1.0
        thetas = [np.array([10.0, 20.0]) + o + sign * noise * (i + 1) for i, o in enumerate(offsets)]
        for i, theta in enumerate(thetas):
            rows.append({"iteration": l, "robot": i, "healthy": True, "theta_0": theta[0], "theta_1": theta[1]})
        average = np.mean(thetas, axis=0)
        rows.append(
            {"iteration": l, "robot": -1, "healthy": True, "theta_0": average[0], "theta_1": average[1],
             "consensus_error": float(l)}
        )  # fmt: skip
    return pd.DataFrame(rows)


def test_the_floor_and_the_persistent_disagreement_have_known_values():
    offsets = [(0.0, 0.0), (3.0, 4.0), (-0.3, -0.4)]
    run = fake_run({"team": {"robots": 3}}, metrics=team_metrics(offsets, noise=0.5))
    run.run.summary = {"headline_robot": -1}
    assert consensus_floor(run) == pytest.approx(np.mean(range(30, 40)))  # the last quarter: iterations 30-39
    # the noise alternates and averages out over the 10 iterations; the offsets persist: |(3, 4) - (-0.3, -0.4)|
    assert theta_disagreement(run) == pytest.approx(5.5)
    still = fake_run({"team": {"robots": 3}}, metrics=team_metrics([(0.0, 0.0)] * 3, noise=2.0))
    assert theta_disagreement(still) == pytest.approx(0.0, abs=1e-12)


def test_a_faulty_robot_is_left_out_of_the_disagreement():
    metrics = team_metrics([(0.0, 0.0), (0.0, 0.0), (30.0, 40.0)], noise=0.0)
    metrics.loc[metrics.robot == 2, "healthy"] = False
    run = fake_run({"team": {"robots": 3}}, metrics=metrics)
    assert theta_disagreement(run) == pytest.approx(0.0, abs=1e-12)
    metrics.loc[metrics.robot == 2, "healthy"] = True
    assert math.isclose(theta_disagreement(fake_run({"team": {"robots": 3}}, metrics=metrics)), 50.0)


def test_groups_whose_values_differ_past_what_a_label_shows_are_told_apart_by_where_they_differ():
    """world.sources differing only in the second source's name: its JSON, cut at 40 characters, was the same in
    both labels, which then ended '#2'. Each label now shows the value where the groups' values first differ."""
    sources = [{"name": "north", "position": [3, 4], "mean": 100.0}, {"name": "b", "position": [9, 9], "mean": 50.0}]
    renamed = [sources[0], {**sources[1], "name": "c"}]
    groups, _ = group_runs([fake_run({"world": {"sources": s}}) for s in (sources, renamed)])
    labels = sorted(g.label for g in groups)
    assert len(set(labels)) == 2 and not any("#" in label for label in labels), labels
    assert '"name": "b"' in labels[0] and '"name": "c"' in labels[1], labels
