"""`riskplan sweep hydra/sweeper=optuna ...`: an optimising Hydra sweeper through the real command line.

The trials are not known before the sweep runs, so riskplan checks the search space instead, runs each trial as a
sweep job (skip, resume, lock, own folder), and writes summary.parquet with one row per trial. A trial the model
rejects fails alone: it returns None, which optuna records as a failed trial, and the study goes on.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd
import pytest
import yaml
from support import TINY, riskplan_cli
from typer.testing import CliRunner

from riskplan.cli import app

pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="the optuna extra is not installed")

pytestmark = pytest.mark.slow
runner = CliRunner()

# 4 trials over beta, with train.iterations=0 (which the model rejects) in some of them: seed 1 draws 0, 0, 3, 3
STUDY = [
    "hydra/sweeper=optuna",
    "risk.beta=interval(0.05,1)",
    "train.iterations=choice(0,3)",
    "hydra.sweeper.n_trials=4",
    "hydra.sweeper.sampler.seed=1",
    *(o for o in TINY if not o.startswith("train.iterations=")),  # the study chooses train.iterations
]


def riskplan(cwd: Path, *args: str):
    return riskplan_cli(cwd, *args, env={"COLUMNS": "250"})


def test_an_optuna_study_runs_isolates_failed_trials_and_resumes(tmp_path):
    first = riskplan(tmp_path, "sweep", *STUDY)
    assert first.returncode == 1, first.stdout + first.stderr  # some trials failed
    assert "4 trials chosen by hydra/sweeper=optuna over risk.beta, train.iterations" in first.stdout
    # the search space was checked with samples: the rejected value is a warning, not bad input
    assert re.search(r"^warning: train\.iterations: got 0; .* trials there will fail alone$", first.stderr, re.M)
    sweep = tmp_path / re.search(r"^sweep directory: (.+)$", first.stdout, re.M).group(1)

    summary = pd.read_parquet(sweep / "summary.parquet")
    assert list(summary.trial) == [0, 1, 2, 3]  # one row per trial, in the sweeper's order
    assert summary["risk.beta"].between(0.05, 1).all() and summary["risk.beta"].nunique() == 4
    assert set(summary["train.iterations"]) == {0, 3}
    failed, done = summary[summary["train.iterations"] == 0], summary[summary["train.iterations"] == 3]
    assert (failed.status == "failed").all() and (done.status == "done").all()
    assert failed.error.str.startswith("train.iterations: got 0; expected a whole number >= 1").all()
    assert failed.cvar.isna().all() and done.cvar.notna().all()
    for name in ("reached_safe", "reached_risky", "reached_none"):
        assert done[name].between(0, 1).all()
    assert (done[["reached_safe", "reached_risky", "reached_none"]].sum(axis=1) - 1).abs().max() < 1e-9
    for row in summary.itertuples():
        folder = tmp_path / row.path
        assert folder.parent == sweep and folder.name.startswith(f"trial_{row.trial:03d},risk.beta=")
        status = json.loads((folder / "status.json").read_text())
        assert status["status"] == row.status
        if row.status == "done":
            assert json.loads((folder / "summary.json").read_text())["cvar"]["value"] == row.cvar

    # optuna saw the CVaR of the trials that ran and a failure (None) for the others; it maximised by default
    log = (sweep / "sweep.log").read_text()
    assert "Directions: ['maximize']" in log
    assert log.count("Failed experiment: Return value must be float-castable. Got 'None'") == len(failed)
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(done.cvar.max())
    assert "best trial: " in first.stdout and "2 of 4 trials did not finish" in first.stderr

    # the same seeded study again in its directory: the finished trials are skipped, the failed ones run again
    stamps = {p: (tmp_path / p / "run.mcap").stat().st_mtime_ns for p in done.path}
    again = riskplan(tmp_path, "sweep", *STUDY, f"hydra.sweep.dir={sweep}")
    assert again.returncode == 1, again.stderr
    assert "(2 launched, 2 skipped," in again.stdout
    assert {p: (tmp_path / p / "run.mcap").stat().st_mtime_ns for p in done.path} == stamps
    second = pd.read_parquet(sweep / "summary.parquet")
    assert list(second.status) == list(summary.status) and list(second["risk.beta"]) == list(summary["risk.beta"])


def test_bad_search_spaces_write_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("COLUMNS", "250")
    for args, expected in [
        (["risk.beta=interval(0.05,1)"], "interval(...) is a search space for an optimising sweeper"),
        (["hydra/sweeper=optuna", "risk=glob(*)"], "the optuna sweeper takes choice(...)"),
        (["hydra/sweeper=optuna", "train.iterations=interval(1.5,4.5)"], "composed with the sample value 3.0"),
        (["hydra/sweeper=optuna", "risk.beta=interval(0.1,1)", "train.iterations=0"], "(in every trial; nothing"),
    ]:
        result = runner.invoke(app, ["sweep", *args])  # in this process: bad input needs no start-up of its own
        assert result.exit_code == 2 and expected in result.stderr, (args, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []
