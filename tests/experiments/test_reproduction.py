"""`riskplan reproduce`'s plan (riskplan.experiments.reproduction): how many jobs each of its sweeps holds, counted
from the overrides, and the job limit checked before anything runs. The whole reproduction runs in
tests/e2e/test_reproduce.py."""

from __future__ import annotations

import json

import pytest

from riskplan.experiments.reproduction import EXPERIMENTS, check_reproduction_dir, check_seeds, experiment_jobs
from riskplan.util.errors import BadInput

PAPER = ["single", "team", "wander", "soft_risk", "frontier"]
STUDIES = ["measures", "policies", "tabular", "hetero_team", "hetero_central", "faults", "faults_free", "floor_plan"]


def test_each_sweep_holds_its_conditions_times_its_seeds():
    assert [folder for folder, *_ in EXPERIMENTS] == PAPER + STUDIES
    # risk=neutral,cvar; one team; wander and soft risk at most 2 seeds; four betas of the frontier at most 2 seeds;
    # then the studies beyond the paper, at most 5 seeds: five measures, two feature sets, tabular, two orders,
    # the centralized team, two aggregations, the fault-free team, the floor plan's two measures
    assert experiment_jobs(1) == [2, 1, 1, 1, 4] + [5, 2, 1, 2, 1, 2, 1, 2]
    assert experiment_jobs(10) == [20, 10, 2, 2, 8] + [25, 10, 5, 10, 5, 10, 5, 10]
    assert check_seeds(1) == 9 + 16


def test_more_jobs_than_the_limit_is_bad_input(monkeypatch):
    monkeypatch.setenv("RISKPLAN_MAX_JOBS", "50")
    assert check_seeds(2) == 18 + 32
    with pytest.raises(BadInput) as err:
        check_seeds(3)
    assert err.value.where == "--seeds" and "69 jobs, more than the 50 allowed" in err.value.problem


def test_a_reproduction_is_completed_only_with_the_settings_it_started_with(tmp_path):
    """Other settings were found by the first sweep, after the plan, and the line said to give a new
    hydra.sweep.dir (reproduce has --out)."""
    out = tmp_path / "r"
    out.mkdir()
    (out / "reproduce.json").write_text(json.dumps({"quick": True, "overrides": ["train.samples=300"]}))
    check_reproduction_dir(out, True, ["train.samples=300"])  # the same: it completes
    for quick, overrides in ((False, ["train.samples=300"]), (True, []), (True, ["train.samples=400"])):
        with pytest.raises(BadInput) as err:
            check_reproduction_dir(out, quick, overrides)
        assert err.value.where == "--out" and err.value.problem == (
            f"{out} holds a reproduction started with other settings (--quick train.samples=300); give a new --out, "
            f"or those settings to complete it"
        )
