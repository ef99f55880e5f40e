"""A sweep's local workers end with their driver (riskplan.experiments.driver_watch), with plain processes standing
in for the driver and its workers. `riskplan sweep` itself, SIGKILLed idle and under load, is in
tests/experiments/sweeping/test_sweep_safety.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support import alive

from riskplan.experiments import driver_watch
from riskplan.experiments.driver_watch import DRIVER_FILE, ENV, end_leftovers, identity

GONE = 5.0  # seconds a dead driver's processes may take to go (the bound)


def dead_driver() -> str:
    """The identity of a process that has ended (as a killed driver's is)."""
    proc = subprocess.Popen(["sleep", "60"])
    name = identity(proc.pid)
    proc.kill()
    proc.wait()
    return name


def sleeper(driver: str) -> subprocess.Popen:
    """A process whose environment names `driver`, as its workers' do."""
    return subprocess.Popen(["sleep", "600"], env={**os.environ, ENV: driver})


def python(code: str, driver: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code], env={**os.environ, ENV: driver}, **kwargs)


def written(folder) -> bool:
    """Whether the worker has written its "1" into folder/written."""
    try:
        return (folder / "written").read_text() == "1"
    except FileNotFoundError:
        return False


def wait_gone(pid: int) -> bool:
    deadline = time.monotonic() + GONE
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not alive(pid)


def test_identity_names_a_living_process_by_pid_and_start_time_and_a_dead_one_not_at_all():
    me = identity(os.getpid())
    assert me is not None and me.startswith(f"{os.getpid()}:")
    assert identity(os.getpid()) == me  # the same process, the same name
    name = dead_driver()
    assert identity(int(name.split(":")[0])) != name


def test_a_process_is_a_local_worker_only_of_another_process_on_this_host(monkeypatch):
    monkeypatch.setenv(ENV, identity(os.getpid()))
    assert driver_watch.driver() is None  # the driver itself
    monkeypatch.setenv(ENV, identity(os.getpid()).replace("@", "@elsewhere-"))
    assert driver_watch.driver() is None  # another host's: a cluster's job
    name = dead_driver()
    monkeypatch.setenv(ENV, name)
    assert driver_watch.driver() == name


def test_an_orphan_kills_itself_as_its_job_arrives_and_writes_nothing(tmp_path):
    code = "from riskplan.experiments.driver_watch import arrive; arrive(); open('written', 'w').write('1')"
    orphan = python(code, dead_driver(), cwd=tmp_path)
    assert orphan.wait(timeout=60) == -signal.SIGKILL
    assert not (tmp_path / "written").exists()


