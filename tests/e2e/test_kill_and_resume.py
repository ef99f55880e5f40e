"""Resume and crash safety: SIGKILL a real `riskplan train` part-way (and inside a checkpoint write), resume it, and
compare every output with an uninterrupted run of the same config and seed.

The kills are deterministic, so the tests are not timing-dependent on a loaded machine:
- `RISKPLAN_TEST_STOP_AFTER_ITERATION=k` makes the run SIGSTOP itself right after iteration k is logged; the test
  waits until the process is stopped and then SIGKILLs it (a kill between two checkpoints, with iterations in
  run.mcap past the last checkpoint);
- `RISKPLAN_TEST_KILL_IN_CHECKPOINT=k` SIGKILLs the run after the temp file of checkpoint k is written and fsynced,
  before the rename.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pandas as pd
import pytest
from support import (
    CHECKPOINTED,
    CHECKPOINTED_TEAM,
    assert_log_holds_each_iteration_once,
    assert_same_outputs,
    checkpoint_iteration,
    kill_after_iteration,
    resume_cli,
    train_cli,
)
from typer.testing import CliRunner

import riskplan.run.training as training
from riskplan import compose, load_run
from riskplan.cli import app
from riskplan.run.checkpoint import CHECKPOINT, CRASH_ENV
from riskplan.run.log_reader import read_log

pytestmark = pytest.mark.slow

RUN = CHECKPOINTED  # 30 iterations, a checkpoint every 5
TEAM = CHECKPOINTED_TEAM  # delays and drops: mixer state
TRACKING = [*TEAM, "team.order=gradient_tracking"]  # the trackers, their running sums and the last gradients too

runner = CliRunner()


# ----------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def baseline(uninterrupted) -> Path:
    """An uninterrupted `riskplan train` of RUN (30 iterations, checkpoints every 5), shared with the session."""
    return uninterrupted(0)


@pytest.fixture(scope="module")
def team_baseline(tmp_path_factory) -> Path:
    """An uninterrupted team run: 3 robots on a line, delayed and dropped messages (trained in this process: the
    numbers of a `riskplan train`, test_determinism.py)."""
    out = tmp_path_factory.mktemp("team_baseline") / "run"
    training.train(compose(TEAM), out)
    return out


# ----------------------------------------------------------------------------------------------- kills
def test_sigkill_part_way_then_resume_equals_the_uninterrupted_run(tmp_path, baseline):
    out = tmp_path / "run"
    assert kill_after_iteration(RUN, out, 12) == -signal.SIGKILL

    # What the kill left: the checkpoint of iteration 10, a log with every flushed iteration, no tables, and a
    # status that still says running.
    assert checkpoint_iteration(out) == 10
    assert not any((out / f).exists() for f in ("summary.json", "metrics.parquet", "eval.parquet"))
    assert json.loads((out / "status.json").read_text())["status"] == "running"
    killed = load_run(out)
    assert not killed.complete and "truncated after iteration 12" in killed.problem
    assert list(killed.metrics.iteration) == list(range(13)) and killed.summary is None
    pd.testing.assert_frame_equal(
        killed.metrics.drop(columns="seconds"),
        pd.read_parquet(baseline / "metrics.parquet").iloc[:13].drop(columns="seconds"),
        check_exact=True,
    )
    from riskplan.experiments.reporting.collect import collect

    (skipped,) = collect([out]).broken  # what `riskplan report` lists as skipped, with the reason
    assert skipped.path == out and "truncated after iteration 12" in skipped.reason

    result = resume_cli(out)
    assert result.returncode == 0, result.stderr
    assert "resuming:" in result.stdout and "30 iterations" in result.stdout
    assert_same_outputs(out, baseline)
    assert_log_holds_each_iteration_once(out, 30, (0,))  # iterations 10-12 were logged twice, kept once
    assert load_run(out).complete and checkpoint_iteration(out) == 30
    assert json.loads((out / "status.json").read_text())["status"] == "done"


def test_kill_inside_a_checkpoint_write_resumes_from_the_previous_checkpoint(tmp_path, baseline):
    out = tmp_path / "run"
    result = train_cli(RUN, out, **{CRASH_ENV: "10"})
    assert result.returncode == -signal.SIGKILL

    # The kill came between the fsynced temp file and the rename: the last good checkpoint is untouched.
    assert checkpoint_iteration(out) == 5
    assert checkpoint_iteration(out, f"{CHECKPOINT}.tmp") == 10
    assert list(load_run(out).metrics.iteration) == list(range(10))

    result = resume_cli(out)
    assert result.returncode == 0, result.stderr
    assert_same_outputs(out, baseline)
    assert_log_holds_each_iteration_once(out, 30, (0,))
    assert not (out / f"{CHECKPOINT}.tmp").exists() and checkpoint_iteration(out) == 30


def test_team_run_killed_twice_resumes_to_the_uninterrupted_run(tmp_path, team_baseline):
    out = tmp_path / "run"
    assert train_cli(TEAM, out, **{CRASH_ENV: "10"}).returncode == -signal.SIGKILL
    assert checkpoint_iteration(out) == 5
    assert resume_cli(out, **{CRASH_ENV: "20"}).returncode == -signal.SIGKILL  # the resumed run dies too
    assert checkpoint_iteration(out) == 15
    assert list(load_run(out).metrics.query("robot == 0").iteration) == list(range(20))

    result = resume_cli(out)
    assert result.returncode == 0, result.stderr
    assert_same_outputs(out, team_baseline)
    assert_log_holds_each_iteration_once(out, 30, (-1, 0, 1, 2))


def test_gradient_tracking_run_killed_resumes_to_the_uninterrupted_run(tmp_path):
    reference = tmp_path / "reference"
    training.train(compose(TRACKING), reference)  # uninterrupted, in this process
    out = tmp_path / "run"
    assert kill_after_iteration(TRACKING, out, 12) == -signal.SIGKILL
    assert checkpoint_iteration(out) == 10
    assert "tracker" in json.loads((out / CHECKPOINT).read_text())["mixer"]
    result = resume_cli(out)
    assert result.returncode == 0, result.stderr
    assert_same_outputs(out, reference)
    assert_log_holds_each_iteration_once(out, 30, (-1, 0, 1, 2))


def test_resume_with_more_iterations_extends_a_finished_run(tmp_path, monkeypatch, baseline):
    monkeypatch.chdir(tmp_path)  # in-process this time: a second launcher for the same numbers
    out = tmp_path / "run"
    first = runner.invoke(app, ["train", *RUN, "train.iterations=15", f"hydra.run.dir={out}"])
    assert first.exit_code == 0, first.output
    assert checkpoint_iteration(out) == 15 and load_run(out).complete

    again = runner.invoke(app, ["train", "--resume", str(out), "train.iterations=30"])
    assert again.exit_code == 0, again.output
    assert "30 iterations (resumed at 15: the last 15 in " in again.output
    assert json.loads((out / "summary.json").read_text())["resumed_at"] == 15
    assert_same_outputs(out, baseline)
    assert_log_holds_each_iteration_once(out, 30, (0,))
    run = load_run(out)
    assert run.config["train"]["iterations"] == 30  # .hydra/config.yaml follows the extension
    assert read_log(out / "run.mcap").metadata["config"]["train"]["iterations"] == 30

    # Resuming the finished run once more (nothing left to train) leaves every file exactly as it was.
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    third = runner.invoke(app, ["train", "--resume", str(out)])
    assert third.exit_code == 0, third.output
    assert "already finished" in third.output
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert_same_outputs(out, baseline)
    assert_log_holds_each_iteration_once(out, 30, (0,))


def test_power_cut_state_resumes_each_checkpoint_is_backed_by_a_synced_log(tmp_path, monkeypatch, baseline):
    """Simulate a power cut: only fsynced bytes survive. At every checkpoint rename, the checkpoint and the log as
    of its last fsync must be enough to resume; resuming from one such state gives the uninterrupted run."""
    out = tmp_path / "run"
    synced: dict[str, bytes] = {}
    states: dict[int, tuple[bytes, bytes]] = {}  # checkpoint iteration -> (checkpoint bytes, synced log bytes)
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        real_fsync(fd)
        path = os.readlink(f"/proc/self/fd/{fd}")
        if Path(path).is_file():
            synced[path] = Path(path).read_bytes()

    def replace(src, dst):
        if Path(dst).name == CHECKPOINT:
            body = synced[str(src)]
            states[json.loads(body)["iteration"]] = (body, synced.get(str(out / "run.mcap"), b""))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    training.train(compose(RUN), out)
    monkeypatch.undo()

    assert sorted(states) == [5, 10, 15, 20, 25, 30]
    for iteration, (_, log) in states.items():
        (tmp_path / "synced.mcap").write_bytes(log)
        assert list(read_log(tmp_path / "synced.mcap").metrics.iteration) == list(range(iteration))

    cut = tmp_path / "cut"  # the disk after a power cut just after checkpoint 15
    (cut / ".hydra").mkdir(parents=True)
    (cut / ".hydra" / "config.yaml").write_bytes((out / ".hydra" / "config.yaml").read_bytes())
    (cut / CHECKPOINT).write_bytes(states[15][0])
    (cut / "run.mcap").write_bytes(states[15][1])
    training.train(compose(RUN), cut, resume=True)
    assert_same_outputs(cut, baseline)
    assert_log_holds_each_iteration_once(cut, 30, (0,))
