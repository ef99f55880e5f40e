"""summary.parquet's rows (riskplan.experiments.sweeping.summary): one per job, its overrides as columns, and the
reason a job did not finish, read from its status file. Finished jobs' figures are checked through the CLI in
test_sweep_command.py."""

from __future__ import annotations

import pandas as pd

from riskplan.experiments.sweep_worker import write_status
from riskplan.experiments.sweeping.jobs import Job
from riskplan.experiments.sweeping.summary import _override_columns, summarize, varying_columns


def test_every_job_gets_a_row_with_why_it_did_not_finish(tmp_path):
    def job(seed: int, sha: str, status: dict | None = None, invalid: str | None = None) -> Job:
        path = None
        if status is not None:
            path = tmp_path / f"seed={seed}"
            path.mkdir()
            write_status(path, status)
        return Job([f"seed={seed}", "risk.beta=0.1"], sha, invalid=invalid, path=path, label=f"seed={seed}")

    jobs = [
        job(0, "a"),  # the sweep stopped before it
        job(1, "b", invalid="risk.beta: got 1.5"),
        job(2, "c", {"status": "failed", "error": "boom", "config_sha": "c"}),
        job(3, "d", {"status": "running", "config_sha": "d"}),  # killed while it ran
        job(4, "e", {"status": "done", "config_sha": "another"}),
    ]
    frame = summarize(jobs)
    assert frame.job.tolist() == [f"seed={s}" for s in range(5)] and frame.seed.tolist() == [0, 1, 2, 3, 4]
    assert (frame["risk.beta"] == 0.1).all()
    assert frame.status.tolist() == ["not run", "not run", "failed", "interrupted", "not run"]
    assert frame.error.tolist() == [
        "not started: the sweep stopped before it",
        "risk.beta: got 1.5",
        "boom",
        "killed while running; re-run the sweep to resume it",
        "its folder holds a run of another config",
    ]
    assert frame[["mean", "cvar_low", "value_at_risk_high", "wall_time"]].isna().all().all()
    assert frame.path[:2].isna().all() and frame.path[2] == str(tmp_path / "seed=2")


def test_override_columns_keep_numbers_and_write_lists_as_json():
    assert _override_columns(["risk.beta=0.1", "seed=3", "world.size=[16,16]", "risk=neutral"]) == {
        "risk.beta": 0.1,
        "seed": 3,
        "world.size": "[16, 16]",
        "risk": "neutral",
    }


def test_the_table_shows_the_overrides_that_vary():
    frame = pd.DataFrame(
        {"job": ["a", "b"], "seed": [0, 1], "risk.beta": [0.1, 0.1], "train.iterations": [5, 5], "status": "done"}
    )
    assert varying_columns(frame) == ["seed"]
    assert varying_columns(frame.iloc[:1]) == ["seed", "risk.beta", "train.iterations"]  # none varies: the first 3
