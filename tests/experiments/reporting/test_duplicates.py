"""One sample per distinct run: a run whose config and seed repeat another's (`run_identity`: the resolved config
without its output paths, seed included) is counted once by the report, with one warning, and listed in runs.csv as
`duplicate`; the sweep summary names such a job in `duplicate_of`. (The export: tests/experiments/test_exporting.py.)

The runs are real and tiny: the same config and seed trained through the Python API and through the CLI into two
directories, a copy of a run directory, and the same config with another seed."""

from __future__ import annotations

import io
import shutil
import warnings
from pathlib import Path

import pandas as pd
import pytest
import yaml
from support import TINY, run_cli, stand_in_job
from typer.testing import CliRunner

import riskplan
from riskplan.cli import app
from riskplan.experiments.reporting import build_report
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.sweep_worker import run_identity
from riskplan.experiments.sweeping.jobs import Job, Outcome
from riskplan.experiments.sweeping.summary import report_outcome, summarize

pytestmark = pytest.mark.slow  # three tiny runs (one through the CLI) and reports drawn from them

runner = CliRunner()
REPEAT = "1 run repeats another run's config and seed (the same sample); each is counted once"


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """api/ (Python API) and cli/ (riskplan train): the same config and seed; copy/: a copy of api/; seed_1/: the
    same config with seed=1."""
    root = tmp_path_factory.mktemp("duplicates")
    riskplan.train(riskplan.compose(TINY), root / "api")
    result = runner.invoke(app, ["train", *TINY, f"hydra.run.dir={root / 'cli'}"])
    assert result.exit_code == 0, result.output
    shutil.copytree(root / "api", root / "copy")
    riskplan.train(riskplan.compose([*TINY, "seed=1"]), root / "seed_1")
    return root


def config(run: Path) -> dict:
    return yaml.safe_load((run / ".hydra" / "config.yaml").read_text())


