"""`riskplan reproduce` through the real command line, shrunk with plain overrides so that it stays small; bad input
and sizes beyond the limits are refused before anything runs."""

from __future__ import annotations

import json
import os
import re
import signal

import pandas as pd
import pytest
from support import FAST, TINY, riskplan_cli
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.experiments import reproduction
from riskplan.experiments.bench_reproduce import read_reproduction
from riskplan.experiments.sweeping import batched

pytestmark = pytest.mark.slow
runner = CliRunner()


def test_reproduce_runs_section_v_through_sweeps_then_the_report(tmp_path):
    # risk.beta: a user's value for the paper set-ups must not clash with the frontier's own beta sweep
    # job by job (--jobs 2): its workers, warm-up and breakdown; the default, batched, is the paper-only test's
    result = riskplan_cli(
        tmp_path, "reproduce", "--quick", "--seeds", "1", "--jobs", "2", "--format", "png", *FAST, "risk.beta=0.1"
    )
    assert result.returncode == 0, result.stdout + result.stderr
    roots = list((tmp_path / "outputs" / "reproduce").iterdir())
    assert len(roots) == 1
    root = roots[0]
    single = pd.read_parquet(root / "single" / "summary.parquet")
    team = pd.read_parquet(root / "team" / "summary.parquet")
    assert sorted(single.risk) == ["cvar", "neutral"] and (single.status == "done").all()
    assert len(team) == 1 and team.status.iloc[0] == "done"
    config = (root / "team" / "seed=0" / ".hydra" / "config.yaml").read_text()
    assert "robots: 3" in config and "iterations: 5" in config  # the user's overrides beat --quick's
    assert (root / "single" / "multirun.yaml").is_file()
    record = json.loads((root / "reproduce.json").read_text())
    studies = {
        "measures",
        "policies",
        "tabular",
        "hetero_team",
        "hetero_central",
        "faults",
        "faults_free",
        "floor_plan",
    }
    assert (
        record["seeds"] == 1
        and record["quick"]
        and set(record["parts"])
        == {"single", "team", "wander", "soft_risk", "frontier", "landscape", "comparison", "report"} | studies
    )
    # said up front: the plan with its estimate, then each stage out of the total with the overall ETA
    assert re.search(r"plan: 15 stages, 25 jobs, on \d+ workers?; estimated time ", result.stdout)
    assert "[stage 1 of 15: single]" in result.stdout and "[stage 15 of 15: report]" in result.stdout
    assert set(record["estimate"]) == set(record["parts"]) - {"comparison"}
    assert "Assumption 6" not in result.stderr  # hetero_team's constant step is the study's own choice
    # where the time went: measured from the jobs' own records (no timed assertion, only the structure)
    assert "where the time went" in result.stdout
    # the closing totals are one number
    went = float(re.search(r"where the time went \(([0-9.]+) s", result.stdout).group(1))
    assert f"reproduced in {went:.1f} s " in result.stdout
    breakdown = record["breakdown"]
    # 2 + 1 + 1 + 1 + 4 jobs of the paper's set-ups, 5 + 2 + 1 + 2 + 1 + 2 + 1 + 2 of the studies beyond it
    assert breakdown["jobs"]["jobs"] == 9 + 16 and breakdown["jobs"]["workers"] >= 1
    assert all(v is None or v >= 0 for v in breakdown["wall"].values())
    assert breakdown["wall"]["report (figures, tables, page)"] > 0 and breakdown["total"] > 0
    assert breakdown["jobs"]["training loop (summary wall_time)"] >= 0
    total, numbers = read_reproduction(root)  # what riskplan bench --reproduce reads of a reproduction
    assert total == breakdown["total"] and set(numbers) == set(record["parts"]) - {"landscape", "comparison", "report"}
    assert numbers["single"].equals(single[["job", "status", "mean", "cvar", "value_at_risk"]])
    # one sweep worker was warmed up while reproduce planned, and the sweeps ran their jobs on it
    warm = record["warm_up"]
    assert warm["workers"] == 1 and len(warm["seconds"]) == 1 and warm["seconds"][0] > 0
    job_pids = {json.loads(p.read_text())["pid"] for p in root.glob("*/*/status.json")}
    assert warm["pids"][0] in job_pids
    for folder, jobs in (("single", 2), ("team", 1), ("frontier", 4)):
        timing = record["parts"][folder]["timing"]
        assert timing["jobs"] == jobs and timing["planning"] >= 0 and timing["running"] >= 0
    soft = pd.read_parquet(root / "soft_risk" / "summary.parquet")
    assert len(soft) == 1 and soft.status.iloc[0] == "done"
    soft_config = (root / "soft_risk" / "seed=0" / ".hydra" / "config.yaml").read_text()
    assert "kind: linear" in soft_config and "- 0\n  - 0\n" in soft_config  # wander/'s theta0, with the schedule
    assert (root / "report" / "soft_risk.png").is_file() and (root / "report" / "soft_risk.csv").is_file()
    wander = pd.read_parquet(root / "wander" / "summary.parquet")
    assert len(wander) == 1 and wander.status.iloc[0] == "done"
    assert "- 0\n  - 0\n" in (root / "wander" / "seed=0" / ".hydra" / "config.yaml").read_text()  # theta0
    assert "Section V across seeds" in result.stdout and "θ0 = (0, 0)" in result.stdout
    assert (root / "report" / "report.html").is_file()
    landscape = json.loads((root / "landscape" / "summary.json").read_text())
    assert landscape["experiment"] == "paper_single" and landscape["theta_fixed"] == [20.0, 20.0]  # no wander/ theta0
    frontier = pd.read_parquet(root / "frontier" / "summary.parquet")
    assert sorted(frontier.beta) == [0.05, 0.2, 0.5, 1.0] and (frontier.status == "done").all()
    assert "CVaR_0.05" in result.stdout and "CVaR_1" in result.stdout
    # the studies beyond the paper: every job done, each with its report figure, table and section
    for folder in studies:
        summary = pd.read_parquet(root / folder / "summary.parquet")
        assert (summary.status == "done").all(), folder
    assert sorted(pd.read_parquet(root / "measures" / "summary.parquet").risk) == sorted(
        ["cvar", "neutral", "wang", "mean_cvar", "entropic"]
    )
    report = root / "report"
    for figure, table in (
        ("risk_measures", "measures"),
        ("richer_policies", "policies"),
        ("hetero_team", "hetero_team"),
        ("faults", "faults"),
    ):
        assert (report / f"{figure}.png").is_file() and (report / f"{table}.csv").is_file()
    assert len(pd.read_csv(report / "measures.csv")) == 5 and len(pd.read_csv(report / "policies.csv")) == 3
    assert pd.read_csv(report / "hetero_team.csv").centralized.tolist() == [False, False, True]
    assert pd.read_csv(report / "faults.csv").fault_free.tolist() == [False, False, True]
    assert "Wang (η=0.5)" in (report / "report.html").read_text()
    assert "8 robots from 8 starts, ring, gradient_tracking" in result.stdout

    # completing an existing reproduction runs nothing again
    again = riskplan_cli(
        tmp_path, "reproduce", "--quick", "--seeds", "1", "--format", "png", "--out", str(root), *FAST, "risk.beta=0.1"
    )
    assert again.returncode == 0, again.stderr
    assert "2 jobs: 0 to run, 2 already finished" in again.stdout
    assert "1 job: 0 to run, 1 already finished" in again.stdout
    assert "4 jobs: 0 to run, 4 already finished" in again.stdout
    assert json.loads((root / "reproduce.json").read_text())["breakdown"]["jobs"]["jobs"] == 0


