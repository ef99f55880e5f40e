"""Ctrl-C and SIGTERM (a scheduler's preemption): the iteration in progress is checkpointed, status.json says
interrupted, one line, exit 130 or 143; --resume continues to the uninterrupted run's result, and a sweep does the
same for its jobs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import pytest
from support import CHECKPOINTED, TIMEOUT, assert_same_outputs, child_env, resume_cli, riskplan_command

from riskplan.run.checkpoint import CHECKPOINT
from riskplan.run.recorder import STOP_ENV
from riskplan.util import interrupt
from riskplan.util.interrupt import REPEAT_SECONDS, Interrupted, StopSignals


def test_a_signal_is_noted_and_raised_where_stopping_loses_nothing():
    with StopSignals() as stop:
        stop.check(4)  # nothing received: nothing happens
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.received == signal.SIGTERM
        with pytest.raises(Interrupted) as stopped:
            stop.check(7)
    assert (stopped.value.finished, stopped.value.name, stopped.value.exit_code) == (7, "SIGTERM", 143)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the previous handlers are back


def test_a_second_sigint_stops_at_once_and_a_repeat_at_once_is_the_same_stop(monkeypatch):
    """A worker of a sweep gets a terminal's Ctrl-C twice, directly and passed on by its driver, within
    milliseconds: one stop. A person pressing Ctrl-C again, later, stops at once."""
    # Python's own Ctrl-C handler, as in a terminal: a shell starts a background job with SIGINT ignored (conftest
    # puts the disposition back after the test)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    now = [100.0]
    monkeypatch.setattr(interrupt.time, "monotonic", lambda: now[0])
    with pytest.raises(KeyboardInterrupt), StopSignals() as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.received == signal.SIGINT
        now[0] += REPEAT_SECONDS / 2
        os.kill(os.getpid(), signal.SIGINT)  # the driver's copy of the same Ctrl-C
        assert stop.received == signal.SIGINT
        now[0] += REPEAT_SECONDS
        os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C does without riskplan: KeyboardInterrupt, now


def test_sigusr2_goes_on_to_the_job_runners_handler_after_the_checkpoint():
    """submitit handles SIGUSR2 (a time limit near: it requeues the job); riskplan notes it, checkpoints at the
    iteration's end, the job is recorded, then Interrupted.end calls that handler (which exits after requeueing;
    one that returns leaves the process to end with the signal's code)."""
    handed = []
    previous = signal.signal(signal.SIGUSR2, lambda signum, frame: handed.append(signum))
    try:
        with pytest.raises(Interrupted) as caught, StopSignals() as stop:
            os.kill(os.getpid(), signal.SIGUSR2)
            assert stop.received == signal.SIGUSR2 and handed == []  # noted, not handled yet
            stop.check(3)
        assert handed == [] and caught.value.finished == 3  # the job records its interruption first
        with pytest.raises(SystemExit) as ended:
            caught.value.end()
        assert handed == [signal.SIGUSR2] and ended.value.code == 128 + signal.SIGUSR2
    finally:
        signal.signal(signal.SIGUSR2, previous)
    with StopSignals():  # nobody handles SIGUSR2 in Python: riskplan leaves it alone
        assert signal.getsignal(signal.SIGUSR2) is previous


def interrupt_at(command: list[str], cwd: Path, iteration: int, signum: int) -> subprocess.CompletedProcess:
    """Run a riskplan command whose training stops itself (SIGSTOP) after logging `iteration`, then send it
    `signum` and let it go on: the signal arrives at a known iteration."""
    proc = subprocess.Popen(
        [*riskplan_command(), *command],
        cwd=cwd,
        env=child_env(**{STOP_ENV: str(iteration)}),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), f"the run ended before iteration {iteration}"
        proc.send_signal(signum)
        proc.send_signal(signal.SIGCONT)
        out, err = proc.communicate(timeout=TIMEOUT)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow
