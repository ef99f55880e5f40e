"""Checkpoints: what resume needs (the next iteration, every robot's theta, the Mixer's state), written atomically
and read back only after every check that it can be this run's."""

from __future__ import annotations

import contextlib
import ctypes
import json
import math
import os
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from riskplan.config.keys import KEYS
from riskplan.engine.step import RunSetup, TrainState, logit_bound
from riskplan.run.run_files import CHECKPOINT, CHECKPOINT_TMP
from riskplan.util.errors import BadInput

CRASH_ENV = "RISKPLAN_TEST_KILL_IN_CHECKPOINT"  # fault injection for the crash-safety tests
RESUME = f"only {KEYS.train.iterations} may change on resume"  # what a checkpoint that is not this run's says
T = TypeVar("T")


def _write_durably(out: Path, payload: dict) -> None:
    """The checkpoint file replaced atomically: temp file, fsync, rename, fsync the directory (CRASH_ENV: SIGKILL
    before the rename at that iteration, for the tests)."""
    _write_temp(out, payload, durable=True)
    _crash_point(payload["iteration"])
    os.replace(out / CHECKPOINT_TMP, out / CHECKPOINT)
    directory = os.open(out, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def save_checkpoint(out: Path, state: TrainState) -> None:
    """Write the checkpoint atomically: temp file, fsync, rename, fsync the directory."""
    _write_durably(out, _payload(state))


def save_checkpoints(outs: list[Path], states: list[TrainState], logs: list) -> list[Exception | None]:
    """Many runs' checkpoints, each after its run.mcap, as one group commit (a batch's round): every temp file
    written, one sync of each file system they lie on (the logs, already written to the system at each iteration's
    end, and the temp files become durable together), every rename, one more sync. Two syncs per file system
    instead of three fsyncs per run. Where the system cannot sync a file system alone (syncfs is Linux's): each
    run's log.sync() and save_checkpoint in turn. Each run's error, or None; a run whose files fail keeps its
    checkpoint before."""
    if _SYNCFS is None or len(outs) < 2:
        return [
            _attempt(lambda out=out, state=state, log=log: (log.sync(), save_checkpoint(out, state)))
            for out, state, log in zip(outs, states, logs)
        ]
    errors = [
        _attempt(lambda out=out, state=state: _write_temp(out, _payload(state))) for out, state in zip(outs, states)
    ]
    written = [k for k, error in enumerate(errors) if error is None]
    try:
        sync_file_systems([outs[k] for k in written])
    except OSError as err:  # not durable: no temp file is renamed, nor left behind
        for k in written:
            (outs[k] / CHECKPOINT_TMP).unlink(missing_ok=True)
            errors[k] = err
        return errors
    for k in written:
        _crash_point(states[k].iteration)
        errors[k] = _attempt(lambda k=k: os.replace(outs[k] / CHECKPOINT_TMP, outs[k] / CHECKPOINT))
    sync_file_systems([outs[k] for k, error in enumerate(errors) if error is None])
    return errors


def _payload(state: TrainState) -> dict:
    return {
        "iteration": state.iteration,
        "thetas": state.thetas.tolist(),
        "mixer": {k: np.asarray(v).tolist() for k, v in state.mixer.items()},
        "mixer_dtypes": {k: str(np.asarray(v).dtype) for k, v in state.mixer.items()},
    }


def _write_temp(out: Path, payload: dict, durable: bool = False) -> None:
    """The checkpoint's temp file, written to the system (synced by the caller, or here when `durable`); one that
    could not be written whole (a full disk) is removed, and the previous checkpoint stays the run's."""
    tmp = out / CHECKPOINT_TMP
    try:
        with open(tmp, "w") as handle:
            handle.write(_text(payload))
            if durable:
                handle.flush()
                os.fsync(handle.fileno())
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _text(payload: dict) -> str:
    """The checkpoint's JSON in one piece: json.dumps takes the C encoder, json.dump the pure-Python one, which
    spent a millisecond on a team's checkpoint (its messages in flight); the same text."""
    return json.dumps(payload)


def _crash_point(iteration: int) -> None:
    """CRASH_ENV: SIGKILL once checkpoint `iteration`'s temp file is durable, before its rename (for the tests)."""
    if os.environ.get(CRASH_ENV) == str(iteration):
        os.kill(os.getpid(), signal.SIGKILL)


def sync_file_systems(folders: list[Path]) -> None:
    """syncfs once for each file system the folders lie on: everything written to it so far becomes durable."""
    seen: set[int] = set()
    for folder in folders:
        fd = os.open(folder, os.O_RDONLY)
        try:
            device = os.fstat(fd).st_dev
            if device not in seen:
                seen.add(device)
                if _SYNCFS(fd) != 0:
                    raise OSError(ctypes.get_errno(), f"{folder}: syncfs failed")
        finally:
            os.close(fd)


def can_sync_file_systems() -> bool:
    """Whether this system syncs a file system alone (syncfs, Linux): a group commit's way to durability."""
    return _SYNCFS is not None


def _libc_syncfs():
    """libc's syncfs (Linux), or None where there is none."""
    try:
        return ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):
        return None


