"""summary.parquet's rows (riskplan.experiments.sweeping.summary): one per job, its overrides as columns, and the
reason a job did not finish, read from its status file. Finished jobs' figures are checked through the CLI in
test_sweep_command.py."""

from __future__ import annotations

import pandas as pd
import pytest
from support import TINY, riskplan_cli

from riskplan.experiments.sweep_worker import write_status
from riskplan.experiments.sweeping.jobs import Job
from riskplan.experiments.sweeping.summary import _override_columns, print_table, summarize, varying_columns


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
    assert frame.status.tolist() == ["not run", "not run", "failed", "interrupted", "failed"]
    assert frame.error.tolist() == [
        "not started: the sweep stopped before it",
        "risk.beta: got 1.5",
        "boom",
        "killed while running; re-run the sweep to resume it",
        f"{tmp_path / 'seed=4'} holds a done run of another config; the job left it as it was: a sweep goes on in its "
        "directory only with the same configs, so give a new hydra.sweep.dir (or remove that folder and run the "
        "sweep again)",
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


@pytest.mark.slow  # a sweep through the CLI
def test_a_degenerate_job_is_marked_in_the_table_named_after_it_and_kept_in_its_row(tmp_path):
    """From [0, 0] both sources lie 12 moves away, the horizon: a policy pushed away from the signals reaches
    neither; from [8, 3], beside the safe source, it does."""
    start = ["world.start=[0,0],[8,3]", "world.horizon=12", "train.theta0=[-20.0,-20.0]", "hydra.sweep.dir=s"]
    result = riskplan_cli(tmp_path, "sweep", *TINY, *start)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("[")]
    assert "degenerate" in next(r for r in rows if r.startswith("[0, 0]")) and "done" in rows[-1]
    warning = result.stderr.splitlines()
    at = warning.index("warning: 1 of 2 runs learned something degenerate:")
    assert warning[at + 1].startswith("  world.start=%5B0,0%5D: reached_no_source: reached no source in its 200")
    frame = pd.read_parquet(tmp_path / "s" / "summary.parquet")
    assert frame.status.tolist() == ["done", "done"]
    assert frame.degenerate[0].startswith("reached_no_source: ") and pd.isna(frame.degenerate[1])


def test_the_table_prints_values_as_text_never_as_markup_or_extra_lines(capsys):
    """A value is printed as typed: '[/]' crashed the table (rich read it as a closing tag) after every job had
    finished, '[red]x' lost its brackets, and a line break forged a line of the sweep's output."""
    frame = pd.DataFrame(
        {
            "job": ["a", "b", "c"],
            "team.address": ["[/]", "[red]x", "x\n[2/2] failed FAKE"],
            "status": "done",
            **{name: 1.0 for name in ("mean", "mean_low", "mean_high", "cvar", "cvar_low", "cvar_high")},
            "value_at_risk": 1.0,
            "wall_time": 1.0,
        }
    )
    print_table(frame, "sweep: s")
    rows = capsys.readouterr().out.splitlines()
    shown = [row.split("│")[0].strip() for row in rows if "│" in row]
    assert shown == ["[/]", "[red]x", "x\\n[2/2] failed FAKE"]
    assert not any(row.startswith("[2/2]") for row in rows)
