"""Determinism: the same config and seed give the same numbers across repeated runs, numbers of threads, launchers
(in-process API, `riskplan train` in a subprocess, `riskplan sweep` with one or two parallel jobs) and resume (see
test_resume.py); different seeds give independent streams."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_resume import FAST, TEAM, assert_same_outputs, run_cli, train_cli

from riskplan import compose
from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.run.build import build_setup, starts
from riskplan.run.training import train


def job_dirs(sweep: Path) -> dict[int, Path]:
    """The job folders of a sweep, by seed (read from each job's resolved config, not from the folder name)."""
    jobs = {}
    for config in sweep.glob("*/.hydra/config.yaml"):
        jobs[int(yaml.safe_load(config.read_text())["seed"])] = config.parent.parent
    return jobs


def test_same_numbers_across_threads_jobs_and_launchers(tmp_path):
    plain = tmp_path / "train_1_thread"
    result = train_cli([*FAST, "seed=1"], plain, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    assert result.returncode == 0, result.stderr

    sweeps = {}
    for jobs in (1, 2):
        sweeps[jobs] = tmp_path / f"sweep_jobs_{jobs}"
        result = run_cli(
            ["sweep", *FAST, "seed=0,1", "--jobs", str(jobs), f"hydra.sweep.dir={sweeps[jobs]}"],
            tmp_path,
            NUMBA_NUM_THREADS="2",
        )
        assert result.returncode == 0, result.stdout + result.stderr
    one, two = job_dirs(sweeps[1]), job_dirs(sweeps[2])
    assert set(one) == set(two) == {0, 1}

    api = tmp_path / "api"
    train(compose([*FAST, "seed=1"]), api)  # in this process: numba's default thread count

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
    config = compose([*FAST, "train.iterations=8", "risk=neutral"])
    train(config, tmp_path / "a")
    train(config, tmp_path / "b")
    assert_same_outputs(tmp_path / "b", tmp_path / "a")


def test_seeds_give_different_runs(tmp_path):
    for seed in (0, 1):
        train(compose([*FAST, "train.iterations=3", f"seed={seed}"]), tmp_path / str(seed))
    with pytest.raises(AssertionError):
        assert_same_outputs(tmp_path / "1", tmp_path / "0")


def test_stream_keys_are_distinct_for_every_seed_purpose_iteration_and_robot():
    purposes = (rng.TRAIN, rng.EVAL, rng.PATHS, rng.BOOTSTRAP, rng.LANDSCAPE)
    keys = [
        rng.stream_key(seed, purpose, iteration, robot)
        for seed, purpose, iteration, robot in itertools.product(range(20), purposes, range(40), range(4))
    ]
    assert len(set(keys)) == len(keys)
    assert len({rng.stream_key(seed) for seed in range(-1000, 1000)}) == 2000


def test_different_seeds_give_independent_episode_streams():
    setup = build_setup(compose([]))
    theta = np.tile(setup.theta0, (1, 1))
    episodes = 20_000
    rewards = {}
    for seed in (0, 1, 2):
        batch = simulate(
            setup.world, setup.kernel, theta, starts(setup)[:1], rng.robot_keys(seed, rng.TRAIN, 0, 1), episodes
        )
        rewards[seed] = batch.total_reward
    for a, b in itertools.combinations(rewards, 2):
        # Same policy, so the same distribution; independent streams: no shared draws, no correlation.
        assert not set(rewards[a]) & set(rewards[b])
        assert abs(np.corrcoef(rewards[a], rewards[b])[0, 1]) < 0.03  # 4 standard errors at n = 20000
        assert abs(np.corrcoef(rewards[a][1:], rewards[b][:-1])[0, 1]) < 0.03  # nor a shifted copy
        assert abs(rewards[a].mean() - rewards[b].mean()) < 5 * rewards[a].std() / np.sqrt(episodes / 2)
