"""The warm-up of a reproduction's local workers (riskplan.experiments.sweeping.launch.warm_workers): it trains tiny
runs in the driver's scratch folder, which the driver's guardian removes, so a worker killed mid-way (a bad input
found after the warm-up began) leaves nothing in the machine's temporary folder."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from support import child_env

from riskplan.experiments.sweep_worker import warm_up
from riskplan.run.recorder import STOP_ENV

pytestmark = pytest.mark.slow

KILLED_MID_WAY = """
import time
from riskplan.experiments import driver_watch
from riskplan.experiments.reproduction import stop_workers
from riskplan.experiments.sweeping.launch import warm_workers

warm_workers(2)
deadline = time.monotonic() + 120
while not list(driver_watch.scratch().glob("warm-up-*/0/run.mcap")) and time.monotonic() < deadline:
    time.sleep(0.05)
print(len(list(driver_watch.scratch().glob("warm-up-*/0/run.mcap"))), flush=True)
stop_workers()  # what a bad input does once the checks end
"""


def test_a_warm_up_killed_mid_way_leaves_nothing_in_the_temporary_folder(tmp_path):
    # STOP_ENV: the warming worker stops itself once iteration 0 is logged, so it is killed mid-way, never done
    env = child_env(TMPDIR=str(tmp_path), **{STOP_ENV: "0"})
    driver = subprocess.run(
        [sys.executable, "-c", KILLED_MID_WAY], env=env, capture_output=True, text=True, timeout=300
    )
    assert driver.returncode == 0 and driver.stdout.split() == ["1"], driver.stdout + driver.stderr
    deadline = time.monotonic() + 10  # the guardian removes the scratch folder once the driver and workers are gone
    while list(tmp_path.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert list(tmp_path.iterdir()) == []


def test_a_finished_warm_up_removes_its_runs_at_once(tmp_path):
    pid, seconds = warm_up(tmp_path)
    assert pid == os.getpid() and seconds > 0
    assert list(tmp_path.iterdir()) == []
