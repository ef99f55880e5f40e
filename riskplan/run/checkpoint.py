"""Checkpoints: what resume needs (the next iteration, every robot's theta, the Mixer's state), written atomically
and read back only after every check that it can be this run's."""

from __future__ import annotations

import json
import math
import os
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from riskplan.run.build import Setup, logit_bound
from riskplan.util.errors import BadInput

CHECKPOINT = "checkpoint"
CRASH_ENV = "RISKPLAN_TEST_KILL_IN_CHECKPOINT"  # fault injection for the crash-safety tests


@dataclass
class State:
    """What a checkpoint holds: the next iteration, every robot's theta, the mixer's buffers, the rows so far."""

    iteration: int
    thetas: np.ndarray  # (N, M)
    mixer: dict
    rows: list[dict]


def save_checkpoint(out: Path, state: State) -> None:
    """Write the checkpoint atomically: temp file, fsync, rename, fsync the directory."""
    tmp = out / f"{CHECKPOINT}.tmp"
    payload = {
        "iteration": state.iteration,
        "thetas": state.thetas.tolist(),
        "mixer": {k: np.asarray(v).tolist() for k, v in state.mixer.items()},
        "mixer_dtypes": {k: str(np.asarray(v).dtype) for k, v in state.mixer.items()},
    }
    with open(tmp, "w") as handle:
        json.dump(payload, handle)
        handle.flush()
        os.fsync(handle.fileno())
    if os.environ.get(CRASH_ENV) == str(state.iteration):
        os.kill(os.getpid(), signal.SIGKILL)
    os.replace(tmp, out / CHECKPOINT)
    directory = os.open(out, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def load_checkpoint(out: Path, setup: Setup) -> State:
    """The last good checkpoint of a run directory (a half-written temp file is ignored), checked against the
    config: a checkpoint that cannot be this run's is bad input, never a run that continues."""
    path = out / CHECKPOINT
    if not path.exists():
        raise BadInput(str(out), "has no checkpoint to resume from; start it again with riskplan train")
    try:
        payload = json.loads(path.read_text())
        thetas = np.array(payload["thetas"], dtype=float)
        mixer = {k: np.array(v, dtype=np.dtype(payload["mixer_dtypes"][k])) for k, v in payload["mixer"].items()}
        iteration = payload["iteration"]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise BadInput(
            str(path),
            f"is damaged ({type(err).__name__}: {err}); it was not written by riskplan, "
            f"which replaces checkpoints atomically: start the run again",
        ) from None
    if type(iteration) is not int or iteration < 1:
        raise BadInput(
            str(path),
            f"holds iteration {iteration!r}; a checkpoint is written after iteration 1 or later: start the run again",
        )
    if thetas.shape != (setup.robots, setup.world.sources):
        raise BadInput(
            str(out),
            f"checkpoint holds {thetas.shape} thetas, the config needs "
            f"{(setup.robots, setup.world.sources)}; only train.iterations may change on resume",
        )
    if not (np.all(np.isfinite(thetas)) and math.isfinite(logit_bound(setup.world, thetas))):
        raise BadInput(str(path), "holds a theta that is not finite (or overflows the softmax); start the run again")
    expected = setup.mixer.state()
    for key, value in mixer.items():
        if (
            key not in expected
            or value.shape != expected[key].shape
            or (value.dtype.kind == "f" and not np.all(np.isfinite(value)))
        ):
            raise BadInput(
                str(path),
                f"holds a consensus state '{key}' that does not fit this team (or is not finite); start the run again",
            )
    if set(mixer) != set(expected):
        raise BadInput(str(path), "lacks part of the consensus state of this team; start the run again")
    if iteration > setup.params.train.iterations:
        raise BadInput(
            "train.iterations",
            f"got {setup.params.train.iterations}, but {out} is checkpointed "
            f"at iteration {iteration}; a resumed run can only be extended: give "
            f"train.iterations >= {iteration}",
        )
    return State(iteration, thetas, mixer, [])