def report(paths: list[Path], out: Path) -> tuple[pd.DataFrame, pd.DataFrame, list[str]]:
    """report.csv, runs.csv and the warnings the report gave."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_report(paths, out, ["png"])
    return pd.read_csv(out / "report.csv"), pd.read_csv(out / "runs.csv"), [str(w.message) for w in caught]


def test_the_identity_is_the_config_and_seed_wherever_the_run_was_written(runs):
    base = {"seed": 0, "risk": {"beta": 0.1}}
    assert run_identity({**base, "hydra": {"run": {"dir": "outputs/runs/a"}}}) == run_identity(
        {**base, "hydra": {"run": {"dir": "elsewhere"}, "sweep": {"dir": "x", "subdir": "y"}}}
    )
    assert run_identity(base) != run_identity({**base, "seed": 1})
    assert run_identity(base) != run_identity({**base, "risk": {"beta": 0.2}})
    # the CLI's config and the Python API's, for the same overrides: one identity; another seed: another one
    assert run_identity(config(runs / "api")) == run_identity(config(runs / "cli"))
    assert run_identity(config(runs / "api")) != run_identity(config(runs / "seed_1"))


def test_the_same_config_and_seed_twice_is_one_seed_with_one_warning(runs, tmp_path):
    table, listed, caught = report([runs / "api", runs / "cli"], tmp_path / "report")
    assert len(table) == 1
    assert table.seeds.tolist() == [1] and table.seed_list.astype(str).tolist() == ["0"]
    assert table.interval.tolist() == ["95% bootstrap over episodes (Wilson for proportions)"]  # not over 2 seeds
    assert listed.status.tolist() == ["used", "duplicate"]
    duplicate = listed.iloc[1]
    assert duplicate.path == str(runs / "cli") and duplicate.seed == 0 and duplicate.group == listed.group[0]
    assert duplicate.note == f"the same config and seed as {runs / 'api'}: one sample, counted once"
    assert caught == [f"{REPEAT} (runs.csv lists them as duplicate)"]
    # the one that is used is the first by path, whichever order the inputs are given in
    _, again, _ = report([runs / "cli", runs / "api"], tmp_path / "again")
    assert again.loc[again.status == "used", "path"].tolist() == [str(runs / "api")]


def test_the_same_numbers_as_the_run_alone(runs, tmp_path):
    alone, _, caught = report([runs / "api"], tmp_path / "alone")
    twice, _, _ = report([runs / "api", runs / "copy"], tmp_path / "twice")
    assert caught == []
    pd.testing.assert_frame_equal(alone, twice)


def test_another_seed_is_not_a_duplicate_and_a_copy_is(runs, tmp_path):
    table, listed, caught = report([runs], tmp_path / "all")
    assert table.seeds.tolist() == [2] and table.seed_list.tolist() == ["0 1"]
    assert table.interval.tolist() == ["95% Student-t over 2 seeds"]
    status = dict(zip(listed.path, listed.status))
    assert status == {
        str(runs / "api"): "used",
        str(runs / "seed_1"): "used",
        str(runs / "cli"): "duplicate",
        str(runs / "copy"): "duplicate",
    }
    assert caught == [
        "2 runs repeat another run's config and seed (the same sample); each is counted once (runs.csv lists them "
        "as duplicate)"
    ]
    collected = collect([runs])
    assert [g.seeds for g in collected.groups] == [[0, 1]]
    assert {(d.path.name, d.of.path.name) for d in collected.duplicates} == {("cli", "api"), ("copy", "api")}


def test_a_study_repeating_a_paper_run_uses_it_too(runs, tmp_path):
    """reproduce's study folders are pooled apart from the paper's runs: a repeat across the two is no duplicate."""
    shutil.copytree(runs / "api", tmp_path / "single" / "cvar,seed=0")
    shutil.copytree(runs / "api", tmp_path / "measures" / "cvar,seed=0")
    shutil.copytree(runs / "api", tmp_path / "measures" / "cvar,seed=0,again")  # within the study: a duplicate
    collected = collect([tmp_path])
    assert [r.path for r in collected.runs] == [tmp_path / "single" / "cvar,seed=0"]
    assert [[r.path for r in s.collection.runs] for s in collected.studies] == [[tmp_path / "measures" / "cvar,seed=0"]]
    assert [(d.path, d.of.path) for d in collected.duplicates] == [
        (tmp_path / "measures" / "cvar,seed=0,again", tmp_path / "measures" / "cvar,seed=0")
    ]


def test_the_command_prints_one_warning_line(runs, tmp_path):
    result = run_cli(["report", str(runs / "api"), str(runs / "cli"), "--out", str(tmp_path / "out")], tmp_path)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if "repeat" in line]
    assert lines == [f"warning: {REPEAT} (runs.csv lists them as duplicate)"], result.stderr
    assert "1 run(s) in 1 group(s), 0 landscape(s), 0 skipped, 1 duplicate (counted once);" in result.stdout


# ------------------------------------------------------------------------------------------------ the sweep summary
def finished_job(root: Path, number: int, sha: str, status: str = "done") -> Job:
    """Job `trial_<number>`, whose status.json says `status` for config `sha`, with every output file."""
    path = root / f"trial_{number}"
    stand_in_job(path, {"status": status, "config_sha": sha, "error": None if status == "done" else "boom"})
    return Job([f"risk.beta=0.{number + 1}"], sha, path=path, label=path.name)


def names(column: pd.Series) -> list[str | None]:
    """A text column's values, a missing one as None (pandas may hold it as NaN)."""
    return [v if isinstance(v, str) else None for v in column]


def test_the_sweep_summary_names_the_job_a_job_repeats(tmp_path, capsys):
    jobs = [
        finished_job(tmp_path, 0, "aaaa"),
        finished_job(tmp_path, 1, "bbbb"),
        finished_job(tmp_path, 2, "aaaa"),  # drew trial_0's values again: the same sample
        finished_job(tmp_path, 3, "bbbb", status="failed"),  # no sample at all
    ]
    frame = summarize(jobs)
    assert frame.status.tolist() == ["done", "done", "done", "failed"]
    assert names(frame.duplicate_of) == [None, None, "trial_0", None]
    buffer = io.BytesIO()
    frame.to_parquet(buffer, index=False)  # as summary.parquet holds it
    assert names(pd.read_parquet(buffer).duplicate_of) == [None, None, "trial_0", None]

    outcome = Outcome(tmp_path, frame.iloc[:3], [], 3, 0, 1.0, optimiser=True)
    assert report_outcome(outcome) == 0  # a repeat is not a failure
    out, err = capsys.readouterr()
    assert err.splitlines() == [
        "warning: 1 trial repeats another trial's config and seed (the same sample); each is counted once "
        "(summary.parquet names the trial each repeats in duplicate_of)"
    ]
    assert "duplicate" in out  # the table's status cell

    assert report_outcome(Outcome(tmp_path, frame.iloc[:2], [], 2, 0, 1.0)) == 0
    assert capsys.readouterr().err == ""