_SYNCFS = _libc_syncfs()


def _attempt(work) -> Exception | None:
    """work(); the Exception that stopped it (this run alone: a full or read-only disk), or None."""
    try:
        work()
    except Exception as err:
        return err
    return None


def load_checkpoint(out: Path, setup: RunSetup) -> TrainState:
    """The last good checkpoint of a run directory (a half-written temp file is ignored), checked against the
    config: a checkpoint that cannot be this run's is bad input, never a run that continues."""
    path, (iteration, thetas, mixer) = _read(out, _arrays)
    if type(iteration) is not int or iteration < 1:
        raise BadInput(
            str(path),
            f"holds iteration {iteration!r}; a checkpoint is written after iteration 1 or later: start the run again",
        )
    if thetas.shape != (setup.robots, len(setup.theta0)):
        raise BadInput(
            str(out),
            f"checkpoint holds {thetas.shape} thetas, the config needs {(setup.robots, len(setup.theta0))}; {RESUME}",
        )
    if not (np.all(np.isfinite(thetas)) and math.isfinite(logit_bound(setup.world, thetas, setup.policy))):
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
    _check_extendable(out, setup, iteration)
    return TrainState(iteration, thetas, mixer)


def _arrays(path: Path, payload: dict) -> tuple[object, np.ndarray, dict[str, np.ndarray]]:
    """(iteration, thetas, the Mixer's state) of a checkpoint's JSON."""
    thetas = np.array(payload["thetas"], dtype=float)
    mixer = {k: np.array(v, dtype=np.dtype(payload["mixer_dtypes"][k])) for k, v in payload["mixer"].items()}
    return payload["iteration"], thetas, mixer


def _read(out: Path, parse: Callable[[Path, dict], T]) -> tuple[Path, T]:
    """(the checkpoint's path, parse(path, its JSON)), for either kind of checkpoint: no file, or one that does not
    parse (a missing key, a wrong type), is bad input naming it."""
    path = out / CHECKPOINT
    if not path.exists():
        raise BadInput(str(out), "has no checkpoint to resume from; start it again with riskplan train")
    try:
        return path, parse(path, json.loads(path.read_text()))
    except BadInput:  # a ValueError too, and already the line to show
        raise
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise BadInput(
            str(path),
            f"is damaged ({type(err).__name__}: {err}); it was not written by riskplan, "
            f"which replaces checkpoints atomically: start the run again",
        ) from None


def _check_extendable(out: Path, setup: RunSetup, iteration: int) -> None:
    """Bad input unless train.iterations reaches the checkpoint's `iteration`: a resumed run can only be extended."""
    if iteration > setup.params.train.iterations:
        raise BadInput(
            KEYS.train.iterations,
            f"got {setup.params.train.iterations}, but {out} is checkpointed "
            f"at iteration {iteration}; a resumed run can only be extended: give "
            f"{KEYS.train.iterations} >= {iteration}",
        )


# --- team.backend=ray: one checkpoint per robot, each at its own iteration (riskplan.run.ray_team) ---------------

TEAM_FORMAT = "ray"  # the "format" of a checkpoint that holds per-robot states


