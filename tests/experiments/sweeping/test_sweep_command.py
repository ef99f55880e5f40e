"""`riskplan sweep` through the real command line (a subprocess per call, but for bad input: typer's runner in this
process), on small configs: a grid runs once, then skips, then reruns only what was deleted; failing jobs fail
alone; bad input exits 2 before anything runs; the submitit launcher; a killed sweep resumes. The grid's expansion
and checks are unit-tested in test_grid.py."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pandas as pd
import pytest
from support import FAST, riskplan_cli
from typer.testing import CliRunner

from riskplan.cli import app

pytestmark = pytest.mark.slow
runner = CliRunner()


def sweep_dir_of(result: subprocess.CompletedProcess, cwd: Path) -> Path:
    match = re.search(r"^sweep directory: (.+)$", result.stdout, re.M)
    assert match, result.stdout + result.stderr
    return cwd / match.group(1)


def job_dirs(sweep: Path) -> list[Path]:
    return sorted(p.parent for p in sweep.glob("*/status.json"))


def test_grid_runs_once_then_skips_then_reruns_only_what_was_deleted(tmp_path):
    first = riskplan_cli(tmp_path, "sweep", "risk.beta=0.1,0.2", "seed=range(0,2)", *FAST, "--jobs", "2")
    assert first.returncode == 0, first.stderr
    sweep = sweep_dir_of(first, tmp_path)
    assert sweep.parent == tmp_path / "outputs" / "sweeps"
    assert "4 jobs: 4 to run, 0 already finished (joblib, 2 workers)" in first.stdout

    # one folder per job, named from the overrides that vary; each a normal run directory
    dirs = job_dirs(sweep)
    assert [d.name for d in dirs] == [
        "risk.beta=0.1,seed=0",
        "risk.beta=0.1,seed=1",
        "risk.beta=0.2,seed=0",
        "risk.beta=0.2,seed=1",
    ]
    for d in dirs:
        assert json.loads((d / "status.json").read_text())["status"] == "done"
        for name in (
            "run.mcap",
            "summary.json",
            "metrics.parquet",
            "eval.parquet",
            ".hydra/config.yaml",
            ".hydra/overrides.yaml",
            "job.log",
        ):
            assert (d / name).is_file(), name
    assert (sweep / "multirun.yaml").is_file() and (sweep / "sweep.log").is_file()
    assert not (sweep / ".jobs.json").exists()  # the launch's job list lasts as long as the launch

    summary = pd.read_parquet(sweep / "summary.parquet")
    assert len(summary) == 4
    assert sorted(zip(summary["risk.beta"], summary["seed"])) == [(0.1, 0), (0.1, 1), (0.2, 0), (0.2, 1)]
    assert (summary.status == "done").all() and summary.error.isna().all()
    assert (summary["train.iterations"] == 5).all()
    for name in ("mean", "cvar", "value_at_risk"):
        assert (summary[f"{name}_low"] <= summary[name]).all() and (summary[name] <= summary[f"{name}_high"]).all()
    assert (summary.wall_time > 0).all()
    one = json.loads((sweep / "risk.beta=0.2,seed=1" / "summary.json").read_text())
    row = summary[(summary["risk.beta"] == 0.2) & (summary.seed == 1)].iloc[0]
    assert row.cvar == one["cvar"]["value"] and row.mean_high == one["mean"]["high"]
    # the progress view: one line per finished job, nothing from the jobs themselves
    assert len(re.findall(r"^\[\d/4\] done ", first.stderr, re.M)) == 4

    stamps = {d.name: (d / "run.mcap").stat().st_mtime_ns for d in dirs}
    again = riskplan_cli(tmp_path, "sweep", "risk.beta=0.1,0.2", "seed=range(0,2)", *FAST, f"hydra.sweep.dir={sweep}")
    assert again.returncode == 0, again.stderr
    assert "4 jobs: 0 to run, 4 already finished" in again.stdout
    assert {d.name: (d / "run.mcap").stat().st_mtime_ns for d in dirs} == stamps

    # the same sweep typed in another order is the same sweep: jobs are recognised by their config
    import shutil

    original = json.loads((sweep / "risk.beta=0.2,seed=0" / "summary.json").read_text())
    shutil.rmtree(sweep / "risk.beta=0.2,seed=0")
    third = riskplan_cli(
        tmp_path, "sweep", *reversed(FAST), "seed=0,1", "risk.beta=0.1,0.2", f"hydra.sweep.dir={sweep}"
    )
    assert third.returncode == 0, third.stderr
    assert "4 jobs: 1 to run, 3 already finished" in third.stdout
    after = {d.name: (d / "run.mcap").stat().st_mtime_ns for d in job_dirs(sweep)}
    assert {k for k in after if after[k] != stamps[k]} == {"risk.beta=0.2,seed=0"}
    rerun = json.loads((sweep / "risk.beta=0.2,seed=0" / "summary.json").read_text())
    assert rerun["cvar"] == original["cvar"]  # seeded: the re-run job gives the same figures
    summary = pd.read_parquet(sweep / "summary.parquet")
    assert len(summary) == 4 and (summary.status == "done").all()
    assert summary.loc[(summary["risk.beta"] == 0.2) & (summary.seed == 0), "cvar"].iloc[0] == rerun["cvar"]["value"]


def test_an_invalid_combination_and_a_raising_job_fail_alone(tmp_path):
    # beta=1.5 is invalid for the model; step 1e308 makes theta overflow, so that job raises in training
    result = riskplan_cli(
        tmp_path, "sweep", "risk.beta=0.2,1.5", "train.step_size.initial=0.1,1e308", *FAST, "hydra.sweep.dir=s"
    )
    assert result.returncode == 1
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet").set_index("job")
    assert len(summary) == 4
    good = "risk.beta=0.2,train.step_size.initial=0.1"
    assert summary.loc[good, "status"] == "done" and summary.loc[good, "cvar"] == summary.loc[good, "cvar"]
    for job in summary.index.drop(good):
        assert summary.loc[job, "status"] == "failed"
        assert job in result.stderr  # named in the final message
    assert "risk.beta: got 1.5" in summary.loc["risk.beta=1.5,train.step_size.initial=0.1", "error"]
    assert "not finite" in summary.loc["risk.beta=0.2,train.step_size.initial=1e+308", "error"]
    assert "3 of 4 jobs did not finish" in result.stderr
    status = json.loads((tmp_path / "s" / "risk.beta=0.2,train.step_size.initial=1e+308" / "status.json").read_text())
    assert status["status"] == "failed" and "not finite" in status["error"]
    # the job's own output stays in its folder (numpy's overflow warning too, in whichever job met it first)
    log = (tmp_path / "s" / "risk.beta=0.2,train.step_size.initial=1e+308" / "job.log").read_text()
    assert "=== failed: iteration 0" in log
    assert "overflow" not in result.stderr + result.stdout and "===" not in result.stderr + result.stdout
    # re-running retries the failed jobs only
    again = riskplan_cli(
        tmp_path, "sweep", "risk.beta=0.2,1.5", "train.step_size.initial=0.1,1e308", *FAST, "hydra.sweep.dir=s"
    )
    assert again.returncode == 1 and "4 jobs: 3 to run, 1 already finished" in again.stdout


@pytest.mark.parametrize(
    "args, names",
    [
        (["risk.beta=0.1,"], "override 'risk.beta=0.1,'"),
        (["risk.bta=0.1,0.2"], "risk.bta"),
        (["risk=cvar,foo"], "foo"),
        (["train.iterations=5,many"], "train.iterations"),
        (["risk.beta=2,3"], "risk.beta"),  # invalid in every combination: nothing to run
        (["seed=0,1", "hydra/launcher=nosuch"], "key 'hydra/launcher': no option 'nosuch'; available: basic, joblib"),
        (["seed=0,1", "hydra/launcher=submitit_local", "--jobs", "2"], "--jobs"),
        (["risk.beta=interval(0,1)"], "sweep"),
        (["seed=0,0"], "override 'seed=0,0': gives the value 0 twice"),  # one job twice
        (["seed=range(0,100000000)"], "RISKPLAN_MAX_JOBS"),  # refused before the combinations are listed
        (["seed=0,1", "hydra.sweep.dir=/proc/riskplan"], "hydra.sweep.dir: /proc/riskplan is under /proc"),
        (["seed=0,1", "hydra.sweep.subdir=same"], "hydra.sweep.subdir"),  # every job in one folder
        (["seed=0", "hydra.sweep.subdir=../out"], "hydra.sweep.subdir"),  # outside the sweep directory
    ],
)
def test_bad_input_exits_2_before_anything_runs(tmp_path, monkeypatch, args, names):
    # in this process: the exit code and stderr are the command's own, without two seconds of start-up per row
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["sweep", *FAST, *args])
    assert result.exit_code == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and names in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "outputs").exists()


def test_submitit_local_launcher_runs_a_two_job_sweep(tmp_path):
    result = riskplan_cli(tmp_path, "sweep", "seed=0,1", *FAST, "hydra/launcher=submitit_local", "hydra.sweep.dir=s")
    assert result.returncode == 0, result.stderr
    assert "(submitit_local)" in result.stdout
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    assert sorted(summary.seed) == [0, 1] and (summary.status == "done").all()
    assert (tmp_path / "s" / ".submitit").is_dir()
    pids = {json.loads((tmp_path / "s" / f"seed={i}" / "status.json").read_text())["pid"] for i in (0, 1)}
    assert len(pids) == 2  # each job in its own submitit process


def test_a_killed_sweep_resumes_its_interrupted_jobs(tmp_path):
    args = ["sweep", "seed=0,1", *FAST, "train.iterations=6", "train.checkpoint_every=2", "hydra.sweep.dir=s"]
    args += ["--jobs", "2"]  # job by job (a batch killed mid-way: test_batched_sweep.py)
    killed = riskplan_cli(tmp_path, *args, env={"RISKPLAN_TEST_KILL_IN_CHECKPOINT": "4"})  # SIGKILL at iteration 4
    assert killed.returncode == 1
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    assert not (summary.status == "done").any()
    assert "interrupted" in set(summary.status)
    resumed = riskplan_cli(tmp_path, *args)
    assert resumed.returncode == 0, resumed.stderr
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    assert (summary.status == "done").all()
    statuses = [json.loads((tmp_path / "s" / f"seed={i}" / "status.json").read_text()) for i in (0, 1)]
    assert any(s["resumed"] for s in statuses)  # from its checkpoint at iteration 2, not from scratch
    assert all(len(pd.read_parquet(tmp_path / "s" / f"seed={i}" / "metrics.parquet")) == 6 for i in (0, 1))
