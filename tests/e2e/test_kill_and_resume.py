"""Resume and crash safety: SIGKILL a real `riskplan train` part-way (and inside a checkpoint write), resume it, and
compare every output with an uninterrupted run of the same config and seed; numerical trouble keeps the last good
checkpoint.

The kills are deterministic, so the tests are not timing-dependent on a loaded machine:
- `RISKPLAN_TEST_STOP_AFTER_ITERATION=k` makes the run SIGSTOP itself right after iteration k is logged; the test
  waits until the process is stopped and then SIGKILLs it (a kill between two checkpoints, with iterations in
  run.mcap past the last checkpoint);
- `RISKPLAN_TEST_KILL_IN_CHECKPOINT=k` SIGKILLs the run after the temp file of checkpoint k is written and fsynced,
  before the rename.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import riskplan.run.training as training
from riskplan import compose, load_run
from riskplan.cli import app
from riskplan.run.checkpoint import CHECKPOINT, CRASH_ENV
from riskplan.run.evaluation import NumericalTrouble
from riskplan.run.record import read_log
from riskplan.run.training import STOP_ENV

FAST = [
    "train.iterations=30",
    "train.samples=500",
    "train.eval_episodes=2000",
    "train.bootstrap=50",
    "train.paths=3",
    "train.checkpoint_every=5",
]
TEAM = [*FAST, "experiment=paper_team", "team.delay.max=2", "team.drop=0.2"]  # delays and drops: mixer state
TRACKING = [*TEAM, "team.order=gradient_tracking"]  # the trackers, their running sums and the last gradients too
TABLES = ("metrics", "eval", "trajectories")
WALL_CLOCK = {"wall_time", "throughput_episodes_per_s"}  # summary.json fields that measure time, not results
TIMEOUT = 300

runner = CliRunner()


# ----------------------------------------------------------------------------------------------- helpers
def riskplan_command() -> list[str]:
    """The installed console script next to this interpreter (the way users run it)."""
    script = Path(sys.executable).with_name("riskplan")
    return [str(script)] if script.is_file() else [sys.executable, "-c", "from riskplan.cli import main; main()"]


def child_env(**extra: str) -> dict[str, str]:
    """The test's environment without the fault-injection variables, plus `extra`."""
    env = {k: v for k, v in os.environ.items() if k not in (CRASH_ENV, STOP_ENV)}
    env.update(extra)
    return env