def test_reproduce_paper_only_runs_section_v_alone(tmp_path):
    result = riskplan_cli(
        tmp_path, "reproduce", "--quick", "--paper-only", "--seeds", "1", "--format", "png", *FAST
    )  # batched: the default
    assert result.returncode == 0, result.stdout + result.stderr
    (root,) = (tmp_path / "outputs" / "reproduce").iterdir()
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == ["report", "single", "team"]
    record = json.loads((root / "reproduce.json").read_text())
    assert record["paper_only"] and set(record["parts"]) == {"single", "team", "comparison", "report"}
    assert "plan: 3 stages, 3 jobs, each sweep one batch" in result.stdout and "[stage 3 of 3: report]" in result.stdout
    # each sweep one batch, in the reproduction's own process
    assert record["batched"] and len({json.loads(p.read_text())["pid"] for p in root.glob("*/*/status.json")}) == 1
    assert (root / "report" / "fig1_paths.png").is_file() and (root / "report" / "fig3_team.png").is_file()


# bad input in this process (typer's runner): the exit code and stderr are the command's own, without a start-up each
def test_reproduce_rejects_sweeps_and_its_own_keys_as_bad_input(in_tmp):
    for args in (["risk.beta=0.1,0.2"], ["seed=3"], ["train.iterations=abc"], ["--seeds", "0"]):
        result = runner.invoke(app, ["reproduce", *args])
        assert result.exit_code == 2, (args, result.stderr)
        assert "Traceback" not in result.stderr
    assert not (in_tmp / "outputs").exists()


