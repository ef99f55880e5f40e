"""Hostile or careless input must not lose or mix a sweep's results: one writer per sweep job folder and per sweep
directory, no workers left behind by a killed driver, job folders that stay inside the sweep directory, and the job
limit. Real `riskplan sweep` subprocesses, kept tiny. Folder names, sizes and status files are unit-tested in
test_grid.py and tests/experiments/test_sweep_worker.py."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from support import CLI, TINY, alive, files, riskplan_cli
from typer.testing import CliRunner

from riskplan import compose
from riskplan.cli import app
from riskplan.experiments import driver_watch
from riskplan.experiments.sweep_worker import NAME_MAX, config_sha
from riskplan.util import lock

pytestmark = pytest.mark.slow


# ------------------------------------------------------------------------------------------------ dying workers


def test_a_killed_driver_leaves_no_workers_behind_and_the_sweep_resumes(tmp_path):
    # joblib's loky workers, busy in a job, outlived a SIGKILLed driver (submitit_local's jobs never did)
    args = [
        "sweep",
        "seed=0,1",
        *TINY,
        "train.iterations=800",
        "train.checkpoint_every=20",
        "--jobs",
        "2",
        "hydra.sweep.dir=s",
    ]
    sweep = tmp_path / "s"
    driver = subprocess.Popen(
        [*CLI, *args],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        env=dict(os.environ),
    )
    workers: dict[str, int] = {}
    try:
        deadline = time.time() + 120
        while len(workers) < 2 and time.time() < deadline and driver.poll() is None:
            for job in ("seed=0", "seed=1"):
                try:
                    status = json.loads((sweep / job / "status.json").read_text())
                except (OSError, ValueError):
                    continue
                if status.get("status") == "running":
                    workers[job] = status["pid"]
            time.sleep(0.05)
        assert len(workers) == 2, f"the jobs did not start: {workers}, driver exit {driver.poll()}"
        assert driver.pid not in workers.values()  # each job in a worker process of its own
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait()
        folders = [sweep / job for job in workers]

        def left() -> list:  # live workers, and job folders still locked (a dying process's threads hold it)
            return [pid for pid in workers.values() if alive(pid)] + [f for f in folders if lock.holder(f)]

        deadline = time.time() + 10
        while left() and time.time() < deadline:
            time.sleep(0.1)
        assert not left(), "workers outlived the killed driver"
    finally:  # whatever is left of the processes this test started (its own session and the workers)
        for kill, pid in [(os.killpg, driver.pid), *((os.kill, pid) for pid in workers.values())]:
            try:
                kill(pid, signal.SIGKILL)
            except OSError:
                pass
        driver.wait()

    again = riskplan_cli(tmp_path, *args)
    assert again.returncode == 0, again.stdout + again.stderr
    summary = pd.read_parquet(sweep / "summary.parquet")
    assert (summary.status == "done").all() and len(summary) == 2
    for job in ("seed=0", "seed=1"):
        assert len(pd.read_parquet(sweep / job / "metrics.parquet")) == 800


def descendants(pid: int) -> set[int]:
    """The processes below `pid` now (children of any of its threads, theirs, ...)."""
    found, todo = set(), [pid]
    while todo:
        for task in Path(f"/proc/{todo.pop()}/task").glob("*"):
            try:
                children = {int(c) for c in (task / "children").read_text().split()}
            except OSError:
                continue
            todo += children - found
            found |= children
    return found


@pytest.mark.parametrize("loaded", [False, True], ids=["idle", "loaded"])
def test_kill_9_of_a_driver_as_its_workers_start_leaves_no_process_of_it_and_nothing_written_after(tmp_path, loaded):
    # the workers that a driver killed as they started outlived it before they ran a job (they were watched from
    # their first job on); a busy-loop process on each core makes it the loaded case
    hogs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() if loaded else 0)
    ]
    driver = subprocess.Popen(
        [*CLI, "sweep", "seed=range(0,8)", *TINY, "train.iterations=50", "--jobs", "2", "hydra.sweep.dir=s"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    seen: set[int] = set()
    try:
        deadline = time.time() + 120
        while (
            sum("LokyProcess" in cmdline(pid) for pid in seen) < 2 and time.time() < deadline and driver.poll() is None
        ):
            seen |= descendants(driver.pid)
            time.sleep(0.02)
        assert sum("LokyProcess" in cmdline(pid) for pid in seen) == 2, (
            f"no workers started (driver exit {driver.poll()})"
        )
        name = driver_watch.identity(driver.pid)
        seen |= descendants(driver.pid)
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait()
        written = files(tmp_path / "s")

        def left() -> set[int]:
            return {pid for pid in seen if alive(pid)} | set(driver_watch.leftovers(name))

        deadline = time.monotonic() + 5
        while left() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not left(), [cmdline(pid) for pid in left()]
        assert files(tmp_path / "s") == written
    finally:
        for pid in [driver.pid, *seen, *(hog.pid for hog in hogs)]:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        for proc in [driver, *hogs]:
            proc.wait()


def test_a_rerun_ends_what_a_killed_driver_of_its_folder_left_and_says_so_in_one_line(tmp_path):
    # a killed sweep whose guardian was killed too: its name in the folder, a process of it still running
    gone = subprocess.Popen(["sleep", "60"])
    name = driver_watch.identity(gone.pid)
    gone.kill()
    gone.wait()
    leftover = subprocess.Popen(["sleep", "600"], env={**os.environ, driver_watch.ENV: name})
    try:
        (tmp_path / "s").mkdir()
        (tmp_path / "s" / driver_watch.DRIVER_FILE).write_text(name)
        result = riskplan_cli(tmp_path, "sweep", "seed=0", *TINY, "hydra.sweep.dir=s")
        assert result.returncode == 0, result.stdout + result.stderr
        ended = [line for line in result.stdout.splitlines() if line.startswith("ended ")]
        assert ended == [
            f"ended 1 process left running by this folder's earlier sweep (its driver, pid {gone.pid}, was killed): "
            f"pid {leftover.pid}"
        ]
        assert leftover.wait(timeout=10) == -signal.SIGKILL
        assert not (tmp_path / "s" / driver_watch.DRIVER_FILE).exists()  # this sweep's own name went as it ended
    finally:
        leftover.kill()
        leftover.wait()


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return ""


# ------------------------------------------------------------------------------------------------ locks


def test_a_job_folder_held_by_another_process_is_left_alone(tmp_path):
    held = tmp_path / "s" / "seed=0"
    held.mkdir(parents=True)
    (tmp_path / "s" / "sweep.log").write_text("")  # the sweep's directory, its job seed=0 running elsewhere
    planted = {
        "status.json": json.dumps(
            {"status": "running", "config_sha": config_sha(compose([*TINY, "seed=0"])), "pid": os.getpid()}
        ),
        "run.mcap": "someone else's log",
    }
    for name, text in planted.items():
        (held / name).write_text(text)
    with lock.hold_lock(held, "test"):
        before = files(held)
        result = riskplan_cli(tmp_path, "sweep", "seed=0,1", *TINY, "hydra.sweep.dir=s", "--jobs", "64")
        after = files(held)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "(joblib, 2 workers)" in result.stdout  # --jobs 64 is capped at the jobs to run
    # Hydra writes .hydra/ (and opens job.log) before the job runs; the job itself touched nothing
    assert {k: v for k, v in after.items() if not k.startswith(".hydra") and k != "job.log"} == before
    assert after.get("job.log", b"") == b""
    summary = pd.read_parquet(tmp_path / "s" / "summary.parquet").set_index("job")
    assert summary.loc["seed=1", "status"] == "done"
    assert summary.loc["seed=0", "status"] == "running"
    assert f"running in another process (pid {os.getpid()})" in summary.loc["seed=0", "error"]

    # once that process is gone, the next run of the sweep takes the folder over
    again = riskplan_cli(tmp_path, "sweep", "seed=0,1", *TINY, "hydra.sweep.dir=s")
    assert again.returncode == 0, again.stdout + again.stderr
    assert "2 jobs: 1 to run, 1 already finished" in again.stdout
    assert json.loads((held / "status.json").read_text())["status"] == "done"


def test_a_second_driver_on_the_same_sweep_directory_is_bad_input(tmp_path):
    sweep = tmp_path / "s"
    sweep.mkdir()
    with lock.hold_lock(sweep, "test"):
        before = files(tmp_path)
        result = riskplan_cli(tmp_path, "sweep", "seed=0,1", *TINY, "hydra.sweep.dir=s")
        assert files(tmp_path) == before
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"error: s: is in use by another riskplan process (pid {os.getpid()})"
    ), result.stderr
    assert sorted(p.name for p in sweep.iterdir()) == [".riskplan.lock"]


# ------------------------------------------------------------------------------------------------ folder names


def test_swept_values_with_path_syntax_stay_direct_children_of_the_sweep_directory(tmp_path):
    long = "n" * 300
    args = [
        "sweep",
        "team.address=a/b,../../x,%2F,..,'sp ace'," + long,  # free text (a source's name is at most 64 characters)
        "seed=0",
        *TINY,
        "hydra.sweep.dir=deep/s",
    ]
    result = riskplan_cli(tmp_path, *args)
    assert result.returncode == 0, result.stdout + result.stderr
    sweep = tmp_path / "deep" / "s"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["deep"]
    assert sorted(p.name for p in (tmp_path / "deep").iterdir()) == ["s"]
    found = sorted(sweep.rglob("overrides.yaml"))
    assert len(found) == 6
    for file in found:
        assert file.parent.parent.parent == sweep, file  # <sweep>/<job>/.hydra/overrides.yaml
    names = sorted(file.parent.parent.name for file in found)
    assert len(set(names)) == 6 and all(len(n.encode()) <= NAME_MAX for n in names)
    assert "team.address=a%2Fb" in names and "team.address=..%2F..%2Fx" in names
    summary = pd.read_parquet(sweep / "summary.parquet")
    assert len(summary) == 6 and (summary.status == "done").all()
    assert sorted(summary["team.address"]) == sorted(["a/b", "../../x", "%2F", "..", "sp ace", long])
    again = riskplan_cli(tmp_path, *args)
    assert again.returncode == 0 and "6 jobs: 0 to run, 6 already finished" in again.stdout


# ------------------------------------------------------------------------------------------------ sizes


def test_the_job_limit_can_be_raised_and_lowered(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # in this process: bad input needs no start-up of its own
    monkeypatch.setenv("RISKPLAN_MAX_JOBS", "2")
    small = CliRunner().invoke(app, ["sweep", "seed=range(0,3)", *TINY])
    assert small.exit_code == 2
    assert small.stderr.strip() == (
        "error: override 'seed=range(0,3)': expands to 3 jobs, more than the 2 allowed; "
        "sweep fewer values, or raise the limit with RISKPLAN_MAX_JOBS=<jobs>"
    )
    assert not (tmp_path / "outputs").exists()