def test_a_worker_of_a_living_driver_works_and_dies_with_its_parent_the_moment_it_is_killed(tmp_path):
    # the "driver" starts a worker naming it; the worker arrives (PR_SET_PDEATHSIG) and writes; the driver is
    # SIGKILLed without a guardian, so only the kernel's signal can end the worker
    worker = (
        "from riskplan.experiments.driver_watch import arrive; import time; arrive(); "
        "open('written', 'w').write('1'); time.sleep(600)"
    )
    starter = (
        "import os, subprocess, sys, time; from riskplan.experiments.driver_watch import ENV, identity; "
        f"w = subprocess.Popen([sys.executable, '-c', {worker!r}], env={{**os.environ, ENV: identity(os.getpid())}}); "
        "print(w.pid, flush=True); time.sleep(600)"
    )
    parent = subprocess.Popen([sys.executable, "-c", starter], cwd=tmp_path, stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    try:
        deadline = time.monotonic() + 60
        while not written(tmp_path) and time.monotonic() < deadline:  # its content, not the file: open() comes first
            time.sleep(0.05)
        assert written(tmp_path) and alive(child)
        parent.kill()
        parent.wait()
        assert wait_gone(child)
    finally:
        for pid in (parent.pid, child):
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_the_guardian_ends_every_process_naming_its_driver_once_the_driver_is_killed(tmp_path):
    """...and removes the driver's scratch folder, with what a worker left in it (the warm-up's files)."""
    starter = (
        "import os, subprocess, time; from riskplan.experiments import driver_watch; "
        "driver_watch.name_driver(True); w = subprocess.Popen(['sleep', '600']); "
        "(driver_watch.scratch() / 'warm-up-1').mkdir(); (driver_watch.scratch() / 'warm-up-1' / 'run.mcap').touch(); "
        "print(w.pid, driver_watch._guardian[0].pid, driver_watch.scratch(), flush=True); time.sleep(600)"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", starter], stdout=subprocess.PIPE, text=True, env={**os.environ, "TMPDIR": str(tmp_path)}
    )
    worker, guardian, scratch = parent.stdout.readline().split()
    worker, guardian = int(worker), int(guardian)
    try:
        assert alive(worker) and alive(guardian)
        assert Path(scratch).parent == tmp_path and Path(scratch, "warm-up-1", "run.mcap").is_file()
        parent.kill()
        parent.wait()
        assert wait_gone(worker)
        assert wait_gone(guardian)  # its work done, it ends too
        assert list(tmp_path.iterdir()) == []
    finally:
        for pid in (worker, guardian):
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_a_rerun_ends_the_processes_of_the_killed_driver_named_in_its_folder_and_no_other(tmp_path):
    killed, other = dead_driver(), dead_driver()
    leftover, stranger = sleeper(killed), sleeper(other)
    try:
        (tmp_path / DRIVER_FILE).write_text(killed)
        line = end_leftovers(tmp_path)
        assert line == (
            f"ended 1 process left running by this folder's earlier sweep (its driver, pid {killed.split(':')[0]}, "
            f"was killed): pid {leftover.pid}"
        )
        assert leftover.wait(timeout=10) == -signal.SIGKILL
        assert stranger.poll() is None  # it names another driver
        assert not (tmp_path / DRIVER_FILE).exists()
        assert end_leftovers(tmp_path) is None  # nothing left to end
    finally:
        for proc in (leftover, stranger):
            proc.kill()
            proc.wait()


def test_a_living_driver_named_in_the_folder_is_left_alone(tmp_path):
    (tmp_path / DRIVER_FILE).write_text(identity(os.getpid()))
    assert end_leftovers(tmp_path) is None
    assert (tmp_path / DRIVER_FILE).read_text() == identity(os.getpid())


@pytest.mark.parametrize("local", [True, False])
def test_a_cluster_launch_names_no_driver_so_its_jobs_outlive_it(monkeypatch, local):
    monkeypatch.setattr(driver_watch, "_guardian", [object()])  # no guardian process for this test
    monkeypatch.setenv(ENV, "stale")
    driver_watch.name_driver(local)
    assert os.environ.get(ENV) == (identity(os.getpid()) if local else None)


def test_a_driver_that_exits_with_its_guardian_running_says_nothing_of_it(tmp_path):
    """The guardian outlives its driver by design: a driver that named itself and then exits (a reproduction's bad
    --out, after its workers started) prints no warning about the child still running, so bad input stays one
    line; and the guardian still ends once the driver has."""
    code = (
        "import os, warnings; warnings.simplefilter('always')\n"
        "from riskplan.experiments import driver_watch\n"
        "driver_watch.name_driver(True)\n"
        "print(driver_watch._guardian[0].pid)\n"
    )
    done = subprocess.run([sys.executable, "-X", "dev", "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    guardian = int(done.stdout)
    deadline = time.monotonic() + GONE + 2 * driver_watch.WATCH_SECONDS
    while alive(guardian) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(guardian)


@pytest.mark.slow  # a driver and its guardian started
def test_a_driver_without_a_temporary_folder_still_names_itself_and_its_guardian_ends(tmp_path):
    """No writable temporary folder anywhere (tempfile finds none): the driver goes without a scratch folder (its
    workers skip the warm-up) instead of failing every local sweep with a traceback."""
    code = (
        "import tempfile\n"
        "def nowhere(*args, **kwargs): raise FileNotFoundError('no usable temporary directory')\n"
        "tempfile.mkdtemp = nowhere\n"
        "from riskplan.experiments import driver_watch\n"
        "driver_watch.name_driver(True)\n"
        "print(driver_watch._guardian[0].pid, driver_watch.scratch())\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    guardian, scratch = done.stdout.split()
    assert scratch == "None"
    deadline = time.monotonic() + GONE + 2 * driver_watch.WATCH_SECONDS
    while alive(int(guardian)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(int(guardian))
