"""Ctrl-C while a sweep's local workers start. It reaches the driver's whole process group, and a worker still
importing (a second or two) printed a traceback from the middle of an import. The driver now spawns its workers with
SIGINT blocked (launch.start_workers); a worker lets it in once its first job handles it (driver_watch.working and
take_interrupts), which then stops that job's set-up, marked interrupted and resumable."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest
from joblib import delayed
from support import TINY, child_env, riskplan_command

from riskplan.experiments.driver_watch import ENV, identity
from riskplan.experiments.reproduction import stop_workers
from riskplan.experiments.sweeping.launch import in_background, start_workers
from riskplan.util.interrupt import sigint_blocked


def blocked_signals() -> int:
    """This process's blocked signals, as the kernel reports them (SigBlk: a hexadecimal bit mask)."""
    return int(Path("/proc/self/status").read_text().split("SigBlk:")[1].split()[0], 16)


SIGINT_BIT = 1 << (signal.SIGINT - 1)


def test_sigint_blocked_holds_a_ctrl_c_back_until_the_block_ends():
    got = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    try:
        with sigint_blocked():
            assert blocked_signals() & SIGINT_BIT
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # to this (main) thread, which blocks it
            assert signal.sigpending() == {signal.SIGINT} and got == []
        assert not blocked_signals() & SIGINT_BIT
        assert got == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.slow  # spawns a pool of workers
def test_workers_start_with_sigint_blocked_and_the_driver_does_not():
    """Starting Python's resource tracker unblocks SIGINT in the spawning thread: start_workers starts it first, so
    every worker inherits the block; the driver's own mask is as it was."""
    stop_workers()  # a pool started before by this session was spawned with another mask
    try:
        masks = in_background(lambda: start_workers(2, [delayed(blocked_signals)() for _ in range(4)]))()
    finally:
        stop_workers()
    assert len(masks) == 4 and all(mask & SIGINT_BIT for mask in masks)
    assert not blocked_signals() & SIGINT_BIT


WORKER = """
import os, signal, sys
from riskplan.experiments import driver_watch
signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # as the driver spawned it
os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while it started
with driver_watch.working():
    try:
        driver_watch.take_interrupts()
    except KeyboardInterrupt:
        print("the job stopped", flush=True)
os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C between jobs
print("still running")
"""


def test_a_worker_takes_a_held_back_ctrl_c_in_its_first_job_and_ends_quietly_when_idle():
    done = subprocess.run(
        [sys.executable, "-c", WORKER],
        env=child_env(**{ENV: identity(os.getpid())}),  # a local worker of this process
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (done.returncode, done.stdout, done.stderr) == (128 + signal.SIGINT, "the job stopped\n", "")


# Slows each local worker's start (Python runs sitecustomize as it starts, before any riskplan code), and says when
# one has begun: a Ctrl-C then lands while it starts, every time.
SLOW_START = """
import os, pathlib, time
if os.environ.get("RISKPLAN_SWEEP_DRIVER") and os.environ.get("SLOW_START_MARK"):
    pathlib.Path(os.environ["SLOW_START_MARK"]).touch()
    time.sleep(1.5)
"""
ARGS = [*TINY, "seed=0,1,2"]
FIGURES = ["mean", "cvar", "value_at_risk"]


@pytest.mark.slow  # three tiny sweeps, one with workers slowed to start
@pytest.mark.parametrize(
    "workers", [["--jobs", "2"], ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]], ids=["jobs", "n_jobs"]
)
def test_ctrl_c_while_the_workers_start_prints_no_traceback_and_the_sweep_resumes(tmp_path, workers):
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(SLOW_START)
    mark = tmp_path / "started"
    env = child_env(PYTHONPATH=os.pathsep.join([str(tmp_path / "site"), os.environ.get("PYTHONPATH", "")]))
    sweep = [*riskplan_command(), "sweep", *ARGS, *workers]
    plain = subprocess.run(
        [*sweep, f"hydra.sweep.dir={tmp_path / 'plain'}"], env=env, capture_output=True, text=True, timeout=300
    )
    assert plain.returncode == 0, plain.stderr

    driver = subprocess.Popen(
        [*sweep, f"hydra.sweep.dir={tmp_path / 's'}"],
        env={**env, "SLOW_START_MARK": str(mark)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's: Ctrl-C goes to the whole group
    )
    deadline = time.time() + 120
    while not mark.exists() and driver.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    assert mark.exists(), "no worker started"
    os.killpg(driver.pid, signal.SIGINT)
    _, stderr = driver.communicate(timeout=300)
    assert driver.returncode == 128 + signal.SIGINT, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    assert stderr.splitlines()[-1].startswith("error: interrupted by SIGINT: 3 jobs did not finish"), stderr

    again = subprocess.run(
        [*sweep, f"hydra.sweep.dir={tmp_path / 's'}"], env=env, capture_output=True, text=True, timeout=300
    )
    assert again.returncode == 0, again.stderr
    after, before = (pd.read_parquet(tmp_path / name / "summary.parquet") for name in ("s", "plain"))
    assert after.status.tolist() == ["done"] * 3
    pd.testing.assert_frame_equal(after[FIGURES], before[FIGURES])