def run_cli(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess:
    """`riskplan <args>` in a subprocess; returns when it exits (or is killed)."""
    return subprocess.run(
        [*riskplan_command(), *args], cwd=cwd, env=child_env(**env), capture_output=True, text=True, timeout=TIMEOUT
    )


def train_cli(overrides: list[str], out: Path, **env: str) -> subprocess.CompletedProcess:
    """`riskplan train <overrides> hydra.run.dir=<out>` in a subprocess."""
    return run_cli(["train", *overrides, f"hydra.run.dir={out}"], out.parent, **env)


def resume_cli(out: Path, *overrides: str, **env: str) -> subprocess.CompletedProcess:
    """`riskplan train --resume <out> [overrides]` in a subprocess."""
    return run_cli(["train", "--resume", str(out), *overrides], out.parent, **env)


def kill_after_iteration(overrides: list[str], out: Path, iteration: int) -> int:
    """Start `riskplan train`, let it log `iteration` (it then stops itself), SIGKILL it; its return code."""
    proc = subprocess.Popen(
        [*riskplan_command(), "train", *overrides, f"hydra.run.dir={out}"],
        cwd=out.parent,
        env=child_env(**{STOP_ENV: str(iteration)}),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)  # returns once the child is stopped (or has exited)
        assert os.WIFSTOPPED(status), f"the run ended before iteration {iteration} (status {status})"
        proc.send_signal(signal.SIGKILL)
        return proc.wait(timeout=TIMEOUT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def checkpoint_iteration(out: Path, name: str = CHECKPOINT) -> int:
    """The iteration a checkpoint file was written at (it parses: never half a file)."""
    return json.loads((out / name).read_text())["iteration"]


def comparable_summary(summary: dict) -> dict:
    """summary.json without wall-clock fields and the git SHA (the shared tree may get commits meanwhile)."""
    out = {k: v for k, v in summary.items() if k not in WALL_CLOCK}
    out["provenance"] = {k: v for k, v in summary.get("provenance", {}).items() if k != "git_sha"}
    return json.loads(json.dumps(out))  # NaN-safe comparison through one JSON round trip


def assert_same_outputs(run: Path, reference: Path) -> None:
    """Every value of every table and of summary.json equal, wall-clock fields aside; the same for run.mcap."""
    for name in TABLES:
        got, want = (pd.read_parquet(d / f"{name}.parquet") for d in (run, reference))
        if name == "metrics":
            got, want = got.drop(columns="seconds"), want.drop(columns="seconds")
        pd.testing.assert_frame_equal(got, want, check_exact=True, obj=name)
    got, want = (json.loads((d / "summary.json").read_text()) for d in (run, reference))
    assert comparable_summary(got) == comparable_summary(want)
    got_log, want_log = read_log(run / "run.mcap"), read_log(reference / "run.mcap")
    assert got_log.complete and want_log.complete, got_log.problem
    pd.testing.assert_frame_equal(
        got_log.metrics.drop(columns="seconds"),
        want_log.metrics.drop(columns="seconds"),
        check_exact=True,
        obj="run.mcap metrics",
    )
    pd.testing.assert_frame_equal(got_log.eval, want_log.eval, check_exact=True, obj="run.mcap eval")
    pd.testing.assert_frame_equal(
        got_log.trajectories, want_log.trajectories, check_exact=True, obj="run.mcap trajectories"
    )
    assert comparable_summary(got_log.summary) == comparable_summary(want_log.summary)


def assert_log_holds_each_iteration_once(run: Path, iterations: int, robots: tuple[int, ...]) -> None:
    """run.mcap's /metrics: every (iteration, robot) exactly once, and the same rows as metrics.parquet."""
    log = read_log(run / "run.mcap")
    pairs = list(zip(log.metrics.iteration, log.metrics.robot))
    assert pairs == [(i, r) for i in range(iterations) for r in sorted(robots)]
    pd.testing.assert_frame_equal(log.metrics, pd.read_parquet(run / "metrics.parquet"), check_exact=True)


# ----------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def baseline(tmp_path_factory) -> Path:
    """An uninterrupted `riskplan train` of FAST (30 iterations, checkpoints every 5)."""
    out = tmp_path_factory.mktemp("baseline") / "run"
    result = train_cli(FAST, out)
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope="module")
def team_baseline(tmp_path_factory) -> Path:
    """An uninterrupted team run: 3 robots on a line, delayed and dropped messages."""
    out = tmp_path_factory.mktemp("team_baseline") / "run"
    result = train_cli(TEAM, out)
    assert result.returncode == 0, result.stderr
    return out


# ----------------------------------------------------------------------------------------------- kills
def test_sigkill_part_way_then_resume_equals_the_uninterrupted_run(tmp_path, baseline):
    out = tmp_path / "run"
    assert kill_after_iteration(FAST, out, 12) == -signal.SIGKILL

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
    result = train_cli(FAST, out, **{CRASH_ENV: "10"})
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
    result = train_cli(TRACKING, reference)
    assert result.returncode == 0, result.stderr
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
    first = runner.invoke(app, ["train", *FAST, "train.iterations=15", f"hydra.run.dir={out}"])
    assert first.exit_code == 0, first.output
    assert checkpoint_iteration(out) == 15 and load_run(out).complete

    again = runner.invoke(app, ["train", "--resume", str(out), "train.iterations=30"])
    assert again.exit_code == 0, again.output
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
    training.train(compose(FAST), out)
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
    training.train(compose(FAST), cut, resume=True)
    assert_same_outputs(cut, baseline)
    assert_log_holds_each_iteration_once(cut, 30, (0,))


# ----------------------------------------------------------------------------------------------- numerics
def _fail_at(monkeypatch, name: str, iteration: int, bad):
    """Make riskplan.run.training.<name> return bad(result) from the given iteration on (the iteration is read off
    the `samples_at` call that opens every iteration)."""
    original, seen = getattr(training, name), {"l": 0}
    original_samples = training.samples_at

    def samples(l, train):
        seen["l"] = l
        return original_samples(l, train)

    def patched(*args, **kwargs):
        result = original(*args, **kwargs)
        return bad(result) if seen["l"] >= iteration else result

    monkeypatch.setattr(training, "samples_at", samples)
    monkeypatch.setattr(training, name, patched)


@pytest.mark.parametrize(
    "name, bad, message",
    [
        ("cvar_gradient", lambda g: np.full_like(g, np.nan), "theta or its gradient is not finite"),
        ("consensus_step", lambda t: np.full_like(t, 1.5e308), "overflows the softmax"),  # finite, but theta.s = inf
    ],
)
def test_numerical_trouble_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch, name, bad, message):
    out = tmp_path / "run"
    config = compose(FAST)
    _fail_at(monkeypatch, name, 7, bad)
    with pytest.raises(NumericalTrouble, match=f"iteration 7: .*{message}.*lower train.step_size.initial"):
        training.train(config, out)

    state = json.loads((out / CHECKPOINT).read_text())
    assert state["iteration"] == 5 and all(math.isfinite(t) for t in state["thetas"][0])
    assert not (out / f"{CHECKPOINT}.tmp").exists()
    assert not any((out / f"{t}.parquet").exists() for t in TABLES) and not (out / "summary.json").exists()
    run = load_run(out)  # the log was closed cleanly, with no iteration 7 and no NaN in it
    assert not run.complete and "stopped after iteration 6" in run.problem
    assert list(run.metrics.iteration) == list(range(7))
    assert np.isfinite(run.metrics.drop(columns="consensus_error").to_numpy(dtype=float)).all()

    monkeypatch.undo()  # the cause gone, the run resumes from its last good checkpoint
    training.train(config, out, resume=True)
    assert_log_holds_each_iteration_once(out, 30, (0,))


def test_diverging_step_size_fails_with_one_line_and_no_nan(tmp_path):
    result = train_cli([*FAST, "train.step_size.initial=1e308"], tmp_path / "run")
    assert result.returncode == 1
    (line,) = result.stderr.strip().splitlines()  # no overflow warning, no traceback: one line
    assert line.startswith("error: run failed: iteration 0: theta or its gradient is not finite")
    assert "lower train.step_size.initial" in line
    assert not (tmp_path / "run" / "metrics.parquet").exists()
    assert read_log(tmp_path / "run" / "run.mcap").metrics.empty  # nothing non-finite was logged
