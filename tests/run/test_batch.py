"""Runs trained as one batch (riskplan.run.batch): each run's files are bit for bit those of the same run alone,
a run that fails leaves the batch alone, and a batch stopped by a signal resumes to the same numbers."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest
from support import CHECKPOINTED, TINY, assert_same_outputs

from riskplan.engine.step import batch_key, batched_rollouts, rollouts
from riskplan.run.batch import BatchRun, train_batch
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.run.training import train_summary
from riskplan.util.interrupt import Interrupted

# Different seeds, measures, levels, step sizes, theta_0, team sizes and graphs: one world, one sample schedule.
RUNS = {
    "cvar": ["seed=0"],
    "neutral": ["seed=1", "risk=neutral", "train.step_size.initial=0.05"],
    "beta": ["seed=2", "risk.beta=0.3", "train.theta0=[10,30]"],
    "team": ["seed=3", "experiment=paper_team", "team.delay.max=1", "team.drop=0.1"],
    "ring": ["seed=4", "experiment=paper_team", "team.robots=4", "team.graph=ring", "risk=wang"],
}


def setups(base, names=RUNS):
    return {name: build_setup(compose([*base, *RUNS[name]])) for name in names}


def alone(tmp_path, built):
    for name, setup in built.items():
        train_summary(setup, tmp_path / "alone" / name)
    return tmp_path / "alone"


@pytest.mark.slow  # over a second
def test_the_runs_share_a_batch_key_and_their_episodes_are_their_own():
    built = setups(TINY)
    assert len({batch_key(s.params) for s in built.values()}) == 1
    assert batch_key(build_setup(compose([*TINY, "world.horizon=21"])).params) != batch_key(built["cvar"].params)
    for l in (0, 2):
        thetas = [np.tile(s.theta0, (s.robots, 1)) + 0.5 * i for i, s in enumerate(built.values())]
        together = batched_rollouts(list(built.values()), l, thetas)
        for (z, scores), setup, theta in zip(together, built.values(), thetas):
            want_z, want_scores = rollouts(setup, l, theta)
            np.testing.assert_array_equal(z, want_z)
            np.testing.assert_array_equal(scores, want_scores)


@pytest.mark.slow  # over a second
def test_every_run_of_a_batch_is_the_same_run_alone(tmp_path):
    built = setups(TINY)
    reference = alone(tmp_path, built)
    seen = []
    runs = train_batch(
        [BatchRun(setups(TINY, [name])[name], tmp_path / "batch" / name) for name in RUNS],
        progress=lambda done, total: seen.append((done, total)),
    )
    assert all(run.error is None and run.summary is not None for run in runs)
    for name in RUNS:
        assert_same_outputs(tmp_path / "batch" / name, reference / name)
    assert seen[-1] == (5 * 3, 5 * 3) and [d for d, _ in seen] == sorted(d for d, _ in seen)


@pytest.mark.slow  # over a second
def test_a_run_that_fails_leaves_the_batch_alone(tmp_path):
    built = setups(TINY, ["cvar", "team"])
    reference = alone(tmp_path, built)
    (tmp_path / "batch" / "taken").mkdir(parents=True)
    (tmp_path / "batch" / "taken" / "summary.json").write_text("{}")  # another run's directory: bad input
    runs = [
        BatchRun(setups(TINY, ["cvar"])["cvar"], tmp_path / "batch" / "cvar"),
        BatchRun(build_setup(compose([*TINY, "train.step_size.initial=1e308"])), tmp_path / "batch" / "diverges"),
        BatchRun(setups(TINY, ["team"])["team"], tmp_path / "batch" / "team"),
        BatchRun(setups(TINY, ["cvar"])["cvar"], tmp_path / "batch" / "taken"),
    ]
    train_batch(runs)
    assert "theta or its gradient is not finite" in str(runs[1].error) and runs[1].summary is None
    assert "already holds a run" in str(runs[3].error)
    for name in ("cvar", "team"):
        assert_same_outputs(tmp_path / "batch" / name, reference / name)
    assert not (tmp_path / "batch" / "diverges" / "summary.json").exists()


@pytest.mark.slow  # over a second
def test_a_run_whose_checkpoint_the_disk_refuses_leaves_the_batch_alone(tmp_path, monkeypatch):
    """The round's checkpoints are written together (one group commit); one that fails (a full disk) stops its run
    alone, with its checkpoints so far kept and its log readable, and the others finish as they would alone."""
    import riskplan.run.checkpoint as checkpoint
    from riskplan.run.results import load_run

    names = ["cvar", "team", "ring"]
    built = setups(CHECKPOINTED, names)
    reference = alone(tmp_path, built)
    real = checkpoint._write_temp

    def full_disk(out, payload):
        if out.name == "team" and payload["iteration"] == 15:
            raise OSError(28, "No space left on device")
        real(out, payload)

    monkeypatch.setattr(checkpoint, "_write_temp", full_disk)
    runs = train_batch([BatchRun(built[n], tmp_path / "batch" / n) for n in names])
    assert isinstance(runs[1].error, OSError) and runs[1].summary is None
    assert json.loads((tmp_path / "batch" / "team" / "checkpoint").read_text())["iteration"] == 10
    assert list(load_run(tmp_path / "batch" / "team").metrics.query("robot == 0").iteration) == list(range(15))
    for name in ("cvar", "ring"):
        assert_same_outputs(tmp_path / "batch" / name, reference / name)


@pytest.mark.slow  # over a second
def test_a_batch_stopped_by_a_signal_resumes_to_the_same_numbers(tmp_path):
    names = ["cvar", "team", "ring"]
    built = setups(CHECKPOINTED, names)
    reference = alone(tmp_path, built)

    def interrupt(done, total):
        if done == 3 * 7:  # mid-run, between two checkpoints (every 5 iterations)
            os.kill(os.getpid(), signal.SIGINT)

    first = [BatchRun(setups(CHECKPOINTED, [n])[n], tmp_path / "batch" / n) for n in names]
    with pytest.raises(Interrupted):
        train_batch(first, progress=interrupt)
    again = [BatchRun(setups(CHECKPOINTED, [n])[n], tmp_path / "batch" / n, resume=True) for n in names]
    train_batch(again)
    for name in names:
        assert_same_outputs(tmp_path / "batch" / name, reference / name)


@pytest.mark.slow  # about a second
def test_each_run_of_a_batch_calibrates_with_its_part_of_the_batchs_time(tmp_path, monkeypatch):
    import time

    from riskplan.run import cost

    monkeypatch.setenv(cost.CACHE_ENV, str(tmp_path / "cache"))
    names = ["cvar", "team", "ring"]
    tic = time.perf_counter()
    train_batch([BatchRun(setups(TINY, [n])[n], tmp_path / n) for n in names])
    whole = time.perf_counter() - tic
    records = json.loads(cost.cache_file().read_text())["runs"]
    assert [steps for steps, _ in records] == [cost.setup_steps(setups(TINY, [n])[n]) for n in names]
    assert sum(seconds for _, seconds in records) <= whole  # parts of the batch, not the batch once per run


@pytest.mark.slow  # two batches trained, evaluated and written (near a second)
def test_a_batch_syncs_its_finished_files_once_and_a_refused_sync_fails_its_runs(tmp_path, monkeypatch):
    """A batch's finished files are written without an fsync each and made durable by one syncfs per file system
    for all its runs, before the runs count as done; a disk that refuses that sync fails them (their files may not
    have reached it), and nothing fsyncs file by file meanwhile."""
    import riskplan.run.batch as batch

    if not batch.can_sync_file_systems():
        pytest.skip("this system has no syncfs: a batch's runs sync their files one by one")
    names = ["cvar", "neutral"]
    synced, fsyncs = [], []
    real_fsync = os.fsync
    monkeypatch.setattr(batch, "sync_file_systems", lambda folders: synced.append(sorted(f.name for f in folders)))
    runs = train_batch([BatchRun(setups(TINY, [n])[n], tmp_path / "ok" / n) for n in names])
    assert all(run.summary is not None for run in runs) and synced == [names]

    def refused(folders):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(batch, "sync_file_systems", refused)
    monkeypatch.setattr(os, "fsync", lambda fd: (fsyncs.append(fd), real_fsync(fd)))
    runs = train_batch([BatchRun(setups(TINY, [n])[n], tmp_path / "refused" / n) for n in names])
    assert all(isinstance(run.error, OSError) and run.summary is None for run in runs)
    finished_files = {"summary.json", "metrics.parquet", "eval.parquet", "trajectories.parquet"}
    assert finished_files <= {p.name for p in (tmp_path / "refused" / "cvar").iterdir()}
    assert len(fsyncs) <= 2 * len(names)  # the checkpoints' (TINY: one each, at the end); none for the files