@dataclass
class TeamCheckpoint:
    """Per-robot checkpoints of a team whose robots run apart (team.backend=ray): robot i's state at its own
    iteration (robots[i]["iteration"], the next one it runs: its theta, what it holds from its neighbours, its
    gradient-tracking sums), taken together as a consistent cut (no robot holds a message its sender had not sent
    by its own checkpoint), and `pending`: the rows of the iterations some robot has not finished yet, with what
    their network-average row needs (each an {"row": dict, "z": (W,), "grad": (M,)})."""

    robots: list[dict[str, np.ndarray]]
    pending: list[dict]

    @property
    def iterations(self) -> list[int]:
        """Each robot's next iteration."""
        return [int(state["iteration"]) for state in self.robots]

    @property
    def iteration(self) -> int:
        """The iteration every robot has reached: the team's (its metrics are complete before it)."""
        return min(self.iterations)


def save_team_checkpoint(out: Path, robots: list[dict[str, np.ndarray]], pending: list[dict]) -> None:
    """Write every robot's checkpoint, and the pending rows, as one file replaced atomically (temp file, fsync,
    rename, fsync the directory), so the robots' states on disk are always one consistent cut."""
    payload = {
        "format": TEAM_FORMAT,
        "iteration": min(int(state["iteration"]) for state in robots),
        "robots": [
            {
                "arrays": {k: np.asarray(v).tolist() for k, v in state.items()},
                "dtypes": {k: str(np.asarray(v).dtype) for k, v in state.items()},
                "shapes": {k: list(np.shape(v)) for k, v in state.items()},
            }
            for state in robots
        ],
        "pending": [
            {"row": entry["row"], "z": np.asarray(entry["z"]).tolist(), "grad": np.asarray(entry["grad"]).tolist()}
            for entry in pending
        ],
    }
    _write_durably(out, payload)


def load_team_checkpoint(out: Path, setup: RunSetup, expected: list[dict[str, np.ndarray]]) -> TeamCheckpoint:
    """The per-robot checkpoints of a run directory, checked against `expected` (each robot's state before its
    first iteration: the names, shapes and dtypes a checkpoint of this team must have) and the config; anything
    that cannot be this run's is bad input."""
    path, checkpoint = _read(out, _team_arrays)
    if len(checkpoint.robots) != len(expected):
        raise BadInput(
            str(out),
            f"checkpoint holds {len(checkpoint.robots)} robots, the config has {len(expected)}; {RESUME}",
        )
    for i, (state, want) in enumerate(zip(checkpoint.robots, expected)):
        _check_robot(path, setup, i, state, want)
    if min(checkpoint.iterations) < 0:
        raise BadInput(str(path), "holds a negative iteration; start the run again")
    _check_extendable(out, setup, max(checkpoint.iterations))
    return checkpoint


def _team_arrays(path: Path, payload: dict) -> TeamCheckpoint:
    """The robots' states and the pending rows of a team checkpoint's JSON; a simulated run's is bad input."""
    if payload.get("format") != TEAM_FORMAT:
        raise BadInput(
            str(path),
            f"holds the checkpoint of a {KEYS.team.backend}=simulated run; resume it with the config it was "
            f"started with ({RESUME})",
        )
    robots = [
        {
            k: np.array(v, dtype=np.dtype(entry["dtypes"][k])).reshape(entry["shapes"][k])
            for k, v in entry["arrays"].items()
        }
        for entry in payload["robots"]
    ]
    pending = [
        {"row": dict(p["row"]), "z": np.array(p["z"], dtype=float), "grad": np.array(p["grad"], dtype=float)}
        for p in payload["pending"]
    ]
    return TeamCheckpoint(robots, pending)


def _check_robot(path: Path, setup: RunSetup, i: int, state: dict[str, np.ndarray], want: dict) -> None:
    """Robot i's checkpointed state has `want`'s names, shapes and dtypes, finite floats, and a usable theta."""
    if set(state) != set(want):
        raise BadInput(str(path), f"robot {i}'s checkpoint does not fit this team; start the run again")
    for key, value in state.items():
        if (
            value.shape != np.shape(want[key])
            or value.dtype != np.asarray(want[key]).dtype
            or (value.dtype.kind == "f" and not np.all(np.isfinite(value)))
        ):
            raise BadInput(
                str(path),
                f"robot {i}'s checkpoint holds a '{key}' that does not fit this team (or is not finite); "
                f"start the run again",
            )
    if not math.isfinite(logit_bound(setup.world, state["theta"][None], setup.policy)):
        raise BadInput(str(path), f"robot {i}'s theta overflows the softmax; start the run again")
