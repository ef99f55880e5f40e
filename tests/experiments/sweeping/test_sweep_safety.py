"""Hostile or careless input must not lose or mix a sweep's results (issue 10): one writer per sweep job folder and
per sweep directory, no workers left behind by a killed driver, job folders that stay inside the sweep directory,
bounded sizes, strict status files. Real `riskplan sweep` subprocesses, kept tiny."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from riskplan.experiments.sweep_worker import NAME_MAX, folder_name, write_status
from riskplan.experiments.sweeping import sweep_size
from riskplan.run.compose import parse_overrides
from riskplan.util import lock
from riskplan.util.errors import BadInput

TINY = ["train.iterations=3", "train.samples=200", "train.eval_episodes=200", "train.bootstrap=10", "train.paths=1"]
CLI = [sys.executable, "-c", "from riskplan.cli import main; main()"]


def riskplan(cwd: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*CLI, *args], cwd=cwd, capture_output=True, text=True, timeout=300, env={**os.environ, **(env or {})}
    )


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def alive(pid: int) -> bool:
    """Whether pid is a live process (a zombie, state Z, counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


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

    again = riskplan(tmp_path, *args)
    assert again.returncode == 0, again.stdout + again.stderr
    summary = pd.read_parquet(sweep / "summary.parquet")
    assert (summary.status == "done").all() and len(summary) == 2
    for job in ("seed=0", "seed=1"):
        assert len(pd.read_parquet(sweep / job / "metrics.parquet")) == 800


# ------------------------------------------------------------------------------------------------ locks


def test_a_job_folder_held_by_another_process_is_left_alone(tmp_path):
    held = tmp_path / "s" / "seed=0"
    held.mkdir(parents=True)
    planted = {
        "status.json": json.dumps({"status": "running", "config_sha": "0" * 16, "pid": os.getpid()}),
        "checkpoint": "someone else's",
        "run.mcap": "someone else's log",
    }
    for name, text in planted.items():
        (held / name).write_text(text)
    with lock.hold(held, "test"):
        before = files(held)
        result = riskplan(tmp_path, "sweep", "seed=0,1", *TINY, "hydra.sweep.dir=s", "--jobs", "64")
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
    again = riskplan(tmp_path, "sweep", "seed=0,1", *TINY, "hydra.sweep.dir=s")
    assert again.returncode == 0, again.stdout + again.stderr
    assert "2 jobs: 1 to run, 1 already finished" in again.stdout
    assert json.loads((held / "status.json").read_text())["status"] == "done"


def test_a_second_driver_on_the_same_sweep_directory_is_bad_input(tmp_path):
    sweep = tmp_path / "s"
    sweep.mkdir()
    with lock.hold(sweep, "test"):
        before = files(tmp_path)
        result = riskplan(tmp_path, "sweep", "seed=0,1", *TINY, "hydra.sweep.dir=s")
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
        "world.sources.0.name=a/b,../../x,%2F,..,'sp ace'," + long,
        "seed=0",
        *TINY,
        "hydra.sweep.dir=deep/s",
    ]
    result = riskplan(tmp_path, *args)
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
    assert "world.sources.0.name=a%2Fb" in names and "world.sources.0.name=..%2F..%2Fx" in names
    summary = pd.read_parquet(sweep / "summary.parquet")
    assert len(summary) == 6 and (summary.status == "done").all()
    assert sorted(summary["world.sources.0.name"]) == sorted(["a/b", "../../x", "%2F", "..", "sp ace", long])
    again = riskplan(tmp_path, *args)
    assert again.returncode == 0 and "6 jobs: 0 to run, 6 already finished" in again.stdout


