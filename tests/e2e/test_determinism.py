"""Determinism of whole runs: the same config and seed give the same numbers across repeated runs, numbers of
threads and launchers (in-process API, `riskplan train` in a subprocess, `riskplan sweep` with one or two parallel
jobs), and resume (see test_kill_and_resume.py); different seeds give different runs. The streams themselves are
checked in tests/engine/test_rng.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from support import CHECKPOINTED, CHECKPOINTED_TEAM, assert_same_outputs, run_cli, train_cli

from riskplan import compose
from riskplan.run.training import train

pytestmark = pytest.mark.slow

RUN, TEAM = CHECKPOINTED, CHECKPOINTED_TEAM  # 30 iterations: several checkpoints, a team with delays and drops


def job_dirs(sweep: Path) -> dict[int, Path]:
    """The job folders of a sweep, by seed (read from each job's resolved config, not from the folder name)."""
    jobs = {}
    for config in sweep.glob("*/.hydra/config.yaml"):
        jobs[int(yaml.safe_load(config.read_text())["seed"])] = config.parent.parent
    return jobs


def test_same_numbers_across_threads_jobs_and_launchers(tmp_path, uninterrupted):
    plain = uninterrupted(1)  # `riskplan train` of RUN, seed=1, in one thread (conftest.py)

    sweeps = {}
    for jobs in (1, 2):
        sweeps[jobs] = tmp_path / f"sweep_jobs_{jobs}"
        result = run_cli(
            ["sweep", *RUN, "seed=0,1", "--jobs", str(jobs), f"hydra.sweep.dir={sweeps[jobs]}"],
            tmp_path,
            NUMBA_NUM_THREADS="2",
        )
        assert result.returncode == 0, result.stdout + result.stderr
    one, two = job_dirs(sweeps[1]), job_dirs(sweeps[2])
    assert set(one) == set(two) == {0, 1}

    api = tmp_path / "api"
    train(compose([*RUN, "seed=1"]), api)  # in this process: numba's default thread count

    for other in (one[1], two[1], api):
        assert_same_outputs(other, plain)
    assert_same_outputs(two[0], one[0])


def test_team_numbers_do_not_depend_on_the_thread_count(tmp_path):
    runs = {}
    for threads in ("1", "2"):
        runs[threads] = tmp_path / f"threads_{threads}"
        result = train_cli(TEAM, runs[threads], NUMBA_NUM_THREADS=threads, OMP_NUM_THREADS=threads)
        assert result.returncode == 0, result.stderr
    assert_same_outputs(runs["2"], runs["1"])


def test_repeated_runs_in_one_process_are_identical(tmp_path):
    config = compose([*RUN, "train.iterations=8", "risk=neutral"])
    train(config, tmp_path / "a")
    train(config, tmp_path / "b")
    assert_same_outputs(tmp_path / "b", tmp_path / "a")


def test_seeds_give_different_runs(tmp_path):
    for seed in (0, 1):
        train(compose([*RUN, "train.iterations=3", f"seed={seed}"]), tmp_path / str(seed))
    with pytest.raises(AssertionError):
        assert_same_outputs(tmp_path / "1", tmp_path / "0")
