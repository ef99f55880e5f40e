"""A batch's checkpoints as one group commit (riskplan.run.checkpoint.save_checkpoints): the same files a run alone
writes, each log synced before its checkpoint becomes visible, a failing run alone left at its checkpoint before,
and the per-run fallback where the system has no syncfs. A checkpoint that cannot be this run's is one line naming
it, for either kind of checkpoint."""

from __future__ import annotations

import json
import resource
import signal

import numpy as np
import pytest
from support import setup_of

import riskplan.run.checkpoint as checkpoint
from riskplan.engine.step import TrainState, initial_state, step
from riskplan.run.checkpoint import (
    CHECKPOINT,
    load_checkpoint,
    load_team_checkpoint,
    save_checkpoint,
    save_checkpoints,
)
from riskplan.util.errors import BadInput


class Log:
    """A stand-in for RunLog: counts its syncs."""

    def __init__(self):
        self.syncs = 0

    def sync(self):
        self.syncs += 1


def states(count: int):
    setups = [setup_of(f"seed={seed}", "experiment=paper_team", "team.delay.max=2") for seed in range(count)]
    return setups, [step(setup, initial_state(setup))[0] for setup in setups]


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
@pytest.mark.parametrize("syncfs", [True, False], ids=["group commit", "run by run"])
def test_the_group_writes_what_each_run_alone_writes(tmp_path, monkeypatch, syncfs):
    if not syncfs:
        monkeypatch.setattr(checkpoint, "_SYNCFS", None)
    elif checkpoint._SYNCFS is None:
        pytest.skip("this system has no syncfs: the group commit falls back to run by run")
    setups, saved = states(3)
    outs = [tmp_path / "group" / str(k) for k in range(3)]
    for out in outs:
        out.mkdir(parents=True)
    logs = [Log() for _ in outs]
    assert save_checkpoints(outs, saved, logs) == [None, None, None]
    assert [log.syncs for log in logs] == ([0, 0, 0] if syncfs else [1, 1, 1])  # the group syncs the disk instead
    for k, (setup, state, out) in enumerate(zip(setups, saved, outs)):
        alone = tmp_path / "alone" / str(k)
        alone.mkdir(parents=True)
        save_checkpoint(alone, state)
        assert (out / CHECKPOINT).read_bytes() == (alone / CHECKPOINT).read_bytes()
        back = load_checkpoint(out, setup)
        assert back.iteration == 1 and np.array_equal(back.thetas, state.thetas)
        assert not (out / checkpoint.CHECKPOINT_TMP).exists()


def test_a_run_whose_temp_file_fails_keeps_its_checkpoint_before_and_the_others_go_on(tmp_path, monkeypatch):
    setups, first = states(2)
    outs = [tmp_path / str(k) for k in range(2)]
    for out in outs:
        out.mkdir()
    save_checkpoints(outs, first, [Log(), Log()])
    second = [step(setup, state)[0] for setup, state in zip(setups, first)]
    real = checkpoint._write_temp

    def full_disk(out, payload):
        if out == outs[0]:
            raise OSError(28, "No space left on device")
        real(out, payload)

    monkeypatch.setattr(checkpoint, "_write_temp", full_disk)
    errors = save_checkpoints(outs, second, [Log(), Log()])
    assert isinstance(errors[0], OSError) and errors[1] is None
    assert json.loads((outs[0] / CHECKPOINT).read_text())["iteration"] == 1
    assert json.loads((outs[1] / CHECKPOINT).read_text())["iteration"] == 2


def refused(load) -> str:
    with pytest.raises(BadInput) as err:
        load()
    return str(err.value)


def test_either_kind_refuses_a_missing_or_damaged_file_in_the_same_words(tmp_path):
    setup = setup_of()
    loads = [lambda: load_checkpoint(tmp_path, setup), lambda: load_team_checkpoint(tmp_path, setup, [])]
    for load in loads:
        assert refused(load) == f"{tmp_path}: has no checkpoint to resume from; start it again with riskplan train"
    (tmp_path / CHECKPOINT).write_text("[]")
    damaged = f"{tmp_path / CHECKPOINT}: is damaged (%s); it was not written by riskplan, which replaces checkpoints "
    damaged += "atomically: start the run again"
    assert refused(loads[0]) == damaged % "TypeError: list indices must be integers or slices, not str"
    assert refused(loads[1]) == damaged % "AttributeError: 'list' object has no attribute 'get'"
    (tmp_path / CHECKPOINT).write_text('{"format": "ray", "robots": []}')
    assert refused(loads[1]) == damaged % "KeyError: 'pending'"
    save_checkpoint(tmp_path, initial_state(setup))
    assert refused(loads[1]) == (
        f"{tmp_path / CHECKPOINT}: holds the checkpoint of a team.backend=simulated run; resume it with the config "
        f"it was started with (only train.iterations may change on resume)"
    )


def test_a_resumed_run_can_only_be_extended(tmp_path):
    setup = setup_of()  # train.iterations=3
    first = initial_state(setup)
    save_checkpoint(tmp_path, TrainState(5, first.thetas, first.mixer))
    assert refused(lambda: load_checkpoint(tmp_path, setup)) == (
        f"train.iterations: got 3, but {tmp_path} is checkpointed at iteration 5; a resumed run can only be "
        f"extended: give train.iterations >= 5"
    )


@pytest.mark.parametrize("group", [False, True], ids=["run by run", "group commit"])
def test_a_checkpoint_the_disk_cannot_hold_leaves_no_temp_file_and_the_one_before(tmp_path, group):
    """A full disk mid-write (here the file size limit, which fails a write the same way) left a zero-byte
    checkpoint.tmp behind, which the docs promise never to leave."""
    if group and checkpoint._SYNCFS is None:
        pytest.skip("this system has no syncfs: the group commit falls back to run by run")
    setups, first = states(2)
    outs = [tmp_path / str(k) for k in range(2)]
    for out in outs:
        out.mkdir()
    save_checkpoints(outs, first, [Log(), Log()])
    before = [(out / CHECKPOINT).read_bytes() for out in outs]
    second = [step(setup, state)[0] for setup, state in zip(setups, first)]
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails (EFBIG) instead of the process
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (len(before[0]) // 2, hard))
    try:
        errors = save_checkpoints(outs if group else outs[:1], second if group else second[:1], [Log(), Log()])
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert errors and all(isinstance(error, OSError) for error in errors)
    for out, was in zip(outs, before):
        assert not (out / checkpoint.CHECKPOINT_TMP).exists()
        assert (out / CHECKPOINT).read_bytes() == was