@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path, uninterrupted, signum, code):
    out = tmp_path / "run"
    done = interrupt_at(["train", *CHECKPOINTED, f"hydra.run.dir={out}"], tmp_path, 12, signum)  # between checkpoints
    assert done.returncode == code, done.stderr
    name = signal.Signals(signum).name
    assert done.stderr.strip().splitlines() == [
        f"interrupted by {name} after 13 iterations, all checkpointed; resume with riskplan train --resume {out}"
    ]
    status = json.loads((out / "status.json").read_text())
    assert status["status"] == "interrupted" and name in status["error"]
    assert json.loads((out / CHECKPOINT).read_text())["iteration"] == 13  # not 10: the iteration cut short is kept
    assert not (out / "summary.json").exists()
    resumed = resume_cli(out)
    assert resumed.returncode == 0, resumed.stderr
    assert_same_outputs(out, uninterrupted(0))


@pytest.mark.slow
@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_sweep_stops_its_jobs_checkpointed_and_resumes_to_the_same_numbers(
    tmp_path, uninterrupted, signum, code
):
    """The signal sent to the driver's pid alone (`kill`, `timeout -s INT`): the driver passes it on to its workers.
    A SIGINT was not passed on (a terminal's reaches every worker), so the jobs trained to their end."""
    overrides = [*CHECKPOINTED, "seed=0,1"]
    sweep = tmp_path / "sweep"
    proc = subprocess.Popen(
        [*riskplan_command(), "sweep", *overrides, f"hydra.sweep.dir={sweep}", "--jobs", "2"],  # a worker per job
        cwd=tmp_path,
        env=child_env(**{STOP_ENV: "12"}),  # every job stops itself after iteration 12
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        statuses = [sweep / f"seed={seed}" / "status.json" for seed in (0, 1)]
        stopped = _wait_until_stopped(proc.pid, count=2)
        proc.send_signal(signum)  # for the driver alone: it passes the signal on to its workers
        for pid in stopped:
            _wait_until_pending(pid, signum)  # passed on while the worker is stopped: a known iteration
            os.kill(pid, signal.SIGCONT)
        _, err = proc.communicate(timeout=TIMEOUT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == code, err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    name = signal.Signals(signum).name
    assert len(lines) == 1 and lines[0].startswith(f"error: interrupted by {name}: 2 jobs did not finish"), err
    for status in statuses:
        record = json.loads(status.read_text())
        assert record["status"] == "interrupted", record
        assert json.loads((status.parent / CHECKPOINT).read_text())["iteration"] == 13
    again = subprocess.run(
        [*riskplan_command(), "sweep", *overrides, f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )
    assert again.returncode == 0, again.stderr
    for seed in (0, 1):
        job = sweep / f"seed={seed}"
        assert json.loads((job / "status.json").read_text())["resumed"] is True
        assert_same_outputs(job, uninterrupted(seed))  # a job's numbers are the run's (test_determinism.py)


def _wait_until_pending(pid: int, signum: int) -> None:
    """Until `signum` waits to be delivered to the (stopped) process `pid` (its pending masks in /proc)."""
    import time

    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        masks = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
        if any(int(masks[key].strip(), 16) >> (signum - 1) & 1 for key in ("SigPnd", "ShdPnd")):
            return
        time.sleep(0.05)
    raise AssertionError(f"signal {signum} never reached process {pid}")


def _wait_until_stopped(driver: int, count: int) -> list[int]:
    """The pids of `count` processes below `driver` that have stopped themselves (state T in /proc)."""
    import time

    from riskplan.util.interrupt import descendants

    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        stopped = []
        for pid in descendants(driver):
            try:
                state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            except (OSError, IndexError):
                continue
            if state == "T":
                stopped.append(pid)
        if len(stopped) >= count:
            return stopped
        time.sleep(0.1)
    raise AssertionError(f"fewer than {count} jobs stopped themselves in time")
