"""Checkpoints committed beside the loop (riskplan.run.recorder.Commits): the state as it was when its checkpoint
was due, whatever the loop does to its arrays meanwhile; one commit at a time; a failure handed to the run when it
is known."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import riskplan.run.recorder as recorder
from riskplan.engine.step import TrainState
from riskplan.run.checkpoint import CHECKPOINT, CHECKPOINT_TMP
from riskplan.run.recorder import Commits


class Log:
    def __init__(self):
        self.fsyncs = 0

    def fsync(self):
        self.fsyncs += 1


def driver(out: Path, state: TrainState) -> SimpleNamespace:
    out.mkdir(parents=True, exist_ok=True)
    return SimpleNamespace(out=out, log=Log(), state=state)


def test_a_commit_writes_the_state_as_it_was_due_while_the_loop_changes_its_arrays(tmp_path, monkeypatch):
    release, real = threading.Event(), recorder.save_checkpoints

    def held(outs, states, logs):  # the commit waits until the loop has moved on
        release.wait()
        return real(outs, states, logs)

    monkeypatch.setattr(recorder, "save_checkpoints", held)
    buffer = np.array([[1.0, 2.0]])
    state = TrainState(10, np.array([[3.0, 4.0]]), {"inbox": buffer})
    run = driver(tmp_path / "run", state)
    commits = Commits()
    commits.start([0], [run])
    buffer[:] = -1.0  # the loop reuses its buffers in place
    state.thetas[:] = -1.0
    release.set()
    assert commits.wait() == []
    saved = json.loads((tmp_path / "run" / CHECKPOINT).read_text())
    assert saved["iteration"] == 10 and saved["thetas"] == [[3.0, 4.0]] and saved["mixer"]["inbox"] == [[1.0, 2.0]]
    assert run.log.fsyncs == 1  # the log first, so the checkpoint never gets ahead of it
    assert commits.wait() == []  # nothing in flight: nothing to wait for


def test_a_commit_that_fails_names_its_runs_with_their_errors(tmp_path, monkeypatch):
    refused = OSError(28, "No space left on device")
    monkeypatch.setattr(recorder, "save_checkpoints", lambda outs, states, logs: [None, refused])
    state = TrainState(5, np.zeros((1, 2)), {})
    commits = Commits()
    commits.start([3, 7], [driver(tmp_path / "a", state), driver(tmp_path / "b", state)])
    assert commits.wait() == [(7, refused)]


def test_a_fault_of_the_whole_commit_is_every_runs(tmp_path, monkeypatch):
    def broken(outs, states, logs):
        raise RuntimeError("boom")

    monkeypatch.setattr(recorder, "save_checkpoints", broken)
    state = TrainState(5, np.zeros((1, 2)), {})
    commits = Commits()
    commits.start([0, 1], [driver(tmp_path / "a", state), driver(tmp_path / "b", state)])
    errors = commits.wait()
    assert [r for r, _ in errors] == [0, 1] and all(isinstance(e, RuntimeError) for _, e in errors)


@pytest.mark.slow  # two runs
@pytest.mark.parametrize("every", [1, 2])
def test_the_last_checkpoint_is_on_disk_when_a_run_finishes(tmp_path, every):
    """Every iteration (a commit each, the one before waited for) or a commit then the last: the loop's end waits
    for the one in flight, before the finished files."""
    from support import TINY

    from riskplan import compose, train

    train(compose([*TINY, f"train.checkpoint_every={every}"]), tmp_path / "run", progress=False)
    assert json.loads((tmp_path / "run" / CHECKPOINT).read_text())["iteration"] == 3
    assert not (tmp_path / "run" / CHECKPOINT_TMP).exists()