def test_folder_names_are_plain_for_plain_values_and_never_collide():
    assert folder_name("risk.beta=0.1,seed=0") == "risk.beta=0.1,seed=0"
    assert folder_name("train.step_size.initial=1e+308") == "train.step_size.initial=1e+308"
    tricky = [
        "a/b",
        "a%2Fb",
        "a%252Fb",
        "..",
        ".",
        "",
        "a\x00b",
        "a b",
        "é",
        "%h" + "0" * 16,
        "x" * 300,
        "x" * 299 + "y",
        "x" * 253,
        "x" * 254 + "%",
        "%empty",
        ".hidden",
        "%2Ehidden",
        "a\\b",
        "a:b",
    ]
    names = [folder_name(t) for t in tricky]
    assert len(set(names)) == len(tricky)
    for name in names:
        assert "/" not in name and "\x00" not in name and name not in ("", ".", "..") and not name.startswith(".")
        assert len(name.encode()) <= NAME_MAX
        assert set(name) <= set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._=,+-%")


# ------------------------------------------------------------------------------------------------ sizes


@pytest.mark.parametrize(
    "args, count",
    [
        (["seed=range(0,100000000)"], 100_000_000),
        (["seed=range(0,10,3)", "risk=neutral,cvar"], 8),
        (["seed=range(5,0,-1)", "train.iterations=5"], 5),
        (["risk.beta=range(0.1,0.5,0.1)"], 4),
        (["risk=glob(*)", "seed=0,1"], 4),
        (["seed=shuffle(range(0,3))"], 3),
        (["seed=range(0,0)"], 0),
        (["seed=range(0,100000000000000000000000000000)"], 10**29),  # more than a C integer holds
        (["risk.beta=range(0,1,0.3)"], 4),
    ],
)
def test_a_sweep_is_counted_without_expanding_it(args, count):
    assert sweep_size(parse_overrides(args))[0] == count


@pytest.mark.parametrize("arg", ["risk.beta=range(0,inf)", "risk.beta=range(0,nan)", "seed=range(0,5,0)"])
def test_a_range_without_an_end_or_a_step_is_bad_input(arg):
    with pytest.raises(BadInput, match=re.escape(f"override '{arg}': has a range")):
        sweep_size(parse_overrides([arg]))


def test_the_job_limit_can_be_raised_and_lowered(tmp_path):
    small = riskplan(tmp_path, "sweep", "seed=range(0,3)", *TINY, env={"RISKPLAN_MAX_JOBS": "2"})
    assert small.returncode == 2
    assert small.stderr.strip() == (
        "error: override 'seed=range(0,3)': expands to 3 jobs, more than the 2 allowed; "
        "sweep fewer values, or raise the limit with RISKPLAN_MAX_JOBS=<jobs>"
    )
    assert not (tmp_path / "outputs").exists()


def test_reproduce_seeds_are_bounded(tmp_path):
    result = riskplan(tmp_path, "reproduce", "--seeds", "40", env={"RISKPLAN_MAX_JOBS": "100"})
    assert result.returncode == 2 and "RISKPLAN_MAX_JOBS" in result.stderr and len(result.stderr.splitlines()) == 1
    result = riskplan(tmp_path, "reproduce", "--seeds", "3", env={"RISKPLAN_MAX_HOURS": "0.0001"})
    assert result.returncode == 2 and "RISKPLAN_MAX_HOURS" in result.stderr and len(result.stderr.splitlines()) == 1
    assert not (tmp_path / "outputs").exists()


# ------------------------------------------------------------------------------------------------ status files


def test_status_json_is_strict_json_and_leaves_no_temp_file(tmp_path):
    write_status(
        tmp_path,
        {
            "status": "done",
            "cvar": float("nan"),
            "figures": [1.0, float("inf"), -float("inf")],
            "nested": {"x": float("nan")},
        },
    )

    def refuse(name):
        raise AssertionError(f"non-standard JSON constant {name}")

    record = json.loads((tmp_path / "status.json").read_text(), parse_constant=refuse)
    assert record == {"status": "done", "cvar": None, "figures": [1.0, None, None], "nested": {"x": None}}
    assert [p.name for p in tmp_path.iterdir()] == ["status.json"]