def test_reproduce_seeds_are_bounded(in_tmp, monkeypatch):
    with monkeypatch.context() as limit:
        limit.setenv("RISKPLAN_MAX_JOBS", "100")
        result = runner.invoke(app, ["reproduce", "--seeds", "40"])
    assert result.exit_code == 2 and "RISKPLAN_MAX_JOBS" in result.stderr and len(result.stderr.splitlines()) == 1
    with monkeypatch.context() as limit:
        limit.setenv("RISKPLAN_MAX_HOURS", "0.0001")
        result = runner.invoke(app, ["reproduce", "--seeds", "3"])
    assert result.exit_code == 2 and "RISKPLAN_MAX_HOURS" in result.stderr and len(result.stderr.splitlines()) == 1
    assert not (in_tmp / "outputs").exists()


# Ctrl-C and failures in this process (typer's runner): a signal sent to this process is the user's Ctrl-C
FIGURES = ["mean", "cvar", "value_at_risk"]


def _reproduce_args(out) -> list[str]:
    return ["reproduce", "--quick", "--paper-only", "--seeds", "1", "--format", "png", "--out", str(out), *TINY]


def test_ctrl_c_in_a_stage_stops_the_reproduction_there_and_it_resumes_to_the_same_numbers(tmp_path, monkeypatch):
    """Ctrl-C stopped only the sweep training at the time: the later stages and the report ran on, and the last
    line said to resume with `riskplan sweep`."""
    plain = runner.invoke(app, _reproduce_args(tmp_path / "plain"))
    assert plain.exit_code == 0, plain.stderr
    prepare = batched.prepare_jobs

    def prepare_then_ctrl_c(*args, **kwargs):
        prepared = prepare(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)  # as single/'s jobs are set up
        return prepared

    monkeypatch.setattr(batched, "prepare_jobs", prepare_then_ctrl_c)
    stopped = runner.invoke(app, _reproduce_args(tmp_path / "r"))
    assert stopped.exit_code == 130, stopped.stderr
    last = stopped.stderr.splitlines()[-1]
    assert last.startswith("error: interrupted by SIGINT during single/: 2 jobs did not finish (each keeps its last ")
    assert f"resume with riskplan reproduce --out {tmp_path / 'r'} --quick --paper-only --seeds 1 " in last
    assert "riskplan sweep" not in stopped.stderr
    assert not (tmp_path / "r" / "team").exists() and not (tmp_path / "r" / "report").exists()  # nothing after it
    record = json.loads((tmp_path / "r" / "reproduce.json").read_text())
    assert record["interrupted"] == {"signal": "SIGINT", "stage": "single/"}

    monkeypatch.setattr(batched, "prepare_jobs", prepare)
    again = runner.invoke(app, _reproduce_args(tmp_path / "r"))
    assert again.exit_code == 0, again.stderr
    assert "interrupted" not in json.loads((tmp_path / "r" / "reproduce.json").read_text())
    for folder in ("single", "team"):
        figures = [
            pd.read_parquet(root / folder / "summary.parquet")[FIGURES] for root in (tmp_path / "plain", tmp_path / "r")
        ]
        pd.testing.assert_frame_equal(*figures)


def test_ctrl_c_in_the_report_stops_it_with_one_line(tmp_path, monkeypatch):
    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt  # what Ctrl-C raises in this process while it draws

    monkeypatch.setattr(reproduction, "build_report", ctrl_c)
    stopped = runner.invoke(app, _reproduce_args(tmp_path / "r"))
    assert stopped.exit_code == 130
    assert stopped.stderr.splitlines()[-1].startswith("error: interrupted by SIGINT during report; resume with ")
    assert "Traceback" not in stopped.stderr


def test_a_reproduction_whose_every_job_failed_exits_1_not_2(tmp_path):
    """Its report stage found no run to report and said so as bad input (exit 2), though the input was fine."""
    failed = runner.invoke(app, [*_reproduce_args(tmp_path / "r"), "train.step_size.initial=1.7e308"])
    assert failed.exit_code == 1, failed.stderr
    assert "error: no report: " in failed.stderr and "theta or its gradient is not finite" in failed.stderr
    assert failed.stderr.splitlines()[-1].startswith("to retry what did not finish (finished jobs are skipped): ")
